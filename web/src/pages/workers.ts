// Workers page: every connected worker with its load and throughput, and the farm's total
// throughput over the last minutes (sampled every two seconds while the dashboard is open).

import { type Worker, controlWorker, workers } from "../api";
import { type TimedValue, timeSeries } from "../chart";
import { h, replace, setText } from "../dom";
import { ago, duration, si } from "../format";
import { card, every, setConnection, stat } from "../ui";

const WINDOW_S = 5 * 60;
// History survives leaving and re-opening the page (not a reload).
// The server keeps no throughput history, so the chart starts when the page is first opened.
const samplesHistory: TimedValue[] = [];
const raysHistory: TimedValue[] = [];

/** Heartbeats come every couple of seconds; a worker silent for longer is shown as stale. */
const STALE_AFTER_S = 10;

function workerState(w: Worker, now: number): "stale" | "rendering" | "idle" {
  if (now - w.last_heartbeat_unix_s > STALE_AFTER_S) return "stale";
  return w.tasks_in_flight > 0 || w.busy_threads > 0 ? "rendering" : "idle";
}

export function mountWorkers(root: HTMLElement): () => void {
  document.title = "Workers · renderfarm";
  const count = h("span", {}, "-");
  const cores = h("span", {}, "-");
  const busy = h("span", {}, "-");
  const sps = h("span", {}, "-");
  const rps = h("span", {}, "-");
  const samplesChart = h("div", { class: "plot-box" });
  const raysChart = h("div", { class: "plot-box" });
  const tbody = h("tbody");
  // Why the last drain/disable/enable was refused (e.g. 403 for a non-admin token).
  const controlError = h("p", { class: "control-message error", role: "alert", hidden: true });
  const empty = h("p", { class: "empty", hidden: true }, "No workers connected. Start one with ",
    h("code", {}, "renderfarm-worker connect --server HOST:PORT"), ".");
  replace(
    root,
    h("div", { class: "page-head" }, h("h1", {}, "Workers")),
    h(
      "div",
      { class: "stats" },
      stat("Workers", count, "workers"),
      stat("Cores", cores, "cores"),
      stat("Busy threads", busy, "busy"),
      stat("Farm samples / s", sps, "samples"),
      stat("Farm rays / s", rps, "rays"),
    ),
    h(
      "div",
      { class: "card table-card" },
      h(
        "div",
        { class: "table-scroll" },
        h(
          "table",
          { class: "table workers-table" },
          h("caption", { class: "visually-hidden" }, "Connected workers"),
          h(
            "thead",
            {},
            h(
              "tr",
              {},
              ["Worker", "State", "Mode", "Cores", "Busy threads", "Tasks in flight", "Tasks done", "Tasks failed", "Samples / s", "Rays / s", "Last heartbeat", "Connected", "Control"].map(
                (t, i) => h("th", { scope: "col", class: i >= 3 && i < 12 ? "num" : undefined }, t),
              ),
            ),
          ),
          tbody,
        ),
      ),
      empty,
      controlError,
    ),
    h("div", { class: "chart-row" }, card("Farm samples per second", samplesChart), card("Farm rays per second", raysChart)),
  );

  const drawCharts = () => {
    // One minute until there is more history to show, then the last five.
    const span = samplesHistory.length ? Date.now() / 1000 - samplesHistory[0].at : 0;
    const window = span > 60 ? WINDOW_S : 60;
    samplesChart.replaceChildren(timeSeries(samplesHistory, window, "samples/s"));
    raysChart.replaceChildren(timeSeries(raysHistory, window, "rays/s"));
  };

  const control = async (button: HTMLButtonElement, id: string, action: "drain" | "disable" | "enable") => {
    button.disabled = true;
    try {
      await controlWorker(id, action);
      controlError.hidden = true;
    } catch (e) {
      controlError.textContent = `Cannot ${action} ${id}: ${(e as Error).message}`;
      controlError.hidden = false;
    }
    await refresh();
  };

  const controls = (w: Worker) => {
    const actions: ["drain" | "disable" | "enable", string][] =
      w.state === "active" ? [["drain", "Drain"], ["disable", "Disable"]]
        : w.state === "disabled" ? [["enable", "Enable"]]
          : [["disable", "Disable"], ["enable", "Enable"]];
    return actions.map(([action, text]) => {
      const button = h("button", { type: "button", class: "button secondary small", "data-action": action }, text) as HTMLButtonElement;
      button.addEventListener("click", () => void control(button, w.id, action));
      return button;
    });
  };

  const refresh = async () => {
    let list: Worker[];
    try {
      list = await workers();
      setConnection(true);
    } catch (e) {
      setConnection(false, (e as Error).message);
      return;
    }
    const now = Date.now() / 1000;
    list.sort((a, b) => a.id.localeCompare(b.id));
    const totalSamples = list.reduce((a, w) => a + w.samples_per_s, 0);
    const totalRays = list.reduce((a, w) => a + w.rays_per_s, 0);
    setText(count, String(list.length));
    setText(cores, String(list.reduce((a, w) => a + w.cores, 0)));
    setText(busy, String(list.reduce((a, w) => a + w.busy_threads, 0)));
    setText(sps, si(totalSamples));
    setText(rps, si(totalRays));
    samplesHistory.push({ at: now, value: totalSamples });
    raysHistory.push({ at: now, value: totalRays });
    for (const hist of [samplesHistory, raysHistory]) {
      while (hist.length && hist[0].at < now - WINDOW_S - 10) hist.shift();
    }
    empty.hidden = list.length > 0;
    tbody.replaceChildren(
      ...list.map((w) => {
        const state = workerState(w, now);
        return h(
          "tr",
          { "data-worker-id": w.id },
          h(
            "td",
            {},
            h("div", { class: "mono" }, w.id),
            h("div", { class: "muted small" }, `${w.hostname} · v${w.version}`),
            w.tags.length ? h("div", { class: "muted small", "data-field": "tags" }, `tags: ${w.tags.join(", ")}`) : null,
            ...w.recent_errors.map((e) => h("div", { class: "worker-error small", "data-field": "error" }, e)),
          ),
          h("td", {}, h("span", { class: `badge worker-${state}` }, state)),
          h("td", {}, h("span", { class: `badge mode-${w.state}`, "data-field": "mode" }, w.state)),
          h("td", { class: "num" }, w.cores),
          h("td", { class: "num" }, `${w.busy_threads} / ${w.cores}`),
          h("td", { class: "num" }, w.tasks_in_flight),
          h("td", { class: "num" }, w.tasks_done.toLocaleString("en")),
          h("td", { class: "num" }, w.tasks_failed.toLocaleString("en")),
          h("td", { class: "num" }, si(w.samples_per_s)),
          h("td", { class: "num" }, si(w.rays_per_s)),
          h("td", { class: "num" }, ago(w.last_heartbeat_unix_s, now)),
          h("td", { class: "num" }, duration(now - w.connected_unix_s)),
          h("td", {}, h("div", { class: "actions" }, ...controls(w))),
        );
      }),
    );
    drawCharts();
  };
  drawCharts();
  return every(2000, refresh);
}
