// The pure part of a job's frame strip (pages/framestrip.ts): how a frame's cell looks and what
// it says, which frame a key press moves to, which tiles of the job belong to a frame, and a
// small byte-budgeted cache for the images of finished frames. Free of the DOM: unit tested.

import type { Frame } from "./api";
import { percent, spp } from "./format";

/** A cell's look: queued (nothing merged), rendering, done, or done short of the noise target. */
export type CellLook = "queued" | "rendering" | "done" | "short";

export interface FrameCell {
  look: CellLook;
  /** Fraction of the frame's tiles that have stopped, 0..1. */
  fill: number;
  /** What the cell says to screen readers and in its tooltip. */
  label: string;
}

/** What a frame is called: "Frame 12", or for a job of every material variant (settings.variant
 * "all", whose frames are the variants' indices) "Variant Red". */
export function frameName(f: Frame): string {
  return f.variant != null ? `Variant ${f.variant}` : `Frame ${f.frame}`;
}

/**
 * The cell of a frame. A finished frame whose error is above a positive noise target (tiles
 * stopped at max_spp or the time limit) is "short"; with noise_threshold 0 there is no target.
 */
export function frameCell(f: Frame, noiseThreshold: number): FrameCell {
  const fill = f.state === "done" ? 1 : f.tiles_total > 0 ? Math.min(1, f.tiles_done / f.tiles_total) : 0;
  const tiles = `${f.tiles_done} of ${f.tiles_total} tiles`;
  const name = frameName(f);
  if (f.state === "queued") return { look: "queued", fill, label: `${name}: queued` };
  const error = `error ${percent(f.error)}`;
  if (f.state === "rendering") {
    return { look: "rendering", fill, label: `${name}: rendering, ${error}, ${spp(f.mean_spp)} spp, ${tiles}` };
  }
  const short = noiseThreshold > 0 && f.error !== null && f.error > noiseThreshold;
  const state = short ? `done above the noise target of ${percent(noiseThreshold)}` : "done";
  return { look: short ? "short" : "done", fill, label: `${name}: ${state}, ${error}, ${spp(f.mean_spp)} spp` };
}

/**
 * The index a key moves the selection to in a strip of `count` frames: arrows by one (left/up
 * back, right/down on), Page Up/Down by `page`, Home/End to the ends, clamped; null for any
 * other key (or an empty strip), which the strip leaves to the browser.
 */
export function keyTarget(key: string, index: number, count: number, page = 10): number | null {
  if (count <= 0) return null;
  const steps: Record<string, number> = {
    ArrowLeft: -1,
    ArrowUp: -1,
    ArrowRight: 1,
    ArrowDown: 1,
    PageUp: -page,
    PageDown: page,
    Home: -Infinity,
    End: Infinity,
  };
  const step = steps[key];
  if (step === undefined) return null;
  return Math.max(0, Math.min(count - 1, index + step));
}

/** The place of `frame` in the job's frame list, or 0 (the first frame) when it is not in it. */
export function frameIndex(frames: readonly Frame[], frame: number | null): number {
  if (frame === null) return 0;
  const i = frames.findIndex((f) => f.frame === frame);
  return i < 0 ? 0 : i;
}

/**
 * The tiles of the frame at `slot` among a job's tile stops, as that frame's own tile indices:
 * the server numbers an animation's tiles across frames, slot s holding s * perFrame up to
 * (s + 1) * perFrame - 1, each frame's grid in row-major order (docs/api.md).
 */
export function frameTiles<T extends { tile: number }>(stops: readonly T[], slot: number, perFrame: number): (T & { local: number })[] {
  const first = slot * perFrame;
  return stops.filter((s) => s.tile >= first && s.tile < first + perFrame).map((s) => ({ ...s, local: s.tile - first }));
}

/** How an event names its tile: "tile 5" of a still; of an animation "frame 20, tile 2", the
 *  tile numbered in its frame's own grid (frameSlots: frame number -> its place in the list). */
export function tileLabel(d: Record<string, unknown>, perFrame: number, frameSlots: ReadonlyMap<number, number>): string {
  const slot = typeof d.frame === "number" ? frameSlots.get(d.frame) : undefined;
  if (slot === undefined || perFrame <= 0) return typeof d.frame === "number" ? `frame ${d.frame}, tile ${d.tile}` : `tile ${d.tile}`;
  return `frame ${d.frame}, tile ${Number(d.tile) - slot * perFrame}`;
}

/** "3 of 4 frames finished, 0.75 s at 4 fps": what the preview movie holds. */
export function movieSummary(framesDone: number, framesTotal: number, fps: number): string {
  const seconds = fps > 0 ? framesDone / fps : 0;
  const length = seconds < 10 ? seconds.toFixed(2) : seconds.toFixed(1);
  return `${framesDone} of ${framesTotal} frames finished, ${length} s at ${fps} fps`;
}

/**
 * A map that keeps its most recently used entries within a budget of `size(value)` units
 * (bytes of decoded images), dropping the least recently used ones; an entry larger than the
 * whole budget is not kept.
 */
export class BudgetCache<K, V> {
  private entries = new Map<K, V>();
  private used = 0;

  constructor(
    private readonly budget: number,
    private readonly size: (value: V) => number,
  ) {}

  get(key: K): V | undefined {
    const value = this.entries.get(key);
    if (value === undefined) return undefined;
    this.entries.delete(key); // re-inserted: the most recently used is last
    this.entries.set(key, value);
    return value;
  }

  set(key: K, value: V): void {
    this.delete(key);
    const n = this.size(value);
    if (n > this.budget) return;
    this.entries.set(key, value);
    this.used += n;
    for (const [k, v] of this.entries) {
      if (this.used <= this.budget) break;
      this.entries.delete(k);
      this.used -= this.size(v);
    }
  }

  delete(key: K): void {
    const old = this.entries.get(key);
    if (old === undefined) return;
    this.entries.delete(key);
    this.used -= this.size(old);
  }

  get bytes(): number {
    return this.used;
  }

  keys(): K[] {
    return [...this.entries.keys()];
  }
}
