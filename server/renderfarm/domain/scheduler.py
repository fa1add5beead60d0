"""The scheduler: tiles, batches, leases, in-order merging and stop decisions. No I/O but the
spill files of the tile cache it may be given (infra/spill.py, injected as a TileCache), which
keeps large jobs' tiles.

One Scheduler holds every unfinished job in memory. Callers (the gRPC worker stream, the REST
API) tell it what happened (a worker connected, a result arrived, time passed) and read back
what to do: tasks to send, tasks to cancel, events to store. Time comes from an injected clock so
tests can drive it.

Determinism (docs/architecture.md): a result is identified by (job, tile, batch), not by the lease
that produced it. Batches of a tile are merged strictly in batch order (early arrivals wait in
`pending`), and the stop decision after batch k only looks at batches 0..k. Hence the merged
image is the same whichever worker rendered what, in any order; duplicates and batches past a
tile's stop point are discarded. The same holds for planned batch sizes (tiling.plan_batch):
batch k's size is planned from the tile's state after batches 0..k-2, once they are merged, so
one batch can render while the next is leased.

The Scheduler class stays whole (its records are in records.py, the continue rule in
continuation.py): its methods keep leases, tile heaps, credits and states consistent with one
another, which a split across modules would hide.
"""

from __future__ import annotations

import heapq
import itertools
import math
import time
from collections.abc import Callable
from typing import Protocol

import numpy as np

from . import channels, pixel_stops
from .channels import job_layout
from .frames import job_frames, job_rects, tiles_per_frame
from .jobspec import JobSettings
from .merge import TileAccumulator, all_finite
from .records import (
    TASK_LOG_MAX,
    WORKER_MODES,
    BatchResult,
    Event,
    FrameProgress,
    JobRun,
    Lease,
    Progress,
    StopRecord,
    TileState,
    WorkerRecord,
    WorkerSlot,
)
from .states import JobState, StopReason, check_transition
from .tiling import PLANNED_FROM, batch_range, batch_start, carries_aovs, plan_batch

# The rows every job has: every result carries them (grpc_decode checks that it does).
_EVERY_RESULT = frozenset(channels.DEFAULT.names)

# How many batches of one tile may be leased or waiting beyond the merged ones when every tile
# already has work: speculation keeps workers busy on small images at the risk of rendering a
# batch past the tile's stop point (it is then cancelled or discarded, never merged).
SPECULATION_DEPTH = 3

# The ETA divides the samples still needed by the rate at which samples were merged over about
# this many recent seconds: the rate of the farm as it is now (workers come and go, tiles differ
# in cost), not an average since the start that includes scene loading and queueing.
ETA_WINDOW_S = 30.0


class TileCache(Protocol):
    """Where tile accumulators live beyond a RAM budget: infra.spill.TileCache, given by the
    job service (the scheduler does no I/O itself)."""

    def register(self, job_id: str, acc: TileAccumulator, tile_size: int) -> None: ...

    def use(self, acc: TileAccumulator) -> None: ...

    def forget_job(self, job_id: str) -> None: ...


class Scheduler:
    def __init__(
        self,
        clock: Callable[[], float] = time.monotonic,
        lease_s: float = 30.0,
        max_task_failures: int = 3,
        cache: TileCache | None = None,
    ):
        """cache: where tile accumulators live beyond a RAM budget (None: all in RAM)."""
        self.clock = clock
        self.cache = cache
        self.lease_s = lease_s
        self.max_task_failures = max_task_failures
        self.jobs: dict[str, JobRun] = {}
        self.workers: dict[str, WorkerSlot] = {}
        self.leases: dict[str, Lease] = {}
        self.events: list[Event] = []
        self.cancellations: dict[str, list[str]] = {}  # worker -> task ids to cancel
        self.records: dict[str, WorkerRecord] = {}  # worker id -> mode and counts (kept)
        # Workers with fewer leases than their credit, by their tags (ordered sets): only they
        # can take a task, so a change asks them alone rather than every connected worker,
        # and of each group only until one is left with room (assign_free).
        self._free: dict[frozenset[str], dict[str, None]] = {}
        self.leases_expired = 0  # since start (renderfarm_leases_expired_total)
        self._task_ids = itertools.count(1)

    # ----------------------------------------------------------------------------- jobs
    def add_job(
        self,
        job_id: str,
        settings: JobSettings,
        scene_sha256: str,
        checkpoint: dict[int, TileAccumulator] | None = None,
        state: JobState = JobState.QUEUED,
        elapsed_s: float = 0.0,
        plans: dict[int, list[int]] | None = None,
        bases: dict[int, list[list]] | None = None,
        after: tuple[str, ...] = (),
        transition: tuple[JobState, str, dict] | None = None,
        require_tags: tuple[str, ...] = (),
        variants: tuple[str, ...] = (),
    ) -> JobRun:
        """Add a job; `checkpoint` resumes tiles from merged accumulators (restart recovery),
        `plans` their planned batch sizes as planned_batches() gave them at that checkpoint,
        `bases` what their planned batches were planned from (plan_basis()), `variants` the
        names of the scene's variants of a job that renders every one (an image each).

        transition: (state it was in, event kind, event data) when a finished job comes back
        (retry, continue): checked against the state machine and recorded as that event; the
        tile stops found again while restoring are not recorded twice."""
        if transition is not None:
            check_transition(transition[0], state)
        now = self.clock()
        events_before = len(self.events)
        iid = settings.sampler == "independent"
        cached = self.cache is not None  # then arrays are made when a tile is first used
        per_frame = tiles_per_frame(settings)
        layout = job_layout(settings)
        tiles = [
            TileState(i, r, TileAccumulator(r.width, r.height, iid, not cached, layout),
                      slot=i // per_frame)
            for i, r in enumerate(job_rects(settings, variants))
        ]  # fmt: skip
        job = JobRun(job_id, settings, scene_sha256, tiles, created=now, state=state, after=after)
        job.frames = job_frames(settings, variants)
        job.variants = tuple(variants)
        job.tiles_per_frame = per_frame
        job.frame_tiles_stopped = [0] * job.frame_count
        job.elapsed_before = elapsed_s
        job.require_tags = frozenset(require_tags)
        job.requires = job.require_tags | channels.capability_tags(layout.rows)
        if state in (JobState.RUNNING, JobState.PAUSED):
            job.started = now - elapsed_s
        if state == JobState.PAUSED:
            job.paused_at = now
        for index, acc in (checkpoint or {}).items():
            tile = tiles[index]
            tile.acc = acc
            tile.basis = {
                int(b): (int(c), int(n), None if e is None else float(e), int(before))
                for b, c, n, e, before in (bases or {}).get(index) or []
            }
            self._register(job, tile)
            tile.next_batch = acc.batches
            job.samples_merged += int(acc.spp_sum)
            if acc.batches:
                self._use(tile)
                tile.error = pixel_stops.tile_error(acc, settings.noise_metric)
                self._decide_stop(job, tile)
            first = max(tile.merged, PLANNED_FROM)
            tile.plan = {first + i: count for i, count in enumerate((plans or {}).get(index, []))}
            if not tile.stopped and tile.merged not in tile.plan:
                # No saved plan (a checkpoint from before planned batches): plan the next
                # batch from the state at hand (not the basis a fresh job would have had, so it
                # is not recorded: a continue renders this tile again).
                self._plan(job, tile, tile.merged, tile.acc.samples, record=False)
            self._plan_ahead(job, tile)
        self.jobs[job_id] = job
        for tile in tiles:
            self._register(job, tile)
            self._touch(job, tile)
        if transition is not None:
            old, kind, data = transition
            del self.events[events_before:]  # the tile stops were recorded when they happened
            self.events.append(Event(kind, job_id, {"from": old.value, "to": state.value, **data}))
        self._maybe_finish(job)
        return job

    def cancel_job(self, job_id: str) -> JobRun:
        job = self.jobs[job_id]
        if not job.state.finished:
            self._finish(job, JobState.CANCELLED)
        return job

    # ------------------------------------------------------------------- job control
    def _transition(self, job: JobRun, state: JobState, kind: str, data: dict) -> None:
        """The one place where a live job changes state: checked against the state machine
        (states.TRANSITIONS; TransitionError when refused) and recorded as an event."""
        check_transition(job.state, state)
        old = job.state
        job.state = state
        job.version += 1
        self.events.append(Event(kind, job.job_id, {"from": old.value, "to": state.value, **data}))

    def pause_job(self, job_id: str) -> JobRun:
        """Stop leasing the job's tasks. The tasks workers hold are returned (cancelled and
        leased again on resume), so the farm turns to other jobs at once; a result of one that
        still arrives is merged, as any result is (it is the same batch whoever renders it)."""
        job = self.jobs[job_id]
        self._transition(job, JobState.PAUSED, "job_paused", {})
        job.paused_at = self.clock()
        for tile in job.tiles:
            for task_id in list(tile.in_flight.values()):
                lease = self.leases.get(task_id)
                if lease is not None:
                    self._release(lease, requeue=True)
                    self.cancellations.setdefault(lease.worker_id, []).append(task_id)
        return job

    def resume_job(self, job_id: str) -> JobRun:
        """Lease the job's tasks again, from where it paused (running if it had started)."""
        job = self.jobs[job_id]
        state = JobState.QUEUED if job.started is None else JobState.RUNNING
        self._transition(job, state, "job_resumed", {})
        if job.paused_at is not None and job.started is not None:
            job.started += self.clock() - job.paused_at  # time paused is not elapsed time
        job.paused_at = None
        for tile in job.tiles:
            self._touch(job, tile)
        return job

    def release_job(self, job_id: str) -> JobRun:
        """Every job a waiting job waits for has completed: queue it."""
        job = self.jobs[job_id]
        self._transition(job, JobState.QUEUED, "job_released", {"after": list(job.after)})
        return job

    def update_job(self, job_id: str, settings: JobSettings, name: str) -> None:
        """New priority (in settings) or name of a live job: an event, and a visible change."""
        job = self.jobs[job_id]
        job.settings = settings
        job.version += 1
        self.events.append(
            Event("job_updated", job_id, {"priority": settings.priority, "name": name})
        )

    def fail_job(self, job_id: str, message: str) -> None:
        job = self.jobs[job_id]
        if not job.state.finished:
            job.error_message = message
            self._finish(job, JobState.FAILED)

    def forget_job(self, job_id: str) -> None:
        """Drop a finished job's in-memory state."""
        job = self.jobs.get(job_id)
        if job is not None and job.state.finished:
            del self.jobs[job_id]
            if self.cache is not None:
                self.cache.forget_job(job_id)

    def drop_job(self, job_id: str) -> None:
        """Drop a job in any state, without an event: another server owns it now (#39). The
        tasks workers hold of it are cancelled; a result of one that still arrives is
        discarded (unknown job)."""
        job = self.jobs.pop(job_id, None)
        if job is None:
            return
        for lease in [x for x in self.leases.values() if x.job_id == job_id]:
            self._release(lease, requeue=False)
            self.cancellations.setdefault(lease.worker_id, []).append(lease.task_id)
        self.events = [e for e in self.events if e.job_id != job_id]
        if self.cache is not None:
            self.cache.forget_job(job_id)

    def _register(self, job: JobRun, tile: TileState) -> None:
        if self.cache is not None:
            self.cache.register(job.job_id, tile.acc, job.settings.tile_size)

    def _use(self, tile: TileState) -> None:
        """Bring a tile's arrays into RAM before they are read or merged."""
        if self.cache is not None:
            self.cache.use(tile.acc)

    def progress(self, job: JobRun) -> Progress:
        now = self.clock()
        paused = job.paused_at if job.state == JobState.PAUSED else None
        done = job.tiles_stopped
        mean_spp = sum(t.acc.spp_sum for t in job.tiles) / (job.pixels * job.frame_count)
        errors = [t.error for t in job.tiles if t.merged]
        error = math.sqrt(sum(e * e for e in errors) / len(errors)) if errors else math.inf
        if job.started is None:
            elapsed = job.elapsed_before
        else:
            elapsed = (paused or job.finished or now) - job.started
        return Progress(
            tiles_total=len(job.tiles),
            tiles_done=done,
            tiles_previewed=sum(1 for t in job.tiles if t.merged),
            mean_spp=mean_spp,
            error=error,
            eta_s=self._eta(job, now, elapsed),
            samples_merged=job.samples_merged,
            elapsed_s=elapsed,
            frames_total=job.frame_count,
            frames_done=sum(1 for n in job.frame_tiles_stopped if n == job.tiles_per_frame),
        )

    @staticmethod
    def frame_progress(job: JobRun, slot: int) -> FrameProgress:
        """Progress of one frame of a job (slot: its place in the frame list)."""
        tiles = job.frame_tiles(slot)
        errors = [t.error for t in tiles if t.merged]
        done = job.frame_tiles_stopped[slot]
        if done == len(tiles):
            state = "done"
        else:
            state = "rendering" if errors else "queued"
        return FrameProgress(
            frame=job.frames[slot] if job.frames is not None else 0,
            variant=job.variants[slot] if job.variants else None,
            state=state,
            tiles_total=len(tiles),
            tiles_done=done,
            mean_spp=sum(t.acc.spp_sum for t in tiles) / job.pixels,
            error=math.sqrt(sum(e * e for e in errors) / len(errors)) if errors else math.inf,
        )

    def _eta(self, job: JobRun, now: float, elapsed: float) -> float | None:
        """Seconds to completion: the samples still needed divided by the samples merged per
        second over the last ETA_WINDOW_S; None until two batches have been merged.

        A tile still rendering needs max_spp samples, or with a noise threshold the samples at
        which its error would reach the threshold (Monte Carlo error falls as 1/sqrt(samples):
        n * (error / threshold)^2, within min_spp..max_spp; under adaptive pixel_mse, whose bound
        grows as sqrt(n / 64), sqrt(64 n) error / threshold). A tile without an error estimate
        yet is taken to need what the estimated tiles need on average. A time limit caps it.
        """
        if job.state.finished:
            return 0.0
        if len(job.merges) < 2:
            return None
        since, base = job.merges[0]
        merged = job.merges[-1][1] - base  # samples merged after the window's first point
        if now <= since or merged <= 0:
            return None
        rate = merged / (now - since)
        s = job.settings
        targets: list[float] = []  # estimated final spp of the tiles that have an estimate
        unknown: list[TileState] = []
        needed = 0.0
        for t in job.tiles:
            if t.stopped:
                continue
            if s.noise_threshold <= 0:
                needed += (s.max_spp - t.acc.samples) * t.rect.pixels
            elif t.merged and math.isfinite(t.error):
                if s.adaptive == "pixel_mse":  # its bound grows with the samples too
                    target = pixel_stops.mse_samples_needed(
                        t.error, t.acc.samples, s.noise_threshold
                    )
                else:
                    target = t.acc.samples * (t.error / s.noise_threshold) ** 2
                target = min(s.max_spp, max(s.min_spp, t.acc.samples, target))
                targets.append(target)
                needed += (target - t.acc.samples) * t.rect.pixels
            else:
                unknown.append(t)
        guess = sum(targets) / len(targets) if targets else s.max_spp
        needed += sum(max(0.0, guess - t.acc.samples) * t.rect.pixels for t in unknown)
        eta = needed / rate
        if s.time_limit_s > 0:
            eta = min(eta, max(0.0, s.time_limit_s - elapsed))
        return eta

    # -------------------------------------------------------------------------- workers
    def add_worker(
        self,
        worker_id: str,
        credit: int,
        tags: tuple[str, ...] = (),
        renders: tuple[str, ...] | None = None,
    ) -> None:
        """A worker with its tags and the rows of the channel table it renders (None: every
        row), which decide the jobs it may take (_job_order)."""
        if worker_id in self.workers:
            self.remove_worker(worker_id)
        matched = frozenset(tags) | channels.capability_tags(renders)
        slot = WorkerSlot(worker_id, max(1, credit), tags=matched)
        self.workers[worker_id] = slot
        self.records.setdefault(worker_id, WorkerRecord())
        self._room_changed(slot)

    def free_workers(self) -> list[str]:
        """The workers with room for another lease (their credit not used up), by tags, each
        group in the order they had room; assign() may still give them nothing."""
        return [worker_id for group in self._free.values() for worker_id in group]

    def _room_changed(self, slot: WorkerSlot, gone: bool = False) -> None:
        group = self._free.get(slot.tags)
        if not gone and len(slot.leases) < slot.credit:
            if group is None:
                group = self._free[slot.tags] = {}
            group.setdefault(slot.worker_id, None)
        elif group is not None:
            group.pop(slot.worker_id, None)
            if not group:
                del self._free[slot.tags]

    def assign_free(
        self,
        owns: Callable[[str], bool] | None = None,
        reachable: Callable[[str], bool] | None = None,
    ) -> list[Lease]:
        """Lease tasks to the workers with room for them (and that `reachable` accepts: the
        server has their stream); the new leases. Within a group of workers with the same
        tags, once one is left with room the work it may take has run out, and so it has for
        the rest of the group and for every group whose tags are a subset of these: they are
        not asked (a worker that is not active, unresponsive or kept off a job is no such
        evidence, and is passed over). So a result costs a few tries, not one per idle
        worker, when the work runs short."""
        new: list[Lease] = []
        dry: list[frozenset[str]] = []
        for tags in list(self._free):
            if any(tags <= d for d in dry):
                continue
            passed = 0  # workers at the group's head that tell nothing (see above)
            while (group := self._free.get(tags)) is not None:
                head = next(itertools.islice(group, passed, None), None)
                if head is None:
                    break
                if reachable is not None and not reachable(head):
                    passed += 1
                    continue
                new += self.assign(head, owns)
                if head in group:  # room left: no task it may take
                    if self.eligible_tags(head) is not None:
                        dry.append(tags)
                        break
                    passed += 1
        return new

    def record(self, worker_id: str) -> WorkerRecord:
        record = self.records.get(worker_id)  # asked per assignment: no record made for naught
        if record is None:
            record = self.records[worker_id] = WorkerRecord()
        return record

    def eligible_tags(self, worker_id: str) -> frozenset[str] | None:
        """The worker's tags when they alone decide which jobs it may render (it is active,
        responsive and no job keeps it off), else None. A worker with these tags that was
        assigned nothing tells that any worker whose tags are a subset of them would be
        assigned nothing either, until the next change."""
        slot = self.workers.get(worker_id)
        if slot is None or slot.unresponsive or self.record(worker_id).mode != "active":
            return None
        if any(worker_id in j.excluded_workers for j in self.jobs.values()):
            return None
        return slot.tags

    def worker_state(self, worker_id: str) -> str:
        """active, draining, drained (draining with no task left) or disabled."""
        mode = self.record(worker_id).mode
        slot = self.workers.get(worker_id)
        if mode == "draining" and (slot is None or not slot.leases):
            return "drained"
        return mode

    def set_worker_mode(self, worker_id: str, mode: str) -> list[Lease]:
        """Drain, disable or enable a worker. Disabling hands its tasks back at once (they are
        re-queued for other workers and cancelled on it); returns the leases handed back."""
        if mode not in WORKER_MODES:
            raise ValueError(f"unknown worker mode {mode!r}")
        self.record(worker_id).mode = mode
        slot = self.workers.get(worker_id)
        if mode != "disabled" or slot is None:
            return []
        back = list(slot.leases.values())
        for lease in back:
            self._release(lease, requeue=True)
            self.cancellations.setdefault(worker_id, []).append(lease.task_id)
        return back

    def remove_worker(self, worker_id: str) -> list[Lease]:
        """A worker left (stream closed): hand its leases back to their tiles."""
        slot = self.workers.pop(worker_id, None)
        if slot is None:
            return []
        self._room_changed(slot, gone=True)
        lost = list(slot.leases.values())
        for lease in lost:
            self._release(lease, requeue=True)
        self.cancellations.pop(worker_id, None)
        for job in self.jobs.values():
            self._check_renderable(job)
        return lost

    def set_credit(self, worker_id: str, credit: int) -> bool:
        """The number of tasks the worker wants leased at once, from now on; True if it grew
        (the caller then assigns). Leases over a lowered credit run to their end."""
        slot = self.workers.get(worker_id)
        if slot is None or credit == slot.credit:
            return False
        grew = credit > slot.credit
        slot.credit = max(1, credit)
        self._room_changed(slot)
        return grew

    def heartbeat(self, worker_id: str) -> None:
        """A heartbeat extends every lease of the worker."""
        slot = self.workers.get(worker_id)
        if slot is None:
            return
        slot.unresponsive = False
        deadline = self.clock() + self.lease_s
        for lease in slot.leases.values():
            lease.deadline = deadline

    def expire_leases(self) -> list[Lease]:
        """Re-queue the batches of leases past their deadline (hung or cut-off workers)."""
        now = self.clock()
        expired = [lease for lease in self.leases.values() if lease.deadline < now]
        for lease in expired:
            slot = self.workers.get(lease.worker_id)
            if slot is not None:
                slot.unresponsive = True
            self._release(lease, requeue=True)
            self.cancellations.setdefault(lease.worker_id, []).append(lease.task_id)
        self.leases_expired += len(expired)
        return expired

    def tick(self) -> None:
        """Apply time limits and expire leases; call about once a second."""
        now = self.clock()
        for job in list(self.jobs.values()):
            limit = job.settings.time_limit_s
            live = job.state in (JobState.QUEUED, JobState.RUNNING)  # a pause stops the clock
            if job.started is not None and live and limit > 0:
                if now - job.started >= limit:
                    for tile in job.tiles:
                        if not tile.stopped:
                            self._stop_tile(job, tile, StopReason.TIME_LIMIT)
                    self._maybe_finish(job)
        self.expire_leases()

    # ------------------------------------------------------------------------- dispatch
    def assign(self, worker_id: str, owns: Callable[[str], bool] | None = None) -> list[Lease]:
        """Lease tasks to the worker up to its credit; returns the new leases. owns(job_id):
        whether this server may lease the job's tasks (None: every job)."""
        slot = self.workers.get(worker_id)
        if slot is None or self.record(worker_id).mode != "active":
            return []  # a draining or disabled worker takes no new task
        if slot.unresponsive:
            return []  # its last lease expired: nothing more until it is heard from
        new: list[Lease] = []
        while len(slot.leases) < slot.credit:
            lease = self._next_task(slot, owns)
            if lease is None:
                break
            new.append(lease)
        return new

    def _job_order(self, worker_id: str, owns: Callable[[str], bool] | None = None) -> list[JobRun]:
        """Priority first, then fair share (fewest leases out), then submission order; only
        the jobs whose required tags the worker has (and that `owns` accepts, when given)."""
        slot = self.workers.get(worker_id)
        tags = slot.tags if slot is not None else frozenset()
        live = [
            j
            for j in self.jobs.values()
            if j.state in (JobState.QUEUED, JobState.RUNNING)  # not paused, waiting, finished
            and worker_id not in j.excluded_workers
            and j.requires <= tags
            and (owns is None or owns(j.job_id))
        ]
        return sorted(live, key=lambda j: (-j.settings.priority, j.leased, j.created))

    def _next_task(
        self, slot: WorkerSlot, owns: Callable[[str], bool] | None = None
    ) -> Lease | None:
        for job in self._job_order(slot.worker_id, owns):
            pick = self._pick_tile_batch(job)
            if pick is not None:
                tile, batch = pick
                return self._lease(job, tile, batch, slot)
        return None

    def _pick_tile_batch(self, job: JobRun) -> tuple[TileState, int] | None:
        """The dispatch candidate with the smallest key (see _tile_key)."""
        heap = job.heap
        while heap:
            _, stamp, index = heap[0]
            tile = job.tiles[index]
            if stamp != tile.stamp:
                heapq.heappop(heap)  # stale: the tile changed since this entry was pushed
                continue
            batch = min(tile.requeue) if tile.requeue else tile.next_batch
            return tile, batch
        return None

    def _tile_key(self, job: JobRun, tile: TileState) -> tuple | None:
        """Dispatch order of a tile, or None when it has nothing to lease.

        Tiles with no work out come first (depth), then the earliest frame of an animation (so
        the first frame previews first and frames are filled in order: a frame's tiles go
        before the next frame's whenever they have work), then the largest error x cost (tiles
        never merged count as infinitely noisy, so a full-frame preview comes first), then the
        fewest merged batches, then the tile index. Deeper tiles are leased speculatively only
        when no tile is idle."""
        if tile.stopped:
            return None
        span = self._span(job, tile, min(tile.requeue) if tile.requeue else tile.next_batch)
        if span is None or span[1] == 0:  # not planned yet, or past max_spp
            return None
        depth = len(tile.in_flight) + len(tile.pending)
        if depth > SPECULATION_DEPTH:
            return None
        cost = tile.seconds_per_sample or (job.cost_sum / job.cost_count if job.cost_count else 1.0)
        urgency = tile.error * cost if math.isfinite(tile.error) else math.inf
        return (depth, tile.slot, -urgency, tile.merged, tile.index)

    # ------------------------------------------------------------------- batch planning
    def _span(self, job: JobRun, tile: TileState, batch: int) -> tuple[int, int] | None:
        """(first sample index, samples per pixel) of a batch of this tile; count 0 when the
        batch lies past max_spp, None while its size is not planned yet."""
        if batch < PLANNED_FROM or job.settings.noise_threshold <= 0:
            return batch_range(batch, job.settings.max_spp)
        count = tile.plan.get(batch)
        return None if count is None else (batch_start(batch), count)

    def _plan(
        self, job: JobRun, tile: TileState, batch: int, before: int, record: bool = True
    ) -> None:
        s = job.settings
        if batch >= PLANNED_FROM and s.noise_threshold > 0 and batch not in tile.plan:
            error = tile.error
            if tile.acc.pixel_adaptive:
                # Which pixels render the batch, and its size from theirs: the median of their
                # smoothed errors (none renders it: no batch).
                self._use(tile)
                error = pixel_stops.stop_pixels(
                    tile.acc, s.noise_threshold, s.min_spp, batch, s.noise_metric,
                    mse=s.adaptive == "pixel_mse",
                )  # fmt: skip
            if error is None:
                count, error = 0, math.inf
            else:
                count = plan_batch(
                    tile.acc.samples, error, s.noise_threshold, s.min_spp, s.max_spp, before
                )
            tile.plan[batch] = count
            if record:
                error = error if math.isfinite(error) else None
                tile.basis[batch] = (count, tile.acc.samples, error, before)

    def _plan_ahead(self, job: JobRun, tile: TileState) -> None:
        """Plan batch merged + 1 from the merged state (called after each in-order merge)."""
        if tile.stopped:
            return
        following = self._span(job, tile, tile.merged)
        if following is not None:
            self._plan(job, tile, tile.merged + 1, tile.acc.samples + following[1])

    @staticmethod
    def planned_batches(tile: TileState) -> list[int]:
        """The planned sizes of the batches from max(merged, PLANNED_FROM) on, in order: what a
        checkpoint saves so that a resumed job renders the same batches."""
        first = max(tile.merged, PLANNED_FROM)
        counts = []
        while first + len(counts) in tile.plan:
            counts.append(tile.plan[first + len(counts)])
        return counts

    @staticmethod
    def plan_basis(tile: TileState) -> list[list]:
        """[batch, count, samples, error or None, before] of every recorded planned batch, in
        batch order: what a checkpoint saves for continue_plan."""
        return [[b, *tile.basis[b]] for b in sorted(tile.basis)]

    def _touch(self, job: JobRun, tile: TileState) -> None:
        """Re-file a tile after any change to it (O(log n); old entries go stale)."""
        tile.stamp += 1
        key = self._tile_key(job, tile)
        if key is not None:
            heapq.heappush(job.heap, (key, tile.stamp, tile.index))
        if len(job.heap) > 4 * len(job.tiles) + 64:  # drop stale entries now and then
            job.heap = [e for e in job.heap if e[1] == job.tiles[e[2]].stamp]
            heapq.heapify(job.heap)

    def _lease(self, job: JobRun, tile: TileState, batch: int, slot: WorkerSlot) -> Lease:
        start, count = self._span(job, tile, batch)
        active, pixels = b"", tile.rect.pixels
        if tile.acc.pixel_adaptive and batch >= PLANNED_FROM:
            self._use(tile)
            mask = tile.acc.active_pixels(batch)
            if not mask.all():  # one bit a pixel, row-major, least significant first
                active = np.packbits(mask.ravel(), bitorder="little").tobytes()
                pixels = int(np.count_nonzero(mask))
        lease = Lease(
            task_id=f"t{next(self._task_ids)}",
            job_id=job.job_id,
            tile_index=tile.index,
            batch_index=batch,
            sample_start=start,
            sample_count=count,
            rect=tile.rect,
            worker_id=slot.worker_id,
            deadline=self.clock() + self.lease_s,
            active=active,
            pixels=pixels,
        )
        tile.requeue.discard(batch)
        tile.next_batch = max(tile.next_batch, batch + 1)
        tile.in_flight[batch] = lease.task_id
        slot.leases[lease.task_id] = lease
        self._room_changed(slot)
        self.leases[lease.task_id] = lease
        job.leased += 1
        self._touch(job, tile)
        if job.state == JobState.QUEUED:
            self._transition(job, JobState.RUNNING, "job_started", {})
            job.started = self.clock() - job.elapsed_before
        return lease

    def _release(self, lease: Lease, requeue: bool) -> None:
        self.leases.pop(lease.task_id, None)
        slot = self.workers.get(lease.worker_id)
        if slot is not None:
            slot.leases.pop(lease.task_id, None)
            self._room_changed(slot)
        job = self.jobs.get(lease.job_id)
        if job is None:
            return
        job.leased -= 1
        tile = job.tiles[lease.tile_index]
        if tile.in_flight.get(lease.batch_index) == lease.task_id:
            del tile.in_flight[lease.batch_index]
            if requeue and not tile.stopped and lease.batch_index >= tile.merged:
                if lease.batch_index not in tile.pending:
                    tile.requeue.add(lease.batch_index)
            self._touch(job, tile)

    # -------------------------------------------------------------------------- results
    def complete(self, task_id: str, result: BatchResult) -> str:
        """Take a result. Returns "merged", "pending" (waits for earlier batches) or why it
        was discarded ("duplicate", "tile stopped", "unknown job", "mismatch: ...").

        A mismatched result of a live lease counts as a failure of its task (failed()): the
        batch is leased again, and a worker that keeps sending bad results is kept off the job."""
        lease = self.leases.get(task_id)
        job = self.jobs.get(result.job_id)
        if job is None or job.state.finished:
            if lease is not None:
                self._release(lease, requeue=False)
            return "unknown job"
        if not 0 <= result.tile_index < len(job.tiles):
            problem = "tile index"
        else:
            tile = job.tiles[result.tile_index]
            problem = self._check_shape(job, tile, result)
        if problem:
            if lease is not None:
                self.failed(task_id, f"result refused: {problem}", retryable=True)
            return "mismatch: " + problem
        if lease is not None:
            self._release(lease, requeue=False)
        if result.render_seconds > 0:
            cost = result.render_seconds / (result.sample_count * tile.rect.pixels)
            if tile.seconds_per_sample == 0:
                job.cost_sum += cost
                job.cost_count += 1
                tile.seconds_per_sample = cost
            else:
                new = 0.7 * tile.seconds_per_sample + 0.3 * cost
                job.cost_sum += new - tile.seconds_per_sample
                tile.seconds_per_sample = new
        if tile.stopped:
            return "tile stopped"
        b = result.batch_index
        if b < tile.merged or b in tile.pending:
            return "duplicate"
        tile.requeue.discard(b)
        # A re-leased copy of this batch is now redundant.
        other = tile.in_flight.pop(b, None)
        if other is not None and other in self.leases:
            redundant = self.leases[other]
            self._release(redundant, requeue=False)
            self.cancellations.setdefault(redundant.worker_id, []).append(other)
        tile.pending[b] = result
        outcome = "pending"
        while tile.merged in tile.pending and not tile.stopped:
            self._use(tile)
            r = tile.pending.pop(tile.merged)
            tile.aovs_dirty |= carries_aovs(r.sample_start)
            spp_sum = tile.acc.spp_sum
            tile.error = tile.acc.merge_batch(
                r.rgb_sum, r.luminance_m2, r.sample_count, r.albedo_sum, r.normal_sum, r.nonfinite,
                r.coverage_sum, r.extra,
            )  # fmt: skip
            if job.settings.noise_metric != "relative":
                tile.error = pixel_stops.tile_error(tile.acc, job.settings.noise_metric)
            job.samples_merged += int(tile.acc.spp_sum - spp_sum)
            self._record_merge(job)
            tile.dirty = True
            outcome = "merged" if r is result or outcome == "merged" else outcome
            self._decide_stop(job, tile)
            self._plan_ahead(job, tile)
        self._touch(job, tile)
        job.version += 1
        self._maybe_finish(job)
        return outcome

    def _record_merge(self, job: JobRun) -> None:
        """A point of the ETA's rate window; points older than the window are dropped, but the
        last one before it stays as the window's start (and at least two stay)."""
        now = self.clock()
        job.merges.append((now, job.samples_merged))
        while len(job.merges) > 2 and job.merges[1][0] <= now - ETA_WINDOW_S:
            job.merges.popleft()

    def _check_shape(self, job: JobRun, tile: TileState, r: BatchResult) -> str:
        span = self._span(job, tile, r.batch_index)
        if span is None or span[1] == 0:
            return f"batch {r.batch_index} is not part of the tile's plan"
        if (r.sample_start, r.sample_count) != span:
            return f"batch {r.batch_index} covers samples {span[0]}+{span[1]}"
        if r.rect != tile.rect:
            return "tile rectangle"
        if r.rgb_sum.size != tile.rect.pixels * 3 or r.luminance_m2.size != tile.rect.pixels:
            return "array sizes"
        # A NaN or infinity would poison the tile's sums for good (workers count non-finite
        # samples and send zeros in their place).
        if not (all_finite(r.rgb_sum) and all_finite(r.luminance_m2)):
            return "non-finite values"
        # The rows the job turned on beyond those every result carries (grpc_decode checks
        # those): present, of the tile's size and finite.
        for row in tile.acc.layout.wire_rows_for(r.sample_start):
            if row.name in _EVERY_RESULT:
                continue
            values = r.extra.get(row.wire)
            if values is None:
                return f"channel {row.name} missing"
            if values.size != tile.rect.pixels * row.wire_components:
                return f"channel {row.name}: array size"
            if not all_finite(values):
                return f"channel {row.name}: non-finite values"
        return ""

    def _decide_stop(self, job: JobRun, tile: TileState) -> None:
        """The stop rule; uses only this tile's merged batches (0..merged-1)."""
        s = job.settings
        n = tile.acc.samples
        if n >= s.max_spp:
            self._stop_tile(job, tile, StopReason.MAX_SPP)
        elif tile.acc.pixel_adaptive:
            # Per pixel: the tile stops when none of its pixels renders the next batch
            # (stop_pixels decided that from batches 0..merged-2).
            if not tile.acc.active_pixels(tile.merged).any():
                self._stop_tile(job, tile, StopReason.CONVERGED)
        elif s.noise_threshold > 0 and n >= s.min_spp and tile.error < s.noise_threshold:
            self._stop_tile(job, tile, StopReason.CONVERGED)

    def _stop_tile(self, job: JobRun, tile: TileState, reason: StopReason) -> None:
        job.tiles_stopped += 1
        job.frame_tiles_stopped[tile.slot] += 1
        tile.stop = StopRecord(tile.index, tile.merged - 1, tile.acc.samples, tile.error, reason)
        tile.dirty = True
        tile.pending.clear()
        tile.requeue.clear()
        for task_id in list(tile.in_flight.values()):
            lease = self.leases.get(task_id)
            if lease is not None:
                self._release(lease, requeue=False)
                self.cancellations.setdefault(lease.worker_id, []).append(task_id)
        tile.in_flight.clear()
        self._touch(job, tile)
        job.version += 1
        self.events.append(
            Event(
                "tile_stopped",
                job.job_id,
                {
                    "tile": tile.index,
                    "batch": tile.stop.batch_index,
                    "spp": tile.stop.spp,
                    "error": tile.stop.error,
                    "reason": reason.value,
                    **self._image_place(job, tile.slot),
                },
            )
        )
        if job.frames is not None and job.frame_tiles_stopped[tile.slot] == job.tiles_per_frame:
            frame = self.frame_progress(job, tile.slot)
            self.events.append(
                Event(
                    "frame_finished",
                    job.job_id,
                    {
                        **self._image_place(job, tile.slot),
                        "spp": frame.mean_spp,
                        "error": frame.error,
                    },
                )
            )

    def _maybe_finish(self, job: JobRun) -> None:
        if not job.state.finished and job.tiles_stopped == len(job.tiles):
            self._finish(job, JobState.COMPLETED)

    def _finish(self, job: JobRun, state: JobState) -> None:
        check_transition(job.state, state)
        if job.state == JobState.QUEUED and state == JobState.COMPLETED:
            job.started = self.clock() - job.elapsed_before
        if job.state == JobState.PAUSED and job.paused_at is not None and job.started is not None:
            job.started += self.clock() - job.paused_at  # time paused is not elapsed time
        old = job.state
        job.state = state
        job.finished = self.clock()
        job.version += 1
        for tile in job.tiles:
            if state == JobState.CANCELLED and not tile.stopped:
                tile.requeue.clear()
                tile.pending.clear()
            for task_id in list(tile.in_flight.values()):
                lease = self.leases.get(task_id)
                if lease is not None:
                    self._release(lease, requeue=False)
                    self.cancellations.setdefault(lease.worker_id, []).append(task_id)
            tile.in_flight.clear()
        job.heap.clear()  # a finished job leases nothing more
        self.events.append(
            Event(
                "job_finished",
                job.job_id,
                {"state": state.value, "error": job.error_message, "from": old.value},
            )
        )

    # ------------------------------------------------------------------------- failures
    def failed(self, task_id: str, error: str, retryable: bool) -> None:
        """A worker could not render a task: re-queue it; after max_task_failures failures (or
        one non-retryable one) keep that worker off the job; fail the job when no connected
        worker may render it."""
        lease = self.leases.get(task_id)
        if lease is None:
            return
        self._release(lease, requeue=True)
        record = self.record(lease.worker_id)
        record.tasks_failed += 1
        record.errors.append(error[:500])
        job = self.jobs.get(lease.job_id)
        if job is None or job.state.finished:
            return
        count = job.failures.get(lease.worker_id, 0) + 1
        job.failures[lease.worker_id] = count
        where = self._task_place(job, lease.tile_index, lease.batch_index)
        self.events.append(
            Event("task_failed", job.job_id,
                  {"worker": lease.worker_id, "error": error, "retryable": retryable, **where})
        )  # fmt: skip
        if not retryable or count >= self.max_task_failures:
            job.excluded_workers.add(lease.worker_id)
            job.error_message = error
            self.events.append(
                Event("worker_excluded", job.job_id, {"worker": lease.worker_id, "error": error})
            )
            self._check_renderable(job)

    @staticmethod
    def _image_place(job: JobRun, slot: int) -> dict[str, int | str]:
        """The image a tile belongs to, as events name it: the frame of an animation, the
        variant (its index as the frame, and its name) of a job of every variant; {} for a
        still."""
        if job.frames is None:
            return {}
        if job.variants:
            return {"frame": slot, "variant": job.variants[slot]}
        return {"frame": job.frames[slot]}

    @classmethod
    def _task_place(cls, job: JobRun, tile_index: int, batch_index: int) -> dict[str, int | str]:
        """Where a task was: its tile (and batch), and the frame of an animation (or the
        variant)."""
        where: dict[str, int | str] = {"tile": tile_index, "batch": batch_index}
        if 0 <= tile_index < len(job.tiles):
            where.update(cls._image_place(job, job.tiles[tile_index].slot))
        return where

    def task_warnings(self, worker_id: str, result: BatchResult) -> None:
        """Record what a worker said about a task (its scene loader's warnings) in the job's
        task log: a task_warning event per message the job has not logged yet, at most
        TASK_LOG_MAX of them (then one saying that later ones are left out)."""
        if not result.warnings:  # nearly every result: nothing to look up
            return
        job = self.jobs.get(result.job_id)
        if job is None or job.state.finished:
            return
        for message in result.warnings:
            if message in job.warnings_logged or len(job.warnings_logged) > TASK_LOG_MAX:
                continue
            job.warnings_logged.add(message)
            if len(job.warnings_logged) > TASK_LOG_MAX:
                message = f"more than {TASK_LOG_MAX} warnings: later ones are not recorded"
            data = {"worker": worker_id, "message": message}
            data |= self._task_place(job, result.tile_index, result.batch_index)
            self.events.append(Event("task_warning", job.job_id, data))

    def _check_renderable(self, job: JobRun) -> None:
        if job.state.finished or not job.excluded_workers:
            return
        if self.workers and all(w in job.excluded_workers for w in self.workers):
            self.fail_job(job.job_id, f"no worker can render this job: {job.error_message}")

    # ---------------------------------------------------------------------------- drain
    def take_events(self) -> list[Event]:
        events, self.events = self.events, []
        return events

    def take_cancellations(self, worker_id: str) -> list[str]:
        return self.cancellations.pop(worker_id, [])
