// The job page's task log: what workers reported about the job's tasks (failures, the scene
// loader's warnings) and the workers kept off the job, picked out of its event log.

import type { JobEvent } from "./api";
import { tileLabel } from "./frames";

export type TaskLogLevel = "error" | "warning";

export interface TaskLogEntry {
  at: number;
  level: TaskLogLevel;
  kind: string;
  worker: string;
  /** Where the task was: "frame 3, tile 2, batch 0", "tile 5, batch 1" or "" (whole job). */
  place: string;
  message: string;
}

const KINDS: Record<string, TaskLogLevel> = {
  task_failed: "error",
  worker_excluded: "error",
  task_warning: "warning",
};

/** perFrame: tiles per frame of an animation (tile numbers in the log are the frame's own);
 *  frameSlots: frame number -> its place in the job's frame list. */
export function taskLog(
  events: JobEvent[],
  perFrame = 0,
  frameSlots: Map<number, number> = new Map(),
): TaskLogEntry[] {
  const out: TaskLogEntry[] = [];
  for (const e of events) {
    const level = KINDS[e.kind];
    if (level === undefined) continue;
    const d = (e.data ?? {}) as Record<string, unknown>;
    const parts: string[] = [];
    if (typeof d.tile === "number") parts.push(tileLabel(d, perFrame, frameSlots));
    else if (typeof d.frame === "number") parts.push(`frame ${d.frame}`);
    if (typeof d.batch === "number") parts.push(`batch ${d.batch}`);
    let message = String(d.message ?? d.error ?? "");
    if (e.kind === "worker_excluded") message = `kept off the job: ${message}`;
    else if (e.kind === "task_failed" && d.retryable === false) message = `${message} (not retried)`;
    out.push({ at: e.at, level, kind: e.kind, worker: String(d.worker ?? ""), place: parts.join(", "), message });
  }
  return out;
}
