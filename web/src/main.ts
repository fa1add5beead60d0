// The dashboard's entry point: a hash router over four pages. Each page mounts into <main> and
// returns a function that stops its timers and streams when the user leaves it.

import { mountJob } from "./pages/job";
import { mountJobs } from "./pages/jobs";
import { mountSubmit } from "./pages/submit";
import { mountWorkers } from "./pages/workers";
import { initSession } from "./session";

type Unmount = () => void;

let unmount: Unmount | null = null;
let first = true;

function route(): void {
  const main = document.getElementById("main")!;
  const hash = location.hash.replace(/^#/, "") || "/jobs";
  const [path, queryText = ""] = hash.split("?");
  const query = new URLSearchParams(queryText);
  const parts = path.split("/").filter(Boolean);
  unmount?.();
  unmount = null;
  let section = parts[0] ?? "jobs";
  if (section === "jobs" && parts[1]) unmount = mountJob(main, decodeURIComponent(parts[1]));
  else if (section === "workers") unmount = mountWorkers(main);
  else if (section === "submit") unmount = mountSubmit(main);
  else {
    section = "jobs";
    unmount = mountJobs(main, query);
  }
  for (const a of document.querySelectorAll<HTMLAnchorElement>("[data-nav]")) {
    if (a.dataset.nav === section) a.setAttribute("aria-current", "page");
    else a.removeAttribute("aria-current");
  }
  // Keyboard and screen-reader users land on the new page's content, not on the old link.
  if (!first) main.focus({ preventScroll: true });
  first = false;
  window.scrollTo(0, 0);
}

function stop(): void {
  unmount?.();
  unmount = null;
}

initSession(stop, route);
window.addEventListener("hashchange", route);
if (document.readyState === "loading") document.addEventListener("DOMContentLoaded", route);
else route();
