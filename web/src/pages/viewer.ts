// The job's image: a canvas showing one layer of the progressive preview, refreshed as samples
// are merged (at most one request in flight, at most two a second), with exposure for the image,
// false colour for the error/spp/variance maps and an SVG overlay of the tile grid. Of an
// animation it shows one frame at a time (setFrame); the images of finished frames, which no
// longer change, are kept decoded so that scrubbing back over them fetches nothing.

import { frameImageUrl, imageUrl, pixelMattes } from "../api";
import type { operations } from "../generated/openapi";
import { applyColourMap, applyExposure, type ColourMap, cssGradient } from "../colormap";
import { h, s, setText } from "../dom";
import { BudgetCache } from "../frames";
import { layerScale, matteText, pngText, type Scale, scaleValue } from "../outputs";
import { Throttled } from "../throttle";

/** A layer of a job's images: one of the server's channel table (domain/channels.py), as the
 * REST API's `layer` parameter lists them. */
export type LayerName = NonNullable<
  NonNullable<operations["image_api_v1_jobs__job_id__image__fmt__get"]["parameters"]["query"]>["layer"]
>;

interface Layer {
  // The layer's name, or for one light group `light_group.<group>` (the PNG of layer
  // light_group with that group).
  id: string;
  label: string;
  colourMap?: ColourMap;
  legend?: string;
  // What a job needs for the layer (the server refuses it otherwise): settings.denoise, or
  // settings.aovs naming an output.
  needs?: { denoise: true } | { aov: string };
}

/** The settings that decide which layers a job has. */
export interface LayerSettings {
  denoise?: boolean;
  aovs?: string;
  // The job's light groups (settings.light_groups): a JSON object of group name -> nodes.
  light_groups?: string;
}

// Longest side of the preview images (`max_size` of image.png): beyond a 4K screen's width.
const PREVIEW_MAX_SIZE = 2048;

// How each layer is shown, in the switch's order: an entry for every layer of the table and no
// other (the type check fails otherwise, so a layer added on the server must be added here).
const LAYER_VIEWS: Record<LayerName, Omit<Layer, "id">> = {
  rgb: { label: "Image" },
  error: { label: "Relative error", colourMap: "inferno", legend: "per-pixel relative error" },
  spp: { label: "Samples / pixel", colourMap: "viridis", legend: "samples per pixel" },
  variance: { label: "Std. error", colourMap: "inferno", legend: "standard error of the mean" },
  albedo: { label: "Albedo" },
  normal: { label: "Normal" },
  depth: { label: "Depth", colourMap: "viridis", legend: "depth along the viewing axis", needs: { aov: "depth" } },
  position: { label: "Position", needs: { aov: "position" } },
  motion: { label: "Motion", needs: { aov: "motion" } },
  instance: { label: "Instance", needs: { aov: "ids" } },
  material: { label: "Material", needs: { aov: "ids" } },
  crypto_object: { label: "Crypto object", needs: { aov: "cryptomatte" } },
  crypto_material: { label: "Crypto material", needs: { aov: "cryptomatte" } },
  crypto_asset: { label: "Crypto asset", needs: { aov: "cryptomatte" } },
  diffuse_direct: { label: "Diffuse direct", needs: { aov: "lobes" } },
  diffuse_indirect: { label: "Diffuse indirect", needs: { aov: "lobes" } },
  glossy_direct: { label: "Glossy direct", needs: { aov: "lobes" } },
  glossy_indirect: { label: "Glossy indirect", needs: { aov: "lobes" } },
  transmission_direct: { label: "Transmission direct", needs: { aov: "lobes" } },
  transmission_indirect: { label: "Transmission indirect", needs: { aov: "lobes" } },
  emission: { label: "Emission", needs: { aov: "lobes" } },
  background: { label: "Background", needs: { aov: "lobes" } },
  light_group: { label: "Light group", needs: { aov: "light_groups" } },
  denoised: { label: "Denoised", needs: { denoise: true } },
};

export const LAYERS: Layer[] = (Object.keys(LAYER_VIEWS) as LayerName[]).map((id) => ({ id, ...LAYER_VIEWS[id] }));

const GROUP_PREFIX = "light_group.";

/** The light groups of a job's settings, in their layers' order. */
function lightGroups(settings: LayerSettings): string[] {
  try {
    return Object.keys(JSON.parse(settings.light_groups || "{}") as Record<string, number[]>);
  } catch {
    return [];
  }
}

/** The layers a job with these settings has, in the switch's order: the light_group layer is
 *  one entry per group. */
export function jobLayers(settings: LayerSettings): Layer[] {
  const aovs = new Set((settings.aovs ?? "").split(",").map((a) => a.trim()));
  return LAYERS.filter((l) => {
    if (!l.needs) return true;
    return "denoise" in l.needs ? settings.denoise === true : aovs.has(l.needs.aov);
  }).flatMap((l) =>
    l.id === "light_group"
      ? lightGroups(settings).map((g) => ({ ...l, id: GROUP_PREFIX + g, label: `Light ${g}` }))
      : [l],
  );
}

/** The label of a light group's layer (null for others). */
function jobLayerLabel(id: string): string | null {
  return id.startsWith(GROUP_PREFIX) ? `light ${id.slice(GROUP_PREFIX.length)}` : null;
}

/** How a layer of the switch is shown (a light group's: as the light_group layer). */
function layerView(id: string): Layer {
  const base = id.startsWith(GROUP_PREFIX) ? "light_group" : id;
  return LAYERS.find((l) => l.id === base)!;
}

/** The query of a layer of the switch: `layer=...`, and a light group's `group=...`. */
export function layerQuery(id: string): { layer: string; group: string } {
  return id.startsWith(GROUP_PREFIX)
    ? { layer: "light_group", group: id.slice(GROUP_PREFIX.length) }
    : { layer: id, group: "" };
}

/** Whether a job's settings turn Cryptomatte on (the viewer then names what is under the
 *  pointer). */
export function hasCryptomatte(settings: LayerSettings): boolean {
  return (settings.aovs ?? "").split(",").some((a) => a.trim() === "cryptomatte");
}

/** Layers shown with exposure: the radiance ones (the image, its lobes and light groups). */
const RADIANCE = new Set([
  "rgb", "denoised", "diffuse_direct", "diffuse_indirect", "glossy_direct", "glossy_indirect",
  "transmission_direct", "transmission_indirect", "emission", "background", "light_group",
]);
const isRadiance = (id: string) => RADIANCE.has(layerQuery(id).layer);

/** Decoded images of finished frames kept for scrubbing: at most this many bytes of RGBA. */
const FRAME_CACHE_BYTES = 192 << 20;

interface Loaded {
  url: string;
  raw: ImageData;
  scale: Scale | null;
  caption: string;
}

export class Viewer {
  readonly el: HTMLElement;
  private canvas: HTMLCanvasElement;
  private overlay: SVGSVGElement;
  private stage: HTMLDivElement;
  private legend: HTMLDivElement;
  private exposureBox: HTMLDivElement;
  private exposure: HTMLInputElement;
  private exposureOut: HTMLOutputElement;
  private gridToggle: HTMLInputElement;
  private caption: HTMLParagraphElement;
  // With Cryptomatte (settings.aovs naming cryptomatte): what is under the pointer.
  private pointerLine: HTMLParagraphElement | null = null;
  private pointerAt: { x: number; y: number } | null = null;
  private pointerBusy = false;
  private layer = "rgb";
  private raw: ImageData | null = null;
  private rawLayer = "";
  private version = -1; // samples_merged the wanted image reflects
  private loadedKey = "";
  private loader: Throttled;
  private converged = new Set<number>();
  private tiles = { width: 0, height: 0, size: 1 };
  // The frame of an animation shown (null: a still, image.png) and, once that frame has
  // finished, a key of its final image (which then no longer follows samples_merged).
  private frame: number | null = null;
  private finalKey: string | null = null;
  private frameCache = new BudgetCache<string, Loaded>(FRAME_CACHE_BYTES, (l) => l.raw.data.byteLength);

  constructor(
    private readonly jobId: string,
    width: number,
    height: number,
    tileSize: number,
    settings: LayerSettings = {},
  ) {
    this.tiles = { width, height, size: tileSize };
    this.canvas = h("canvas", { width, height, class: "preview", "aria-label": "Preview of the render", role: "img" });
    this.overlay = s("svg", {
      class: "tile-overlay",
      viewBox: `0 0 ${width} ${height}`,
      preserveAspectRatio: "none",
      "aria-hidden": "true",
    });
    this.stage = h("div", { class: "stage" }, this.canvas, this.overlay);
    this.stage.style.aspectRatio = `${width} / ${height}`;
    this.stage.style.maxWidth = `calc(68vh * ${width / height})`;

    const radios = jobLayers(settings).map((l) =>
      h(
        "label",
        { class: "seg-option" },
        h("input", {
          type: "radio",
          name: "layer",
          value: l.id,
          checked: l.id === this.layer,
          onchange: () => this.setLayer(l.id),
        }),
        h("span", {}, l.label),
      ),
    );
    this.exposure = h("input", {
      type: "range",
      id: "exposure",
      min: -4,
      max: 4,
      step: 0.25,
      value: "0",
      "aria-describedby": "exposure-note",
      oninput: () => this.exposureChanged(),
    });
    this.exposureOut = h("output", { for: "exposure", class: "mono" }, "+0.00 EV");
    this.exposureBox = h(
      "div",
      { class: "control" },
      h("label", { for: "exposure" }, "Exposure"),
      this.exposure,
      this.exposureOut,
      h("button", {
        type: "button",
        class: "button small secondary",
        onclick: () => {
          this.exposure.value = "0";
          this.exposureChanged();
        },
      }, "Reset"),
    );
    this.gridToggle = h("input", { type: "checkbox", id: "tile-grid", onchange: () => this.drawOverlay() });
    this.legend = h("div", { class: "legend-bar", hidden: true });
    this.caption = h("p", { class: "muted small viewer-caption", "aria-live": "off" });
    if (hasCryptomatte(settings)) {
      this.pointerLine = h("p", { class: "small mono viewer-pointer", "aria-live": "polite" });
      this.canvas.addEventListener("pointermove", (e) => this.pointerMoved(e));
      this.canvas.addEventListener("pointerleave", () => {
        this.pointerAt = null;
        setText(this.pointerLine!, "");
      });
    }

    this.el = h(
      "section",
      { class: "card viewer", "aria-label": "Image" },
      h(
        "div",
        { class: "viewer-toolbar" },
        h("fieldset", { class: "segmented radio" }, h("legend", { class: "visually-hidden" }, "Layer"), radios),
        h("div", { class: "viewer-controls" },
          this.exposureBox,
          h("div", { class: "control" }, this.gridToggle, h("label", { for: "tile-grid" }, "Tile grid")),
        ),
      ),
      h("div", { class: "stage-wrap" }, this.stage),
      h("div", { class: "viewer-foot" }, this.legend, this.caption),
      ...(this.pointerLine ? [this.pointerLine] : []),
      h("p", { class: "muted small", id: "exposure-note" },
        "Exposure scales the linear radiance of the sRGB preview (clamped to 1 by the server); the EXR keeps the full range."),
    );
    this.loader = new Throttled(() => this.load(), 500);
  }

  /** The pixel under the pointer, named from the job's Cryptomatte: one request in flight,
   *  the latest position asked for when it returns. */
  private pointerMoved(e: PointerEvent): void {
    const r = this.canvas.getBoundingClientRect();
    const x = Math.floor(((e.clientX - r.left) / r.width) * this.tiles.width);
    const y = Math.floor(((e.clientY - r.top) / r.height) * this.tiles.height);
    if (x < 0 || y < 0 || x >= this.tiles.width || y >= this.tiles.height) return;
    this.pointerAt = { x, y };
    if (!this.pointerBusy) void this.askPointer();
  }

  private async askPointer(): Promise<void> {
    const at = this.pointerAt;
    if (!at || !this.pointerLine) return;
    this.pointerBusy = true;
    try {
      const m = await pixelMattes(this.jobId, this.frame ?? 0, at.x, at.y);
      if (this.pointerAt) setText(this.pointerLine, `(${m.x}, ${m.y}) ${matteText(m)}`);
    } catch {
      // no samples yet, or the job went away: say nothing
    } finally {
      this.pointerBusy = false;
    }
    const now = this.pointerAt;
    if (now && (now.x !== at.x || now.y !== at.y)) void this.askPointer();
  }

  /** New samples were merged: fetch the preview again (throttled). */
  update(samplesMerged: number): void {
    if (samplesMerged === this.version) return;
    this.version = samplesMerged;
    this.loader.request();
  }

  async final(samplesMerged: number): Promise<void> {
    this.version = samplesMerged;
    await this.loader.flush();
  }

  /**
   * Shows `frame` of an animation; `finalKey` names its final image once it has finished (its
   * mean spp, say: a job carried on to more samples renders it again), null while it renders.
   * A finished frame seen before is painted at once from memory; others are fetched (throttled,
   * so scrubbing asks for the frame the user stops at, not for every one passed).
   */
  setFrame(frame: number, finalKey: string | null): void {
    if (frame === this.frame && finalKey === this.finalKey) return;
    this.frame = frame;
    this.finalKey = finalKey;
    if (this.fromCache()) return;
    this.loader.request();
  }

  setConverged(tiles: Iterable<number>): void {
    const next = new Set(tiles);
    if (next.size === this.converged.size && [...next].every((t) => this.converged.has(t))) return;
    this.converged = next;
    this.drawOverlay();
  }

  stop(): void {
    this.loader.stop();
  }

  private setLayer(id: string): void {
    this.layer = id;
    this.el.dataset.layer = id;
    const layer = layerView(id);
    this.exposureBox.hidden = !isRadiance(id);
    this.legend.hidden = !layer.colourMap;
    this.drawLegend(null);
    if (this.fromCache()) return;
    void this.loader.flush();
  }

  /** The key of the image wanted now: layer and version, of a frame also the frame. */
  private wantedKey(): string {
    if (this.frame === null) return `${this.layer}:${this.version}`;
    return `${this.layer}:${this.finalKey ?? this.version}@${this.frame}`;
  }

  /** Paints a finished frame's image from memory when it is there. */
  private fromCache(): boolean {
    if (this.frame === null || this.finalKey === null) return false;
    const key = this.wantedKey();
    const hit = this.frameCache.get(key);
    if (!hit) return false;
    this.show(this.layer, key, this.frame, hit);
    return true;
  }

  /** The colour bar of a heat map with the values of its ends: the scale the server recorded
   *  in the PNG (black 0, white the layer's maximum), "max" until one is loaded. */
  private drawLegend(scale: Scale | null): void {
    const layer = layerView(this.layer);
    if (!layer.colourMap) return;
    const low = scale ? scaleValue(layer.id, scale.min) : "0";
    const high = scale ? scaleValue(layer.id, scale.max) : "max";
    this.legend.dataset.max = scale ? String(scale.max) : "";
    this.legend.replaceChildren(
      h("span", { class: "legend-min mono" }, low),
      h("span", {
        class: "legend-gradient",
        style: `background: ${cssGradient(layer.colourMap)}`,
        title: "unknown values (no samples yet) show as the top of the scale",
      }),
      h("span", { class: "legend-max mono" }, high),
      h("span", {}, `· ${layer.legend}`),
    );
  }

  private exposureChanged(): void {
    const ev = Number(this.exposure.value);
    setText(this.exposureOut, `${ev >= 0 ? "+" : "−"}${Math.abs(ev).toFixed(2)} EV`);
    this.paint();
  }

  private async load(): Promise<void> {
    const layer = this.layer;
    const version = this.version;
    const frame = this.frame;
    const finalKey = this.finalKey;
    const key = this.wantedKey();
    if (key === this.loadedKey) return;
    // A preview no larger than the screen shows: a large render's full-resolution PNG takes
    // the server seconds to encode (the Download buttons still fetch it).
    const query = layerQuery(layer);
    const base =
      (frame === null ? imageUrl(this.jobId, "png", query.layer) : frameImageUrl(this.jobId, frame, "png", query.layer)) +
      (query.group ? `&group=${encodeURIComponent(query.group)}` : "");
    const url = `${base}&max_size=${PREVIEW_MAX_SIZE}&v=${encodeURIComponent(finalKey ?? version)}`;
    const response = await fetch(url);
    if (!response.ok) return; // e.g. no samples merged yet; the next update tries again
    const blob = await response.blob();
    // The scale is in the PNG's tEXt chunks, ahead of the image data.
    const scale = layerScale(pngText(new Uint8Array(await blob.slice(0, 1 << 16).arrayBuffer())));
    const bitmap = await createImageBitmap(blob);
    const work = document.createElement("canvas");
    work.width = bitmap.width;
    work.height = bitmap.height;
    const ctx = work.getContext("2d", { willReadFrequently: true })!;
    ctx.drawImage(bitmap, 0, 0);
    bitmap.close();
    const name = (jobLayerLabel(layer) ?? layerView(layer).label).toLowerCase();
    const size = `${work.width}×${work.height}`;
    const loaded: Loaded = {
      url,
      raw: ctx.getImageData(0, 0, work.width, work.height),
      scale,
      caption:
        frame === null
          ? `${size} · ${name} at ${version.toLocaleString("en")} samples merged`
          : `frame ${frame} · ${size} · ${name}` + (finalKey === null ? ` at ${version.toLocaleString("en")} samples merged` : ", finished"),
    };
    if (frame !== null && finalKey !== null) this.frameCache.set(key, loaded);
    if (frame !== this.frame) {
      this.loader.request(); // another frame was chosen meanwhile: that one next
      return;
    }
    this.show(layer, key, frame, loaded);
  }

  private show(layer: string, key: string, frame: number | null, loaded: Loaded): void {
    this.raw = loaded.raw;
    this.rawLayer = layer;
    this.loadedKey = key;
    if (layer === this.layer) this.drawLegend(loaded.scale);
    this.paint();
    this.el.dataset.loaded = key; // lets tests wait for a given layer and version
    this.canvas.dataset.src = loaded.url; // the image shown
    if (frame !== null) {
      this.el.dataset.frame = String(frame);
      this.canvas.setAttribute("aria-label", `Preview of frame ${frame} of the render`);
    }
    setText(this.caption, loaded.caption);
  }

  private paint(): void {
    if (!this.raw) return;
    const layer = layerView(this.rawLayer);
    let img = this.raw;
    if (layer.colourMap) img = applyColourMap(img, layer.colourMap);
    else if (isRadiance(this.rawLayer) && Number(this.exposure.value) !== 0) img = applyExposure(img, Number(this.exposure.value));
    if (this.canvas.width !== img.width || this.canvas.height !== img.height) {
      this.canvas.width = img.width;
      this.canvas.height = img.height;
    }
    this.canvas.getContext("2d")!.putImageData(img, 0, 0);
  }

  private drawOverlay(): void {
    this.overlay.replaceChildren();
    this.stage.classList.toggle("grid-on", this.gridToggle.checked);
    if (!this.gridToggle.checked) return;
    const { width, height, size } = this.tiles;
    const cols = Math.ceil(width / size);
    const rows = Math.ceil(height / size);
    for (let r = 0; r < rows; r++) {
      for (let c = 0; c < cols; c++) {
        const index = r * cols + c;
        const w = Math.min(size, width - c * size);
        const hgt = Math.min(size, height - r * size);
        const done = this.converged.has(index);
        this.overlay.append(
          s("rect", {
            x: c * size,
            y: r * size,
            width: w,
            height: hgt,
            class: done ? "tile converged" : "tile",
            "vector-effect": "non-scaling-stroke",
            "data-tile": index,
          }),
        );
      }
    }
  }
}
