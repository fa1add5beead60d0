// frames.ts: the frame strip's cells, keys and tile numbering. Expected labels are written out
// by hand from the dashboard's formatting rules (percent: two decimals under 10%; spp: one
// decimal under 100); tile numbers from the server's layout (docs/api.md: slot s holds tiles
// s * perFrame .. (s + 1) * perFrame - 1).
import assert from "node:assert/strict";
import { describe, test } from "node:test";

import type { Frame } from "../src/api";
import { BudgetCache, frameCell, frameIndex, frameTiles, keyTarget, movieSummary } from "../src/frames";

const frame = (over: Partial<Frame>): Frame => ({
  frame: 1,
  state: "queued",
  tiles_total: 4,
  tiles_done: 0,
  mean_spp: 0,
  error: null,
  ...over,
});

describe("frameCell", () => {
  test("a job of every material variant names the variant", () => {
    const cell = frameCell(frame({ frame: 1, variant: "Dark blue", state: "done", error: 0.01, mean_spp: 4 }), 0.02);
    assert.equal(cell.label, "Variant Dark blue: done, error 1.00%, 4.0 spp");
  });

  test("a queued frame: nothing merged, nothing filled", () => {
    assert.deepEqual(frameCell(frame({ frame: 5 }), 0.02), { look: "queued", fill: 0, label: "Frame 5: queued" });
  });
  test("a rendering frame: filled by its share of stopped tiles, with error and spp", () => {
    const cell = frameCell(frame({ frame: 2, state: "rendering", tiles_done: 1, mean_spp: 6.25, error: 0.0512 }), 0);
    assert.deepEqual(cell, { look: "rendering", fill: 0.25, label: "Frame 2: rendering, error 5.12%, 6.3 spp, 1 of 4 tiles" });
  });
  test("a rendering frame with no error yet says so with a dash", () => {
    assert.equal(frameCell(frame({ state: "rendering" }), 0).label, "Frame 1: rendering, error -, 0.0 spp, 0 of 4 tiles");
  });
  test("a done frame at or under the target, or with no target, is done", () => {
    const under = frame({ frame: 3, state: "done", tiles_done: 4, mean_spp: 128, error: 0.02 });
    assert.deepEqual(frameCell(under, 0.02), { look: "done", fill: 1, label: "Frame 3: done, error 2.00%, 128 spp" });
    assert.equal(frameCell({ ...under, error: 0.5 }, 0).look, "done"); // threshold 0: no target
  });
  test("a done frame above a positive target is short of it", () => {
    const cell = frameCell(frame({ frame: -4, state: "done", tiles_done: 4, mean_spp: 16, error: 0.031 }), 0.02);
    assert.deepEqual(cell, { look: "short", fill: 1, label: "Frame -4: done above the noise target of 2.00%, error 3.10%, 16.0 spp" });
  });
  test("the fill stays within 0..1 whatever the counts", () => {
    assert.equal(frameCell(frame({ state: "rendering", tiles_total: 0 }), 0).fill, 0);
    assert.equal(frameCell(frame({ state: "rendering", tiles_done: 9 }), 0).fill, 1);
    assert.equal(frameCell(frame({ state: "done", tiles_done: 0 }), 0).fill, 1);
  });
});

describe("keyTarget", () => {
  test("arrows move by one, back with left and up, on with right and down", () => {
    assert.equal(keyTarget("ArrowRight", 2, 10), 3);
    assert.equal(keyTarget("ArrowDown", 2, 10), 3);
    assert.equal(keyTarget("ArrowLeft", 2, 10), 1);
    assert.equal(keyTarget("ArrowUp", 2, 10), 1);
  });
  test("Home and End go to the ends; Page keys by a page", () => {
    assert.equal(keyTarget("Home", 7, 10), 0);
    assert.equal(keyTarget("End", 0, 10), 9);
    assert.equal(keyTarget("PageDown", 3, 40), 13);
    assert.equal(keyTarget("PageUp", 13, 40, 5), 8);
  });
  test("clamped to the strip", () => {
    assert.equal(keyTarget("ArrowLeft", 0, 4), 0);
    assert.equal(keyTarget("ArrowRight", 3, 4), 3);
    assert.equal(keyTarget("PageDown", 2, 4), 3);
    assert.equal(keyTarget("PageUp", 2, 4), 0);
  });
  test("other keys, and an empty strip, are left alone", () => {
    for (const key of ["Enter", " ", "Tab", "a"]) assert.equal(keyTarget(key, 1, 4), null, key);
    assert.equal(keyTarget("ArrowRight", 0, 0), null);
  });
});

describe("frameIndex", () => {
  const frames = [1, 3, 5, 7].map((n) => frame({ frame: n }));
  test("the place of a frame the job renders", () => {
    assert.equal(frameIndex(frames, 1), 0);
    assert.equal(frameIndex(frames, 5), 2);
    assert.equal(frameIndex(frames, 7), 3);
  });
  test("no frame, or one the job does not render: the first", () => {
    assert.equal(frameIndex(frames, null), 0);
    assert.equal(frameIndex(frames, 4), 0);
    assert.equal(frameIndex(frames, 0), 0);
  });
});

describe("frameTiles", () => {
  // 3 frames of 4 tiles: frame slot 1 holds tiles 4..7.
  const stops = [0, 3, 4, 6, 7, 8, 11].map((tile) => ({ tile, spp: tile }));
  test("the stops of one frame, numbered in that frame's grid", () => {
    assert.deepEqual(
      frameTiles(stops, 1, 4).map((s) => [s.tile, s.local, s.spp]),
      [[4, 0, 4], [6, 2, 6], [7, 3, 7]],
    );
    assert.deepEqual(frameTiles(stops, 0, 4).map((s) => s.local), [0, 3]);
    assert.deepEqual(frameTiles(stops, 2, 4).map((s) => s.local), [0, 3]);
  });
  test("a frame with no stops, or past the last, has none", () => {
    assert.deepEqual(frameTiles(stops, 3, 4), []);
    assert.deepEqual(frameTiles([], 0, 4), []);
  });
  test("a still (slot 0, one frame) keeps its own numbers", () => {
    assert.deepEqual(frameTiles(stops, 0, 16).map((s) => s.local), [0, 3, 4, 6, 7, 8, 11]);
  });
});

describe("movieSummary", () => {
  test("frames finished and the movie's length at the job's fps", () => {
    assert.equal(movieSummary(3, 4, 4), "3 of 4 frames finished, 0.75 s at 4 fps");
    assert.equal(movieSummary(1, 120, 24), "1 of 120 frames finished, 0.04 s at 24 fps");
    assert.equal(movieSummary(240, 240, 24), "240 of 240 frames finished, 10.0 s at 24 fps");
    assert.equal(movieSummary(5, 10, 12.5), "5 of 10 frames finished, 0.40 s at 12.5 fps");
  });
});

describe("BudgetCache", () => {
  const cache = () => new BudgetCache<string, number[]>(10, (v) => v.length);
  test("keeps entries within its budget, dropping the least recently used", () => {
    const c = cache();
    c.set("a", [1, 1, 1, 1]);
    c.set("b", [2, 2, 2, 2]);
    assert.equal(c.bytes, 8);
    c.get("a"); // a is now more recent than b
    c.set("c", [3, 3, 3]);
    assert.deepEqual(c.keys(), ["a", "c"]);
    assert.equal(c.bytes, 7);
    assert.equal(c.get("b"), undefined);
    assert.deepEqual(c.get("a"), [1, 1, 1, 1]);
  });
  test("replacing an entry counts only its new size", () => {
    const c = cache();
    c.set("a", [1, 1, 1, 1, 1, 1]);
    c.set("a", [1, 1]);
    assert.equal(c.bytes, 2);
    assert.deepEqual(c.keys(), ["a"]);
  });
  test("an entry larger than the budget is not kept, and evicts nothing", () => {
    const c = cache();
    c.set("a", [1, 1]);
    c.set("big", new Array(11).fill(0));
    assert.deepEqual(c.keys(), ["a"]);
    assert.equal(c.bytes, 2);
  });
  test("delete frees its share", () => {
    const c = cache();
    c.set("a", [1, 1, 1]);
    c.delete("a");
    c.delete("missing");
    assert.equal(c.bytes, 0);
    assert.deepEqual(c.keys(), []);
  });
});
