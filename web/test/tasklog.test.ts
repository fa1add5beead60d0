// tasklog.ts: the expected entries are written out by hand from the event shapes the server
// documents (docs/api.md, "task_failed", "task_warning", "worker_excluded").
import assert from "node:assert/strict";
import { describe, test } from "node:test";

import type { JobEvent } from "../src/api";
import { taskLog } from "../src/tasklog";

const ev = (kind: string, data: Record<string, unknown>, at = 10): JobEvent => ({ kind, data, at }) as JobEvent;

describe("taskLog", () => {
  test("keeps only what workers said about tasks, in order", () => {
    const log = taskLog([
      ev("submitted", {}),
      ev("task_warning", { worker: "w1", message: "texture ignored", tile: 4, batch: 0 }, 11),
      ev("tile_stopped", { tile: 4 }),
      ev("task_failed", { worker: "w2", error: "scene load: bad", retryable: true, tile: 1, batch: 2 }, 12),
    ]);
    assert.deepEqual(log, [
      { at: 11, level: "warning", kind: "task_warning", worker: "w1", place: "tile 4, batch 0", message: "texture ignored" },
      { at: 12, level: "error", kind: "task_failed", worker: "w2", place: "tile 1, batch 2", message: "scene load: bad" },
    ]);
  });
  test("an animation's tiles are numbered within their frame", () => {
    // Frames 10, 20 with 6 tiles each: global tile 8 is frame 20's tile 2.
    const slots = new Map([[10, 0], [20, 1]]);
    const [entry] = taskLog([ev("task_warning", { worker: "w", message: "m", tile: 8, batch: 1, frame: 20 })], 6, slots);
    assert.equal(entry.place, "frame 20, tile 2, batch 1");
  });
  test("failures that are not retried and excluded workers say so", () => {
    const log = taskLog([
      ev("task_failed", { worker: "w", error: "no animation named Walk", retryable: false, tile: 0, batch: 0 }),
      ev("worker_excluded", { worker: "w", error: "no animation named Walk" }),
    ]);
    assert.equal(log[0].message, "no animation named Walk (not retried)");
    assert.equal(log[1].message, "kept off the job: no animation named Walk");
    assert.equal(log[1].place, "");
  });
});
