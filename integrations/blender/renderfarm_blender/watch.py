"""Following jobs without blocking Blender: a thread per job asks the farm for the job every
second (GET /api/v1/jobs/{id}); a timer on Blender's main thread copies what the threads saw
into the scene (bpy may only be touched there) and redraws the panel and the status bar.

The timer stops when no job is followed; a job is followed until it finishes or the farm says
it cannot be (401, 403, 404).
"""

from __future__ import annotations

import threading
import time

import bpy

from .client import FINISHED, FarmClient, FarmError

POLL_INTERVAL_S = 1.0
APPLY_INTERVAL_S = 0.25


class Watcher(threading.Thread):
    def __init__(self, client: FarmClient, job_id: str):
        super().__init__(name=f"renderfarm-watch-{job_id[:8]}", daemon=True)
        self.client = client
        self.job_id = job_id
        self.lock = threading.Lock()
        self.stop_event = threading.Event()
        self.latest: dict | None = None  # the job as the farm last answered
        self.problem = ""  # why the last request failed ("" when it succeeded)
        self.gave_up = False  # the farm said the job cannot be followed
        self.fresh = False  # something new for the main thread

    def run(self) -> None:
        delay = POLL_INTERVAL_S
        while not self.stop_event.is_set():
            try:
                job = self.client.job(self.job_id)
            except FarmError as e:
                with self.lock:
                    self.problem = e.report()
                    self.gave_up = e.status in (401, 403, 404)
                    self.fresh = True
                if self.gave_up:
                    return
                delay = min(delay * 2, 10.0)  # an unreachable farm: back off, keep trying
            else:
                with self.lock:
                    self.latest, self.problem, self.fresh = job, "", True
                if job.get("state") in FINISHED:
                    return
                delay = POLL_INTERVAL_S
            self.stop_event.wait(delay)

    def take(self):
        """(job or None, problem, gave_up) if something new arrived, else None."""
        with self.lock:
            if not self.fresh:
                return None
            self.fresh = False
            return self.latest, self.problem, self.gave_up


_watchers: dict[str, Watcher] = {}


def watch(client: FarmClient, job_id: str) -> None:
    """Follow a job (again); the timer applies its updates to the scenes that hold it."""
    old = _watchers.get(job_id)
    if old is not None and old.is_alive():
        return
    w = Watcher(client, job_id)
    _watchers[job_id] = w
    w.start()
    if not bpy.app.timers.is_registered(apply_updates):
        bpy.app.timers.register(apply_updates, first_interval=APPLY_INTERVAL_S, persistent=True)


def following() -> list[str]:
    return [job_id for job_id, w in _watchers.items() if w.is_alive() or w.fresh]


def _entries(job_id: str):
    for scene in bpy.data.scenes:
        for entry in scene.renderfarm.jobs:
            if entry.job_id == job_id:
                yield scene, entry


def apply_job(entry, job: dict) -> None:
    entry.state = str(job.get("state", entry.state))
    entry.message = str(job.get("error") or "")
    progress = job.get("progress") or {}
    entry.tiles_done = int(progress.get("tiles_done") or 0)
    entry.tiles_total = int(progress.get("tiles_total") or 0)
    entry.mean_spp = float(progress.get("mean_spp") or 0.0)
    entry.error = float(progress.get("error") or 0.0)
    eta = progress.get("eta_s")
    entry.eta_s = -1.0 if eta is None else float(eta)
    entry.elapsed_s = float(progress.get("elapsed_s") or 0.0)
    entry.frames_total = int(progress.get("frames_total") or 1)
    entry.frames_done = int(progress.get("frames_done") or 0)
    entry.noise_threshold = float((job.get("settings") or {}).get("noise_threshold") or 0.0)


def _redraw() -> None:
    wm = bpy.context.window_manager
    for window in getattr(wm, "windows", ()):
        for area in window.screen.areas:
            if area.type in ("PROPERTIES", "STATUSBAR"):
                area.tag_redraw()


def apply_updates():
    """The timer: copy what the watchers saw into the scenes; the seconds until the next call,
    or None (the timer ends) when no job is followed."""
    changed = False
    for job_id, w in list(_watchers.items()):
        update = w.take()
        if update is not None:
            job, problem, gave_up = update
            for _scene, entry in _entries(job_id):
                if job is not None:
                    apply_job(entry, job)
                if problem:
                    entry.message = problem + ("" if gave_up else " (retrying)")
                elif job is not None and not job.get("error"):
                    entry.message = ""
                if gave_up:
                    entry.state = "unknown"
            changed = True
        if not w.is_alive() and not w.fresh:
            del _watchers[job_id]
    if changed:
        _redraw()
    return APPLY_INTERVAL_S if _watchers else None


def wait_all(timeout_s: float) -> bool:
    """Apply updates until no job is followed or timeout_s passed; True if none is left.
    For scripts and tests that run Blender without its event loop (bpy as a module, or
    blender --background), where timers do not fire by themselves."""
    deadline = time.monotonic() + timeout_s
    while True:
        apply_updates()
        if not _watchers:
            return True
        if time.monotonic() > deadline:
            return False
        for w in list(_watchers.values()):
            w.join(timeout=min(APPLY_INTERVAL_S, max(0.0, deadline - time.monotonic())))


def stop_all() -> None:
    for w in _watchers.values():
        w.stop_event.set()
    for w in _watchers.values():
        w.join(timeout=5.0)
    _watchers.clear()
    if bpy.app.timers.is_registered(apply_updates):
        bpy.app.timers.unregister(apply_updates)
