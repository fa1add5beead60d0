// Small components shared by the pages: state badges, progress bars, cards, the connection flag.

import type { JobState, Progress } from "./api";
import { h, setText } from "./dom";
import { percent } from "./format";

export function stateBadge(state: JobState | string): HTMLSpanElement {
  return h("span", { class: `badge state-${state}`, "data-state": state }, state);
}

export function updateBadge(el: HTMLElement, state: string): void {
  if (el.dataset.state === state) return;
  el.dataset.state = state;
  el.className = `badge state-${state}`;
  el.textContent = state;
}

/** A progress bar of converged tiles (role=progressbar, so tests and screen readers read it). */
export class TileProgress {
  readonly el: HTMLDivElement;
  private fill: HTMLDivElement;
  private text: HTMLSpanElement;

  constructor(label = "Tiles converged") {
    this.fill = h("div", { class: "progress-fill" });
    this.text = h("span", { class: "progress-text" });
    this.el = h(
      "div",
      { class: "progress", role: "progressbar", "aria-label": label, "aria-valuemin": 0 },
      h("div", { class: "progress-track" }, this.fill),
      this.text,
    );
  }

  update(p: Progress, state: JobState): void {
    const fraction = p.tiles_total ? p.tiles_done / p.tiles_total : 0;
    this.el.setAttribute("aria-valuemax", String(p.tiles_total));
    this.el.setAttribute("aria-valuenow", String(p.tiles_done));
    this.el.setAttribute("aria-valuetext", `${p.tiles_done} of ${p.tiles_total} tiles converged`);
    this.fill.style.width = `${(fraction * 100).toFixed(2)}%`;
    this.el.dataset.state = state;
    setText(this.text, `${p.tiles_done}/${p.tiles_total}`);
  }
}

/** "3.21% / 2.00%", marked as met when the error is at or below the target. */
export function errorVsTarget(el: HTMLElement, error: number | null, target: number): void {
  const met = error !== null && target > 0 && error <= target;
  el.classList.toggle("met", met);
  const text = target > 0 ? `${percent(error)} / ${percent(target)}` : `${percent(error)} / none`;
  setText(el, text);
  el.title = target > 0 ? "current relative error / noise target" : "noise_threshold 0: renders max_spp everywhere";
}

export function card(title: string | null, ...children: (Node | null)[]): HTMLElement {
  return h("section", { class: "card" }, title ? h("h2", { class: "card-title" }, title) : null, ...children);
}

export function stat(label: string, value: Node | string, id?: string): HTMLElement {
  return h("div", { class: "stat", "data-stat": id }, h("div", { class: "stat-label" }, label), h("div", { class: "stat-value" }, value));
}

/** The top bar's flag: shown only while the server cannot be reached. */
export function setConnection(ok: boolean, message = "Server unreachable, retrying…"): void {
  const el = document.getElementById("conn");
  if (!el) return;
  el.classList.toggle("down", !ok);
  setText(el, ok ? "" : message);
}

/** setInterval that pauses while the tab is hidden and runs at once when it comes back. */
export function every(ms: number, fn: () => void | Promise<void>): () => void {
  let timer: number | undefined;
  let busy = false;
  const tick = async () => {
    if (busy || document.hidden) return;
    busy = true;
    try {
      await fn();
    } finally {
      busy = false;
    }
  };
  const onVisible = () => {
    if (!document.hidden) void tick();
  };
  timer = window.setInterval(tick, ms);
  document.addEventListener("visibilitychange", onVisible);
  void tick();
  return () => {
    window.clearInterval(timer);
    document.removeEventListener("visibilitychange", onVisible);
  };
}
