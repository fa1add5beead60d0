// An animation's frames on its job page: a strip of one button per frame showing its state and
// error (frames.ts decides the look and the words), a slider to scrub through them, and the
// preview movie of the finished frames. The page owns what a selection does (image, tile grid,
// URL); this file only shows the frames and reports the chosen one.

import { type Frame, movieUrl } from "../api";
import { h, setText } from "../dom";
import { frameCell, frameName, keyTarget, movieSummary } from "../frames";

export class FrameStrip {
  readonly el: HTMLElement;
  private cells: HTMLButtonElement[] = [];
  private frames: Frame[];
  private index: number;
  private readonly list: HTMLDivElement;
  private readonly slider: HTMLInputElement;
  private readonly output: HTMLOutputElement;
  private readonly summary: HTMLParagraphElement;

  constructor(
    frames: Frame[],
    index: number,
    private readonly noiseThreshold: number,
    private readonly onSelect: (frame: Frame, index: number) => void,
    extra: HTMLElement | null = null,
  ) {
    this.frames = frames;
    this.index = index;
    this.slider = h("input", {
      type: "range",
      id: "frame-slider",
      class: "frame-slider",
      min: 0,
      max: Math.max(0, frames.length - 1),
      step: 1,
      value: String(index),
      oninput: () => this.select(Number(this.slider.value)),
    });
    this.output = h("output", { for: "frame-slider", class: "mono frame-output", "aria-live": "off" });
    this.summary = h("p", { class: "muted small frame-summary", "data-field": "frames-summary" });
    this.list = h("div", {
      class: "frame-cells",
      role: "toolbar",
      "aria-label": "Frames",
      "aria-orientation": "horizontal",
      onkeydown: (ev: KeyboardEvent) => this.onKey(ev),
    });
    this.el = h(
      "section",
      { class: "card frame-strip", "aria-label": "Frames" },
      h("h2", { class: "card-title" }, "Frames"),
      h("div", { class: "control frame-scrub" }, h("label", { for: "frame-slider" }, "Frame"), this.slider, this.output),
      this.list,
      this.summary,
      extra,
    );
    this.build();
    this.update(frames);
  }

  /** The frame shown. */
  get current(): Frame {
    return this.frames[this.index];
  }

  get currentIndex(): number {
    return this.index;
  }

  /** The frames' latest progress (GET .../frames): recolours the cells in place. */
  update(frames: Frame[]): void {
    if (frames.length !== this.cells.length) {
      this.frames = frames;
      this.index = Math.min(this.index, Math.max(0, frames.length - 1));
      this.build();
    }
    this.frames = frames;
    frames.forEach((f, i) => {
      const cell = frameCell(f, this.noiseThreshold);
      const button = this.cells[i];
      if (button.dataset.look !== cell.look) {
        button.dataset.look = cell.look;
        button.className = `frame-cell look-${cell.look}`;
      }
      button.dataset.state = f.state;
      button.style.setProperty("--fill", `${(cell.fill * 100).toFixed(1)}%`);
      if (button.getAttribute("aria-label") !== cell.label) {
        button.setAttribute("aria-label", cell.label);
        button.title = cell.label;
      }
    });
    const done = frames.filter((f) => f.state === "done").length;
    const rendering = frames.filter((f) => f.state === "rendering").length;
    setText(this.summary, `${done} of ${frames.length} frames done` + (rendering ? `, ${rendering} rendering` : ""));
    this.describeCurrent();
  }

  /** Shows the frame at `index` (clamped) and tells the page; `focus` moves focus to its cell. */
  select(index: number, focus = false): void {
    const i = Math.max(0, Math.min(this.frames.length - 1, Math.round(index)));
    const changed = i !== this.index;
    this.index = i;
    this.cells.forEach((c, k) => {
      c.setAttribute("aria-pressed", String(k === i));
      c.tabIndex = k === i ? 0 : -1;
    });
    if (this.slider.value !== String(i)) this.slider.value = String(i);
    this.describeCurrent();
    if (focus) {
      this.cells[i].focus();
      this.cells[i].scrollIntoView({ block: "nearest", inline: "nearest" });
    }
    if (changed) this.onSelect(this.frames[i], i);
  }

  private build(): void {
    this.cells = this.frames.map((f, i) =>
      h(
        "button",
        {
          type: "button",
          class: "frame-cell",
          "data-frame": f.frame,
          "aria-pressed": String(i === this.index),
          tabindex: i === this.index ? 0 : -1,
          onclick: () => this.select(i, true),
        },
        h("span", { class: "frame-number" }, f.frame),
      ),
    );
    this.list.replaceChildren(...this.cells);
    this.slider.max = String(Math.max(0, this.frames.length - 1));
    this.slider.value = String(this.index);
  }

  private describeCurrent(): void {
    const f = this.frames[this.index];
    if (!f) return;
    const text = `${frameName(f)} (${this.index + 1} of ${this.frames.length}), ${f.state}`;
    setText(this.output, text);
    this.slider.setAttribute("aria-valuetext", text);
    this.el.dataset.frame = String(f.frame);
  }

  private onKey(ev: KeyboardEvent): void {
    const target = keyTarget(ev.key, this.index, this.frames.length);
    if (target === null) return;
    ev.preventDefault();
    this.select(target, true);
  }
}

/**
 * The preview movie (GET .../movie.mp4: H.264 of the finished frames at the job's fps): shown
 * once a frame has finished, played in a <video> on request and linked for download. The
 * movie grows as frames finish; Play loads the latest one when it has more frames than the
 * one loaded.
 */
export class MoviePanel {
  readonly el: HTMLElement;
  private readonly video: HTMLVideoElement;
  private readonly play: HTMLButtonElement;
  private readonly download: HTMLAnchorElement;
  private readonly note: HTMLParagraphElement;
  private readonly problem: HTMLParagraphElement;
  private framesDone = 0;

  constructor(
    private readonly jobId: string,
    fileName: string,
    private readonly fps: number,
  ) {
    this.video = h("video", {
      class: "movie",
      controls: true,
      muted: true,
      loop: true,
      playsinline: true,
      preload: "metadata",
      hidden: true,
      "aria-label": "Preview movie of the finished frames",
    });
    this.video.muted = true; // the attribute alone does not mute a video made by script
    this.problem = h("p", { class: "control-message error small", role: "status", hidden: true });
    this.video.addEventListener("error", () => {
      this.problem.hidden = false;
      // A 503 (a server without ffmpeg) or a browser without H.264 both end here.
      setText(this.problem, "The movie cannot be played here (the server may lack ffmpeg, or this browser H.264): try Download MP4.");
    });
    this.video.addEventListener("loadedmetadata", () => {
      this.problem.hidden = true;
      this.video.dataset.ready = "true";
    });
    this.play = h("button", { type: "button", class: "button secondary small", "data-action": "play-movie", onclick: () => this.start() }, "Play preview movie");
    this.download = h("a", { class: "button secondary small", download: `${fileName}.mp4`, "data-action": "download-movie" }, "Download MP4");
    this.note = h("p", { class: "muted small" });
    this.el = h(
      "div",
      { class: "movie-panel", hidden: true, "data-field": "movie" },
      h("h3", { class: "movie-title" }, "Preview movie"),
      this.note,
      h("div", { class: "actions" }, this.play, this.download),
      this.problem,
      this.video,
    );
  }

  /** The job's frame counts: the panel shows while at least one frame has finished. */
  update(framesDone: number, framesTotal: number): void {
    this.framesDone = framesDone;
    this.el.hidden = framesDone < 1;
    if (framesDone < 1) {
      this.video.pause();
      return;
    }
    setText(this.note, movieSummary(framesDone, framesTotal, this.fps));
    const href = this.url();
    if (this.download.getAttribute("href") !== href) this.download.setAttribute("href", href);
  }

  stop(): void {
    this.video.pause();
    this.video.removeAttribute("src");
    this.video.load(); // ends the media request
  }

  private url(): string {
    return `${movieUrl(this.jobId)}?v=${this.framesDone}`;
  }

  private start(): void {
    this.video.hidden = false;
    if (this.video.dataset.frames !== String(this.framesDone)) {
      this.video.dataset.frames = String(this.framesDone);
      delete this.video.dataset.ready;
      this.video.src = this.url();
    }
    this.video.play().catch(() => {
      // Refused or not decodable: the error event says why; the controls still work.
    });
  }
}
