// Jobs list: every job with its live progress, filterable by state. Polls the list endpoint (one
// request every two seconds) and updates rows in place, so focus and selection survive updates.

import { ApiError, FINISHED, JOB_STATES, type Job, type JobState, listJobs } from "../api";
import { h, replace, setText } from "../dom";
import { dateTime, duration, spp } from "../format";
import { TileProgress, errorVsTarget, every, setConnection, stateBadge, updateBadge } from "../ui";

const PAGE = 50;

interface Row {
  tr: HTMLTableRowElement;
  update(job: Job): void;
}

function makeRow(job: Job): Row {
  const badge = stateBadge(job.state);
  const bar = new TileProgress(`Tiles converged of ${job.name || job.id}`);
  const meanSpp = h("td", { class: "num" });
  const error = h("span", { class: "error-vs-target" });
  const elapsed = h("td", { class: "num" });
  const eta = h("td", { class: "num" });
  const priority = h("td", { class: "num" });
  const owner = h("td", { class: "muted" });
  const tr = h(
    "tr",
    { "data-job-id": job.id },
    h(
      "td",
      { class: "job-name" },
      h("a", { href: `#/jobs/${job.id}` }, job.name || "(unnamed)"),
      h("div", { class: "mono muted small", title: `created ${dateTime(job.created_unix_s)}` }, job.id),
    ),
    owner,
    h("td", {}, badge),
    h("td", { class: "progress-cell" }, bar.el),
    meanSpp,
    h("td", { class: "num" }, error),
    elapsed,
    eta,
    priority,
  );
  const update = (j: Job) => {
    updateBadge(badge, j.state);
    // A waiting job names the jobs it waits for (submitted with `after`).
    badge.title = j.state === "waiting" && j.after?.length ? `waits for ${j.after.join(", ")}` : "";
    bar.update(j.progress, j.state);
    // `owner` arrives with auth tokens; until then the column shows "-".
    setText(owner, j.owner || "-");
    setText(meanSpp, `${spp(j.progress.mean_spp)} / ${j.settings.max_spp}`);
    errorVsTarget(error, j.progress.error, j.settings.noise_threshold);
    setText(elapsed, duration(j.progress.elapsed_s));
    setText(eta, FINISHED.has(j.state) ? "-" : duration(j.progress.eta_s));
    setText(priority, String(j.settings.priority));
  };
  update(job);
  return { tr, update };
}

export function mountJobs(root: HTMLElement, query: URLSearchParams): () => void {
  const raw = query.get("state") ?? "";
  const state: JobState | "" = (JOB_STATES as string[]).includes(raw) ? (raw as JobState) : "";
  document.title = state ? `${state} jobs · renderfarm` : "Jobs · renderfarm";

  const filters = h(
    "nav",
    { class: "segmented", "aria-label": "Filter by state" },
    ["", ...JOB_STATES].map((s) =>
      h("a", { href: s ? `#/jobs?state=${s}` : "#/jobs", "aria-current": s === state ? "page" : undefined, "data-filter": s || "all" }, s || "all"),
    ),
  );
  const tbody = h("tbody");
  const empty = h("p", { class: "empty", hidden: true });
  const more = h("button", { class: "button secondary", type: "button", hidden: true }, "Load older jobs");
  const status = h("p", { class: "muted small", role: "status", "aria-live": "polite" });
  const table = h(
    "table",
    { class: "table jobs-table" },
    h("caption", { class: "visually-hidden" }, "Jobs, newest first"),
    h(
      "thead",
      {},
      h(
        "tr",
        {},
        ["Name", "Owner", "State", "Progress (tiles)", "Mean spp", "Error / target", "Elapsed", "ETA", "Priority"].map((t, i) =>
          h("th", { scope: "col", class: i >= 4 ? "num" : undefined }, t),
        ),
      ),
    ),
    tbody,
  );
  replace(
    root,
    h(
      "div",
      { class: "page-head" },
      h("h1", {}, "Jobs"),
      h("a", { class: "button", href: "#/submit" }, "Submit a job"),
    ),
    filters,
    h("div", { class: "card table-card" }, h("div", { class: "table-scroll" }, table), empty),
    h("div", { class: "table-foot" }, more, status),
  );

  const rows = new Map<string, Row>();
  let olderToken = "";
  let olderLoaded = false;

  const render = (jobs: Job[]) => {
    // Newest first; rows already shown stay in place and are updated.
    let prev: HTMLTableRowElement | null = null;
    for (const job of jobs) {
      let row = rows.get(job.id);
      if (!row) {
        row = makeRow(job);
        rows.set(job.id, row);
      } else {
        row.update(job);
      }
      const want: ChildNode | null = prev ? prev.nextSibling : tbody.firstChild;
      if (want !== row.tr) tbody.insertBefore(row.tr, want);
      prev = row.tr;
    }
    empty.hidden = rows.size > 0;
    setText(empty, state ? `No ${state} jobs.` : "No jobs yet. Submit a scene to start rendering.");
  };

  const refresh = async () => {
    try {
      const page = await listJobs(state, PAGE);
      setConnection(true);
      if (!olderLoaded) olderToken = page.next_page_token;
      const ids = new Set(page.jobs.map((j) => j.id));
      // Rows of the first page that left the filter (a job that finished, under state=running).
      for (const [id, row] of rows) {
        if (!ids.has(id) && !olderLoaded) {
          row.tr.remove();
          rows.delete(id);
        }
      }
      render(page.jobs);
      more.hidden = !olderToken;
      setText(status, `Updated ${new Date().toLocaleTimeString()}`);
    } catch (e) {
      setConnection(false, e instanceof ApiError && e.status ? e.message : undefined);
    }
  };

  more.addEventListener("click", async () => {
    more.disabled = true;
    try {
      const page = await listJobs(state, PAGE, olderToken);
      olderLoaded = true;
      olderToken = page.next_page_token;
      for (const job of page.jobs) {
        if (rows.has(job.id)) continue;
        const row = makeRow(job);
        rows.set(job.id, row);
        tbody.appendChild(row.tr);
      }
      more.hidden = !olderToken;
    } catch (e) {
      setConnection(false, e instanceof Error ? e.message : undefined);
    } finally {
      more.disabled = false;
    }
  });

  return every(2000, refresh);
}
