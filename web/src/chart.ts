// Charts drawn as SVG: the error-against-time plot (log-log, with the 1/sqrt(t) line that Monte
// Carlo error follows) and time series of the farm's throughput.

import { s } from "./dom";
import { si } from "./format";

const W = 520;
const H = 300;
const M = { left: 58, right: 18, top: 18, bottom: 42 };
const PW = W - M.left - M.right;
const PH = H - M.top - M.bottom;

let clipIds = 0;

function frame(ariaLabel: string): SVGSVGElement {
  return s("svg", {
    viewBox: `0 0 ${W} ${H}`,
    class: "chart",
    role: "img",
    "aria-label": ariaLabel,
    preserveAspectRatio: "xMidYMid meet",
  });
}

/** Tick values for a log axis over [lo, hi] (linear values): 1-2-5 steps, or decades if wide. */
function logTicks(lo: number, hi: number): number[] {
  const decades = Math.log10(hi) - Math.log10(lo);
  const mantissas = decades > 2.5 ? [1] : decades > 1.2 ? [1, 3] : [1, 2, 5];
  const ticks: number[] = [];
  for (let d = Math.floor(Math.log10(lo)); d <= Math.ceil(Math.log10(hi)); d++) {
    for (const m of mantissas) {
      const v = m * Math.pow(10, d);
      if (v >= lo * 0.999 && v <= hi * 1.001) ticks.push(v);
    }
  }
  return ticks;
}

function niceNumber(v: number): string {
  if (v >= 1) return String(Number(v.toPrecision(3)));
  return String(Number(v.toPrecision(2)));
}

export interface ErrorPoint {
  t: number;
  error: number;
}

/**
 * Relative error against elapsed time, both axes logarithmic. The reference line c/sqrt(t) goes
 * through the latest point: measured error parallel to it means the render converges at the
 * Monte Carlo rate; the dotted line is the job's noise target.
 */
export function convergencePlot(points: ErrorPoint[], target: number | null): SVGSVGElement {
  const usable = points.filter((p) => p.t > 0 && p.error > 0 && Number.isFinite(p.error));
  const svg = frame(
    usable.length
      ? `Relative error against time, log-log: ${usable.length} samples, latest ${(usable[usable.length - 1].error * 100).toFixed(2)}%`
      : "Relative error against time: no samples yet",
  );
  if (usable.length < 2) {
    svg.append(
      s("text", { x: W / 2, y: H / 2, class: "chart-empty", "text-anchor": "middle" },
        usable.length ? "Waiting for more samples…" : "No error estimate yet"),
    );
    return svg;
  }
  const last = usable[usable.length - 1];
  let tLo = usable[0].t;
  let tHi = last.t;
  let eLo = Math.min(...usable.map((p) => p.error));
  let eHi = Math.max(...usable.map((p) => p.error));
  if (target && target > 0) {
    eLo = Math.min(eLo, target);
    eHi = Math.max(eHi, target);
  }
  // Pad in log space and keep at least a third of a decade on each axis.
  const pad = (lo: number, hi: number): [number, number] => {
    let a = Math.log10(lo);
    let b = Math.log10(hi);
    const span = Math.max(b - a, 0.35);
    const mid = (a + b) / 2;
    a = mid - span / 2 - span * 0.06;
    b = mid + span / 2 + span * 0.06;
    return [a, b];
  };
  const [x0, x1] = pad(tLo, tHi);
  const [y0, y1] = pad(eLo, eHi);
  tLo = Math.pow(10, x0);
  tHi = Math.pow(10, x1);
  eLo = Math.pow(10, y0);
  eHi = Math.pow(10, y1);
  const X = (t: number) => M.left + ((Math.log10(t) - x0) / (x1 - x0)) * PW;
  const Y = (e: number) => M.top + (1 - (Math.log10(e) - y0) / (y1 - y0)) * PH;

  const grid = s("g", { class: "grid" });
  const axes = s("g", { class: "axis" });
  for (const t of logTicks(tLo, tHi)) {
    grid.append(s("line", { x1: X(t), x2: X(t), y1: M.top, y2: M.top + PH }));
    axes.append(s("text", { x: X(t), y: M.top + PH + 16, "text-anchor": "middle" }, `${niceNumber(t)} s`));
  }
  for (const e of logTicks(eLo, eHi)) {
    grid.append(s("line", { x1: M.left, x2: M.left + PW, y1: Y(e), y2: Y(e) }));
    axes.append(s("text", { x: M.left - 6, y: Y(e) + 4, "text-anchor": "end" }, `${niceNumber(e * 100)}%`));
  }
  axes.append(
    s("text", { x: M.left + PW / 2, y: H - 6, "text-anchor": "middle", class: "axis-title" }, "elapsed time"),
    s("text", {
      x: 14, y: M.top + PH / 2, "text-anchor": "middle", class: "axis-title",
      transform: `rotate(-90 14 ${M.top + PH / 2})`,
    }, "relative error"),
  );
  const clip = `plot-clip-${++clipIds}`;
  const defs = s("defs", {}, s("clipPath", { id: clip }, s("rect", { x: M.left, y: M.top, width: PW, height: PH })));
  const plot = s("g", { "clip-path": `url(#${clip})` });
  // c / sqrt(t) through the latest point.
  const c = last.error * Math.sqrt(last.t);
  plot.append(
    s("line", { class: "ref-line", x1: X(tLo), y1: Y(c / Math.sqrt(tLo)), x2: X(tHi), y2: Y(c / Math.sqrt(tHi)) }),
  );
  if (target && target > 0) {
    plot.append(s("line", { class: "target-line", x1: M.left, x2: M.left + PW, y1: Y(target), y2: Y(target) }));
  }
  const d = usable.map((p, i) => `${i ? "L" : "M"}${X(p.t).toFixed(1)},${Y(p.error).toFixed(1)}`).join("");
  plot.append(s("path", { class: "series", d }));
  plot.append(s("circle", { class: "series-dot", cx: X(last.t), cy: Y(last.error), r: 3.5 }));
  const legend = s(
    "g",
    { class: "legend", transform: `translate(${M.left + PW - 150}, ${M.top + 8})` },
    s("rect", { x: -8, y: -6, width: 156, height: target ? 58 : 40, rx: 4, class: "legend-bg" }),
    s("line", { class: "series", x1: 0, x2: 22, y1: 6, y2: 6 }),
    s("text", { x: 28, y: 10 }, "measured"),
    s("line", { class: "ref-line", x1: 0, x2: 22, y1: 24, y2: 24 }),
    s("text", { x: 28, y: 28 }, "∝ 1/√t reference"),
    target ? s("line", { class: "target-line", x1: 0, x2: 22, y1: 42, y2: 42 }) : null,
    target ? s("text", { x: 28, y: 46 }, "noise target") : null,
  );
  svg.append(defs, s("rect", { class: "plot-bg", x: M.left, y: M.top, width: PW, height: PH }), grid, axes, plot, legend);
  return svg;
}

export interface TimedValue {
  at: number; // unix seconds
  value: number;
}

/** A value over the last `windowS` seconds, linear axes, from zero. */
export function timeSeries(points: TimedValue[], windowS: number, unit: string, now = Date.now() / 1000): SVGSVGElement {
  const latest = points.length ? points[points.length - 1].value : 0;
  const svg = frame(`${unit} over the last ${windowS >= 120 ? `${Math.round(windowS / 60)} minutes` : `${windowS} seconds`}; now ${si(latest)} ${unit}`);
  const shown = points.filter((p) => p.at >= now - windowS);
  let top = Math.max(1, ...shown.map((p) => p.value));
  const mag = Math.pow(10, Math.floor(Math.log10(top)));
  top = [1, 2, 2.5, 5, 10].map((m) => m * mag).find((v) => v >= top) ?? top;
  const X = (at: number) => M.left + ((at - (now - windowS)) / windowS) * PW;
  const Y = (v: number) => M.top + (1 - v / top) * PH;
  const grid = s("g", { class: "grid" });
  const axes = s("g", { class: "axis" });
  for (let i = 0; i <= 4; i++) {
    const v = (top * i) / 4;
    grid.append(s("line", { x1: M.left, x2: M.left + PW, y1: Y(v), y2: Y(v) }));
    axes.append(s("text", { x: M.left - 6, y: Y(v) + 4, "text-anchor": "end" }, si(v)));
  }
  const step = windowS <= 60 ? 10 : 60;
  const steps = Math.round(windowS / step);
  for (let i = 0; i <= steps; i++) {
    const at = now - windowS + i * step;
    grid.append(s("line", { x1: X(at), x2: X(at), y1: M.top, y2: M.top + PH }));
    const back = (steps - i) * step;
    const text = i === steps ? "now" : step === 60 ? `−${back / 60} min` : `−${back} s`;
    axes.append(s("text", { x: X(at), y: M.top + PH + 16, "text-anchor": "middle" }, text));
  }
  axes.append(
    s("text", {
      x: 14, y: M.top + PH / 2, "text-anchor": "middle", class: "axis-title",
      transform: `rotate(-90 14 ${M.top + PH / 2})`,
    }, unit),
  );
  svg.append(s("rect", { class: "plot-bg", x: M.left, y: M.top, width: PW, height: PH }), grid, axes);
  if (shown.length >= 2) {
    const line = shown.map((p, i) => `${i ? "L" : "M"}${X(p.at).toFixed(1)},${Y(p.value).toFixed(1)}`).join("");
    const area = `${line}L${X(shown[shown.length - 1].at).toFixed(1)},${Y(0)}L${X(shown[0].at).toFixed(1)},${Y(0)}Z`;
    svg.append(s("path", { class: "series-area", d: area }), s("path", { class: "series", d: line }));
  } else {
    svg.append(s("text", { x: W / 2, y: H / 2, class: "chart-empty", "text-anchor": "middle" }, "Collecting samples…"));
  }
  return svg;
}
