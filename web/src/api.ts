// The server's REST API (/api/v1) as typed functions. Errors carry the server's message and the
// offending field ({"detail", "field"}), so forms can show them beside the field.

// The API's types are generated from the server's OpenAPI document (web/openapi.json, written
// by `make openapi` from the server's models) by openapi-typescript: `npm run api-types`.
import type { components } from "./generated/openapi";

type Schemas = components["schemas"];
export type JobState = Schemas["Job"]["state"];
export const JOB_STATES: JobState[] = ["waiting", "queued", "running", "paused", "completed", "failed", "cancelled"];
export type Progress = Schemas["Progress"];
/** A job's settings (the server's one table, server/renderfarm/domain/jobspec.py). */
export type JobSettings = Schemas["JobSettings"];
export type Job = Schemas["Job"];
export type StopRecord = Schemas["StopRecord"];
export type JobDetail = Schemas["JobDetail"];
export type JobEvent = Schemas["JobEvent"];
export type SettingDoc = Schemas["SettingDoc"];

/** A connected worker; `state` is operator control (docs/operators.md): drained = draining
 *  with no task left. */
export type Worker = Schemas["WorkerInfo"];
export type ConvergencePoint = Schemas["ConvergencePoint"];
/** One frame of a job (`GET .../frames`): a still has one, frame 0. */
export type Frame = Schemas["Frame"];

export const FINISHED: ReadonlySet<JobState> = new Set(["completed", "failed", "cancelled"]);

export class ApiError extends Error {
  constructor(
    readonly status: number,
    message: string,
    readonly field: string = "",
  ) {
    super(message);
  }
}

const BASE = "/api/v1";

let unauthorized: ((message: string) => void) | null = null;
/** Called on every 401 answer (no token, or an unknown or revoked one): the sign-in form. */
export function onUnauthorized(handler: (message: string) => void): void {
  unauthorized = handler;
}

async function request<T>(path: string, init?: RequestInit, signingIn = false): Promise<T> {
  let response: Response;
  try {
    response = await fetch(path, init);
  } catch {
    throw new ApiError(0, "the server cannot be reached");
  }
  if (!response.ok) {
    let detail = `${response.status} ${response.statusText}`;
    let field = "";
    try {
      const body = await response.json();
      if (typeof body.detail === "string") detail = body.detail;
      if (typeof body.field === "string") field = body.field;
    } catch {
      // not JSON: keep the status line
    }
    if (response.status === 401 && !signingIn) unauthorized?.(detail);
    throw new ApiError(response.status, detail, field);
  }
  if (response.status === 204) return undefined as T;
  return (await response.json()) as T;
}

export type Caller = Schemas["WhoAmI"];

/** Checks a token and keeps it in the HttpOnly session cookie (which EventSource and images use). */
export const signIn = (token: string) =>
  request<Caller>(
    `${BASE}/session`,
    { method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify({ token }) },
    true,
  );
export const signOut = () => request<void>(`${BASE}/session`, { method: "DELETE" }, true);

export function listJobs(
  state: JobState | "",
  pageSize = 50,
  pageToken = "",
): Promise<{ jobs: Job[]; next_page_token: string }> {
  const q = new URLSearchParams({ page_size: String(pageSize) });
  if (state) q.set("state", state);
  if (pageToken) q.set("page_token", pageToken);
  return request(`${BASE}/jobs?${q}`);
}

export const getJob = (id: string) => request<JobDetail>(`${BASE}/jobs/${encodeURIComponent(id)}`);
export const jobEvents = (id: string) =>
  request<JobEvent[]>(`${BASE}/jobs/${encodeURIComponent(id)}/events`);
export const cancelJob = (id: string) =>
  request<Job>(`${BASE}/jobs/${encodeURIComponent(id)}/cancel`, { method: "POST" });
const jobPost = (id: string, action: string, body?: unknown) =>
  request<Job>(`${BASE}/jobs/${encodeURIComponent(id)}/${action}`, {
    method: "POST",
    ...(body === undefined ? {} : { headers: { "Content-Type": "application/json" }, body: JSON.stringify(body) }),
  });
export const pauseJob = (id: string) => jobPost(id, "pause");
export const resumeJob = (id: string) => jobPost(id, "resume");
export const retryJob = (id: string) => jobPost(id, "retry");
/** Carries a completed job on: a higher max_spp and/or a lower noise_threshold. */
export const continueJob = (id: string, settings: { max_spp?: number; noise_threshold?: number }) =>
  jobPost(id, "continue", { settings });
export const updateJob = (id: string, change: { priority?: number; name?: string }) =>
  request<Job>(`${BASE}/jobs/${encodeURIComponent(id)}`, {
    method: "PATCH",
    headers: { "Content-Type": "application/json" },
    body: JSON.stringify(change),
  });
export const workers = () => request<Worker[]>(`${BASE}/workers`);
/** Admin tokens only: drain (finish, take no more), disable (hand tasks back now), enable. */
export const controlWorker = (id: string, action: "drain" | "disable" | "enable") =>
  request<Worker>(`${BASE}/workers/${encodeURIComponent(id)}/${action}`, { method: "POST" });
export const listFrames = (id: string) => request<Frame[]>(`${BASE}/jobs/${encodeURIComponent(id)}/frames`);
/** What pixel (x, y) of an image's Cryptomatte holds (a still's image is frame 0). */
export type PixelMattes = Schemas["PixelMattes"];
export const pixelMattes = (id: string, frame: number, x: number, y: number) =>
  request<PixelMattes>(`${BASE}/jobs/${encodeURIComponent(id)}/frames/${frame}/mattes?x=${x}&y=${y}`);
export const convergence = (id: string) =>
  request<ConvergencePoint[]>(`${BASE}/jobs/${encodeURIComponent(id)}/convergence`);

let settingsDoc: Promise<SettingDoc[]> | null = null;
export function settings(): Promise<SettingDoc[]> {
  settingsDoc ??= request<SettingDoc[]>(`${BASE}/settings`).catch((e) => {
    settingsDoc = null;
    throw e;
  });
  return settingsDoc;
}

export function submitJob(scene: File, name: string, jobSettings: Record<string, unknown>): Promise<Job> {
  const form = new FormData();
  form.append("scene", scene, scene.name);
  form.append("settings", JSON.stringify(jobSettings));
  if (name) form.append("name", name);
  return request<Job>(`${BASE}/jobs`, { method: "POST", body: form });
}

export const imageUrl = (id: string, fmt: "png" | "exr", layer = "rgb") =>
  `${BASE}/jobs/${encodeURIComponent(id)}/image.${fmt}` + (fmt === "png" ? `?layer=${layer}` : "");

/** One frame of an animation, with the query parameters of imageUrl. */
export const frameImageUrl = (id: string, frame: number, fmt: "png" | "exr", layer = "rgb") =>
  `${BASE}/jobs/${encodeURIComponent(id)}/frames/${frame}/image.${fmt}` + (fmt === "png" ? `?layer=${layer}` : "");

/** The API path of the preview movie, as the server's OpenAPI document names it. */
export const MOVIE_PATH = "/api/v1/jobs/{job_id}/movie.mp4";
/** The H.264 preview movie of an animation's finished frames (404 for a still, 409 before a frame finished). */
export const movieUrl = (id: string) => `${BASE}/jobs/${encodeURIComponent(id)}/movie.mp4`;

export const watchUrl = (id: string) => `${BASE}/jobs/${encodeURIComponent(id)}/watch`;

let routes: Promise<Set<string>> | null = null;
/**
 * Whether the server offers an API path, from its OpenAPI document (read once). Lets the
 * dashboard use endpoints that are being added without probing them with failing requests.
 */
export async function serverHas(path: string): Promise<boolean> {
  routes ??= fetch("/openapi.json")
    .then((r) => (r.ok ? r.json() : { paths: {} }))
    .then((doc: { paths?: Record<string, unknown> }) => new Set(Object.keys(doc.paths ?? {})))
    .catch(() => new Set<string>());
  return (await routes).has(path);
}
