// The dashboard's entry point: a hash router over four pages. Each page mounts into <main> and
// returns a function that stops its timers and streams when the user leaves it.

import { mountJob } from "./pages/job";
import { mountJobs } from "./pages/jobs";
import { mountSubmit } from "./pages/submit";
import { mountWorkers } from "./pages/workers";
import { parseRoute, section } from "./router";
import { initSession } from "./session";

type Unmount = () => void;

let unmount: Unmount | null = null;
let first = true;

function route(): void {
  const main = document.getElementById("main")!;
  unmount?.();
  unmount = null;
  const current = parseRoute(location.hash);
  if (current.page === "job") unmount = mountJob(main, current.jobId, current.frame);
  else if (current.page === "workers") unmount = mountWorkers(main);
  else if (current.page === "submit") unmount = mountSubmit(main);
  else unmount = mountJobs(main, current.query);
  const nav = section(current);
  for (const a of document.querySelectorAll<HTMLAnchorElement>("[data-nav]")) {
    if (a.dataset.nav === nav) a.setAttribute("aria-current", "page");
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
