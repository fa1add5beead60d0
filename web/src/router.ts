// The pure part of the dashboard's hash router: a location hash ("#/jobs/42", "#/jobs?state=done")
// to the page it names and that page's parameters. main.ts mounts the page; keeping the parsing
// free of the DOM lets it be unit tested.

/** The sections of the navigation bar; a job's page belongs to "jobs". */
export type Section = "jobs" | "workers" | "submit";

export type Route =
  | { page: "jobs"; query: URLSearchParams }
  | { page: "job"; jobId: string }
  | { page: "workers" }
  | { page: "submit" };

/**
 * The route of a location hash. An empty hash is the jobs list, and so is any path the dashboard
 * does not know. The job id is percent-decoded (a malformed escape throws URIError, as
 * decodeURIComponent does).
 */
export function parseRoute(hash: string): Route {
  const [path, queryText = ""] = hash.replace(/^#/, "").split("?");
  const parts = path.split("/").filter(Boolean);
  const section = parts[0] ?? "jobs";
  if (section === "jobs" && parts[1]) return { page: "job", jobId: decodeURIComponent(parts[1]) };
  if (section === "workers") return { page: "workers" };
  if (section === "submit") return { page: "submit" };
  return { page: "jobs", query: new URLSearchParams(queryText) };
}

/** The navigation link to mark as the current page. */
export function section(route: Route): Section {
  return route.page === "job" ? "jobs" : route.page;
}
