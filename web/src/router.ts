// The pure part of the dashboard's hash router: a location hash ("#/jobs/42", "#/jobs?state=done")
// to the page it names and that page's parameters. main.ts mounts the page; keeping the parsing
// free of the DOM lets it be unit tested.

/** The sections of the navigation bar; a job's page belongs to "jobs". */
export type Section = "jobs" | "workers" | "submit";

export type Route =
  | { page: "jobs"; query: URLSearchParams }
  | { page: "job"; jobId: string; frame: number | null }
  | { page: "workers" }
  | { page: "submit" };

/** Frame numbers the server accepts (domain/frames.py MAX_FRAME): within +-1e6. */
export const MAX_FRAME = 1_000_000;

/**
 * The frame a job page's query names (`?frame=12`, negative frames too): null when there is
 * none or it is not a whole number within +-MAX_FRAME, so a bad link shows the first frame.
 */
export function frameParam(query: URLSearchParams): number | null {
  const text = (query.get("frame") ?? "").trim();
  if (!/^-?\d{1,7}$/.test(text)) return null;
  const frame = Number(text);
  return Math.abs(frame) <= MAX_FRAME ? frame + 0 : null; // + 0: "-0" is frame 0
}

/** The hash of a job's page, showing `frame` of an animation (null: the page's default). */
export function jobHash(jobId: string, frame: number | null = null): string {
  return `#/jobs/${encodeURIComponent(jobId)}` + (frame === null ? "" : `?frame=${frame}`);
}

/**
 * The route of a location hash. An empty hash is the jobs list, and so is any path the dashboard
 * does not know. The job id is percent-decoded (a malformed escape throws URIError, as
 * decodeURIComponent does); a job's page carries the frame its query names (frameParam).
 */
export function parseRoute(hash: string): Route {
  const [path, queryText = ""] = hash.replace(/^#/, "").split("?");
  const parts = path.split("/").filter(Boolean);
  const section = parts[0] ?? "jobs";
  if (section === "jobs" && parts[1]) {
    return { page: "job", jobId: decodeURIComponent(parts[1]), frame: frameParam(new URLSearchParams(queryText)) };
  }
  if (section === "workers") return { page: "workers" };
  if (section === "submit") return { page: "submit" };
  return { page: "jobs", query: new URLSearchParams(queryText) };
}

/** The navigation link to mark as the current page. */
export function section(route: Route): Section {
  return route.page === "job" ? "jobs" : route.page;
}
