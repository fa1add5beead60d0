// Submit page: a scene dropped or chosen, a name, and a settings form built from the server's
// own list of settings (GET /api/v1/settings). Validation is the server's: a 400 names the
// offending field and its message is shown beside that field.

import { ApiError, type SettingDoc, settings as fetchSettings, submitJob } from "../api";
import { h, replace, setText } from "../dom";
import { fieldHead, fieldSetting } from "../fields";
import { bytes, label } from "../format";

const GROUPS: [string, string[]][] = [
  ["Image", ["width", "height", "tile_size"]],
  ["Light transport", ["integrator", "sampler", "max_depth", "seed"]],
  ["Convergence", ["noise_threshold", "min_spp", "max_spp", "time_limit_s"]],
  ["Scheduling", ["priority"]],
];

/** The values of an enumerated setting (GET /api/v1/settings lists them); null for others. */
function choices(doc: SettingDoc): string[] | null {
  const list = doc.choices ?? [];
  return list.length ? list : null;
}

interface Field {
  doc: SettingDoc;
  input: HTMLInputElement | HTMLSelectElement;
  message: HTMLElement;
  wrap: HTMLElement;
}

export function mountSubmit(root: HTMLElement): () => void {
  document.title = "Submit · renderfarm";
  let disposed = false;
  let scene: File | null = null;

  const fileInput = h("input", { type: "file", id: "scene-file", name: "scene", accept: ".glb,.gltf,.usd,.usda,.usdc,.usdz,.zip,.tar,.tgz", class: "visually-hidden", "aria-describedby": "scene-help scene-error" });
  const fileInfo = h("p", { class: "file-info", "aria-live": "polite" });
  const sceneError = h("p", { class: "field-error", id: "scene-error" });
  const drop = h(
    "label",
    { class: "dropzone", for: "scene-file", "data-testid": "dropzone" },
    fileInput,
    h("span", { class: "dropzone-title" }, "Drop a scene here"),
    h("span", { class: "muted", id: "scene-help" }, "or press to choose a file: .glb, a .gltf with every buffer and image embedded, a USD stage (.usd, .usda, .usdc, .usdz) or a .zip/.tar bundle of a scene and its files"),
    fileInfo,
  );
  const setScene = (file: File | null) => {
    scene = file;
    drop.classList.toggle("has-file", !!file);
    setText(fileInfo, file ? `${file.name} · ${bytes(file.size)}` : "");
    clearError("scene");
    if (file && !nameInput.value) nameInput.placeholder = file.name.replace(/\.(glb|gltf|usd|usda|usdc|usdz|zip|tar|tgz)$/i, "");
  };
  fileInput.addEventListener("change", () => setScene(fileInput.files?.[0] ?? null));
  drop.addEventListener("dragenter", (e) => {
    e.preventDefault();
    drop.classList.add("dragging");
  });
  drop.addEventListener("dragover", (e) => {
    e.preventDefault();
    if (e.dataTransfer) e.dataTransfer.dropEffect = "copy";
  });
  drop.addEventListener("dragleave", () => drop.classList.remove("dragging"));
  drop.addEventListener("drop", (e) => {
    e.preventDefault();
    drop.classList.remove("dragging");
    const file = e.dataTransfer?.files?.[0];
    if (file) setScene(file);
  });

  const nameInput = h("input", { type: "text", id: "job-name", name: "name", autocomplete: "off", "aria-describedby": "name-error" });
  const nameError = h("p", { class: "field-error", id: "name-error" });
  const formError = h("div", { class: "alert", role: "alert", hidden: true });
  const groups = h("div", { class: "settings-groups" }, h("p", { class: "muted" }, "Loading settings…"));
  const submitButton = h("button", { type: "submit", class: "button" }, "Submit job");
  const resetButton = h("button", { type: "button", class: "button secondary" }, "Reset to defaults");
  const fields = new Map<string, Field>();

  const clearError = (field: string) => {
    if (field === "scene") {
      setText(sceneError, "");
      drop.classList.remove("invalid");
    } else if (field === "name") {
      setText(nameError, "");
      nameInput.removeAttribute("aria-invalid");
    } else {
      const f = fields.get(field);
      if (f) {
        setText(f.message, "");
        f.input.removeAttribute("aria-invalid");
        f.wrap.classList.remove("invalid");
      }
    }
  };
  const clearAll = () => {
    clearError("scene");
    clearError("name");
    for (const k of fields.keys()) clearError(k);
    formError.hidden = true;
  };

  /** Puts the server's message beside the field it names; returns the element to focus. */
  const showError = (field: string, message: string): HTMLElement | null => {
    const head = fieldHead(field); // "scene" for a USD refusal's "scene:/World/Tex.inputs:file"
    if (head === "scene" || head === "scene_sha256") {
      setText(sceneError, message);
      drop.classList.add("invalid");
      return fileInput;
    }
    if (head === "name") {
      setText(nameError, message);
      nameInput.setAttribute("aria-invalid", "true");
      return nameInput;
    }
    const setting = head === "settings" ? fieldSetting(field) : head;
    const f = fields.get(setting);
    if (f) {
      setText(f.message, message);
      f.input.setAttribute("aria-invalid", "true");
      f.wrap.classList.add("invalid");
      return f.input;
    }
    formError.hidden = false;
    setText(formError, field ? `${field}: ${message}` : message);
    return null;
  };

  const buildFields = (all: SettingDoc[]) => {
    // Settings the server fills in itself (from the scene) are not the user's to choose.
    const docs = all.filter((d) => !d.derived);
    const known = new Set(GROUPS.flatMap(([, names]) => names));
    const byName = new Map(docs.map((d) => [d.name, d]));
    const groupList: [string, SettingDoc[]][] = GROUPS.map(([title, names]) => [
      title,
      names.map((n) => byName.get(n)).filter((d): d is SettingDoc => !!d),
    ]);
    const rest = docs.filter((d) => !known.has(d.name));
    if (rest.length) groupList.push(["More settings", rest]);
    const sections = groupList
      .filter(([, list]) => list.length)
      .map(([title, list]) => {
        const grid = h("div", { class: "field-grid" });
        for (const doc of list) {
          const id = `setting-${doc.name}`;
          const message = h("p", { class: "field-error", id: `${id}-error` });
          const options = choices(doc);
          let input: HTMLInputElement | HTMLSelectElement;
          const describedBy = `${id}-help ${id}-error`;
          if (doc.type === "bool") {
            // A true/false setting (denoise): a checkbox, sent only when changed.
            input = h("input", { id, name: doc.name, type: "checkbox", checked: doc.default === true, "aria-describedby": describedBy });
          } else if (options) {
            input = h("select", { id, name: doc.name, "aria-describedby": describedBy }, options.map((o) => h("option", { value: o }, o)));
            input.value = String(doc.default);
          } else {
            input = h("input", {
              id,
              name: doc.name,
              type: "text",
              inputmode: doc.type === "int" ? "numeric" : doc.type === "float" ? "decimal" : "text",
              autocomplete: "off",
              spellcheck: "false",
              value: String(doc.default ?? ""),
              "aria-describedby": describedBy,
            });
          }
          input.addEventListener("input", () => clearError(doc.name));
          const wrap = h(
            "div",
            { class: "field", "data-setting": doc.name },
            h("label", { for: id }, label(doc.name), " ", h("code", { class: "muted" }, doc.name)),
            input,
            h("p", { class: "field-help", id: `${id}-help` }, doc.help, doc.default !== "" ? ` (default ${String(doc.default)})` : ""),
            message,
          );
          fields.set(doc.name, { doc, input, message, wrap });
          grid.append(wrap);
        }
        return h("fieldset", { class: "settings-group" }, h("legend", {}, title), grid);
      });
    replace(groups, sections);
  };

  const values = (): Record<string, unknown> => {
    const out: Record<string, unknown> = {};
    for (const [name, f] of fields) {
      if (f.doc.type === "bool") {
        const checked = (f.input as HTMLInputElement).checked;
        if (checked !== (f.doc.default === true)) out[name] = checked;
        continue;
      }
      const text = f.input.value.trim();
      if (text === String(f.doc.default ?? "")) continue; // unchanged: the server's default applies
      if (f.doc.type === "int" && /^[-+]?\d+$/.test(text)) out[name] = parseInt(text, 10);
      else if (f.doc.type === "float" && text !== "" && Number.isFinite(Number(text))) out[name] = Number(text);
      else out[name] = text; // anything else goes as typed, and the server says what is wrong
    }
    return out;
  };

  const form = h(
    "form",
    { class: "submit-form", novalidate: true, "aria-label": "Submit a job" },
    h(
      "section",
      { class: "card" },
      h("h2", { class: "card-title" }, "Scene"),
      drop,
      sceneError,
      h("div", { class: "field name-field" }, h("label", { for: "job-name" }, "Job name"), nameInput, nameError),
    ),
    h("section", { class: "card" }, h("h2", { class: "card-title" }, "Settings"), groups),
    formError,
    h("div", { class: "form-actions" }, submitButton, resetButton),
  );

  resetButton.addEventListener("click", () => {
    for (const f of fields.values()) {
      if (f.doc.type === "bool") (f.input as HTMLInputElement).checked = f.doc.default === true;
      else f.input.value = String(f.doc.default ?? "");
    }
    clearAll();
  });

  form.addEventListener("submit", async (e) => {
    e.preventDefault();
    clearAll();
    if (!scene) {
      showError("scene", "Choose a scene file (.glb, self-contained .gltf, USD or a bundle) first.");
      fileInput.focus();
      return;
    }
    submitButton.disabled = true;
    setText(submitButton, "Uploading…");
    try {
      const job = await submitJob(scene, nameInput.value.trim() || nameInput.placeholder, values());
      if (!disposed) location.hash = `#/jobs/${job.id}`;
    } catch (err) {
      const focus =
        err instanceof ApiError ? showError(err.status === 413 && !err.field ? "scene" : err.field, err.message) : showError("", String(err));
      focus?.focus();
    } finally {
      submitButton.disabled = false;
      setText(submitButton, "Submit job");
    }
  });

  replace(root, h("div", { class: "page-head" }, h("h1", {}, "Submit a job")), form);
  fetchSettings()
    .then((docs) => {
      if (!disposed) buildFields(docs);
    })
    .catch((err) => replace(groups, h("div", { class: "alert", role: "alert" }, `Cannot load the settings: ${(err as Error).message}`)));

  return () => {
    disposed = true;
  };
}
