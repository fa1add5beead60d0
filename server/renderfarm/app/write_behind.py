"""Database writes that must not block merging: events, finished jobs and checkpoints are
written by FarmService's background task (flush), retried with exponential backoff while the
database is away; a finished job is reported finished only once stored; what a stopping server
could not write goes to the spool (infra/spool.py).

In a farm of several servers every write of a job's owner carries its fence (ownership.fence:
replica and epoch); one the database refuses (LeaseLost: another server holds the job now)
drops the job here (FarmService._drop_lost) rather than being retried.
"""

from __future__ import annotations

import asyncio
import logging
import time
from typing import Any

import psycopg
from psycopg_pool import PoolTimeout

from ..domain.records import JobRun
from ..domain.states import JobState
from ..errors import LeaseLost
from ..infra import spool
from ..infra.store import DatabaseUnavailable
from . import checkpoints
from .views import finite_or_none

log = logging.getLogger(__name__)


STORED_WAIT_S = 5.0  # how long a cancel waits for its final state to be stored


class WriteBehind:
    """Part of FarmService (jobs.py), whose __init__ sets the attributes used here."""

    async def flush(self, force: bool = False) -> bool:
        """Write pending events, finished jobs and due checkpoints. While the database is away
        this keeps everything in memory and tries again with exponential backoff (0.5 s
        doubling to 10 s); merging and serving workers go on meanwhile. True when all written."""
        now = self.clock()
        if not force and now < self._db_retry_at:
            return False
        try:
            # Both lists are taken at one instant: _after_change extends them together, so
            # every finish taken here has its job_finished event in the batch, which is written
            # first: a job is never stored as finished before its event. What arrives during
            # the writes is written by the next pass (a few passes at most, so a steady stream
            # of events cannot hold the background round here).
            for _ in range(4):
                batch = list(self._pending_events)
                finishes = len(self._pending_finishes)
                if not batch and not finishes:
                    break
                if batch:
                    lost: list[str] = []
                    try:
                        await self.store.add_events(batch, self._event_fences(batch))
                    except LeaseLost as e:  # the others of the batch are written
                        lost = e.job_ids
                    del self._pending_events[: len(batch)]
                    for job_id in lost:
                        self._drop_lost(job_id)
                for _ in range(finishes):
                    if not self._pending_finishes:
                        break  # dropped: another server owns it now
                    job_id = self._pending_finishes[0]
                    try:
                        await self._persist_job(job_id, tiles=True)
                        points = self.history.get(job_id, [])
                        await self.store.add_events(
                            [(job_id, "convergence", {"points": points})],
                            self._event_fences([(job_id, "", {})]),
                        )
                    except LeaseLost:
                        self._drop_lost(job_id)
                        continue
                    self._pending_finishes.pop(0)
                    await self.ownership.release(job_id)  # its final state is stored
                    self._forget_later(job_id)
                    await self._announce_stored(job_id)
                    self._waiting_dirty = True  # a job waiting for this one may go now
            if force or now - self._last_checkpoint >= self.settings.checkpoint_interval_s:
                await self.checkpoint(force=force)
        except (psycopg.Error, PoolTimeout, OSError) as e:
            self.db_errors += 1
            self._db_failures += 1
            self.database_ok = False
            delay = min(10.0, 0.5 * 2 ** (self._db_failures - 1))
            self._db_retry_at = self.clock() + delay
            log.warning("database write failed (%s); retrying in %.1f s", e, delay)
            return False
        if not self.database_ok:
            log.info("database writes caught up")
        self._db_failures = 0
        self.database_ok = True
        return True

    async def drain(self, timeout_s: float) -> None:
        """Stop leasing and wait for the tasks in flight to come back, while the last
        checkpoint would still be written within timeout_s (by the measured checkpoint rate)."""
        self.draining = True
        deadline = time.monotonic() + timeout_s
        while self.scheduler.leases and time.monotonic() + self._final_checkpoint_s() < deadline:
            await asyncio.sleep(0.1)
        if self.scheduler.leases:
            log.warning("drain timed out with %d tasks in flight", len(self.scheduler.leases))

    def _final_checkpoint_s(self) -> float:
        """Estimated seconds the last checkpoint needs for the tiles merged since the last
        one, from the measured rate (plus a margin for the job rows and the commit)."""
        dirty = [t for job in self.scheduler.jobs.values() for t in job.tiles if t.dirty]
        return 0.5 + checkpoints.dirty_bytes(dirty) / self._checkpoint_rate.value

    async def checkpoint(self, force: bool = False) -> None:
        """Write every tile merged since the last checkpoint, and each live job's progress.

        Under very heavy merge load a checkpoint can take a while to serialise; the next one
        then waits at least 4x as long as this one took, so checkpoints never take more than
        about a fifth of the server's time (the interval setting is a target, not a promise)."""
        started = self.clock()
        for job in list(self.scheduler.jobs.values()):
            if job.state.finished and not force:
                continue
            if not self.ownership.owns(job.job_id):
                continue  # its owner writes it (collaborators.Ownership)
            try:
                await self._persist_job(job.job_id, tiles=True)
            except LeaseLost:
                self._drop_lost(job.job_id)
        took = self.clock() - started
        self._last_checkpoint = started + max(0.0, 4 * took - self.settings.checkpoint_interval_s)

    async def _persist_job(self, job_id: str, tiles: bool) -> None:
        job = self.scheduler.jobs.get(job_id)
        if job is None:
            return
        # Snapshots are taken here, on the loop (cheap: accumulators are copy-on-write); the
        # bytes are made in a worker thread so merging is not stalled by large checkpoints.
        # A chunk at a time (one transaction each): a snapshot keeps alive the arrays that
        # merges replace meanwhile, and its bytes are a copy, so a large job's checkpoint
        # holds at most a chunk of them.
        for chunk in checkpoints.chunks([t for t in job.tiles if t.dirty] if tiles else []):
            snapshots, taken = [], []  # taken: (tile, whether its AOVs were snapshotted too)
            for t in chunk:
                if t.dirty:
                    snapshots.append(checkpoints.tile_snapshot(t, t.aovs_dirty))
                    taken.append((t, t.aovs_dirty))
                    t.dirty = t.aovs_dirty = False
            started = time.monotonic()
            try:
                rows = await asyncio.to_thread(
                    lambda s=snapshots: [checkpoints.tile_row(*x) for x in s]
                )
                await self.store.save_tiles(job_id, rows, fence=self.ownership.fence(job_id))
            except BaseException:
                # Not written (a database error, or the task cancelled mid-checkpoint by
                # stop(), whose final checkpoint must then write these tiles): write them again.
                for t, aovs in taken:
                    t.dirty = True
                    t.aovs_dirty |= aovs
                raise
            self._checkpoint_rate.add(
                checkpoints.dirty_bytes(chunk, taken), time.monotonic() - started
            )
        await self.store.update_job(
            job_id, **self._job_fields(job), fence=self.ownership.fence(job_id)
        )

    def _event_fences(self, events: list[tuple[str | None, str, Any]]) -> dict[str, Any]:
        """The fences of the events' jobs that this server holds (an owner's events); the
        events of other jobs (an update of a finished job, which no one holds) go unfenced."""
        fences = {}
        for job_id, _, _ in events:
            if job_id and job_id not in fences and self.ownership.epoch(job_id) >= 0:
                fence = self.ownership.fence(job_id)
                if fence is not None:
                    fences[job_id] = fence
        return fences

    def _job_fields(self, job: JobRun) -> dict[str, Any]:
        """The job row's columns that change (Store.update_job's arguments)."""
        p = self.scheduler.progress(job)
        return {
            "state": job.state.value,
            "error": job.error_message if job.state == JobState.FAILED else "",
            "started": job.started,
            "finished": job.finished,
            "elapsed_s": p.elapsed_s,
            "samples_merged": p.samples_merged,
            "mean_spp": p.mean_spp,
            "error_estimate": finite_or_none(p.error),
            "tiles_done": p.tiles_done,
            "tiles_previewed": p.tiles_previewed,
            "frames_done": p.frames_done,
        }

    def _reported_state(self, job: JobRun) -> JobState:
        """The state the APIs show: a finished job whose final state is not stored yet is
        shown as it was before (a restart would resume it from the database)."""
        if job.state.finished and job.job_id in self._pending_finishes:
            return JobState.RUNNING if job.started is not None else JobState.QUEUED
        return job.state

    async def _announce_stored(self, job_id: str) -> None:
        """A job's final state was stored: watchers and waiting cancels see it now."""
        job = self.scheduler.jobs.get(job_id)
        if job is not None:
            job.version += 1
        self._changed.notify()

    async def _until_stored(self, job_id: str) -> None:
        """Wait for the background writer to store a finished job's final state; while the
        database does not take it the caller is told to retry (DatabaseUnavailable)."""
        try:
            await self._changed.wait_for(
                lambda: job_id not in self._pending_finishes, timeout=STORED_WAIT_S
            )
        except TimeoutError:
            raise DatabaseUnavailable(
                f"database unavailable: job {job_id} is stopped, but its final state is "
                "not stored yet"
            ) from None

    def _spool_unsaved(self) -> None:
        """The final flush failed: keep whatever is not stored in the spool, replayed at the
        next start (infra/spool.py). Synchronous, so no merge lands between snapshot and file."""
        events = list(self._pending_events)
        for job_id in self._pending_finishes:  # what flush() writes after a finished job
            events.append((job_id, "convergence", {"points": self.history.get(job_id, [])}))
        jobs = []
        for job in self.scheduler.jobs.values():
            if job.state.finished and job.job_id not in self._pending_finishes:
                continue  # stored already
            tiles = [
                checkpoints.tile_row(*checkpoints.tile_snapshot(t, t.aovs_dirty))
                for t in job.tiles
                if t.dirty
            ]
            fence = self.ownership.fence(job.job_id)
            jobs.append(spool.UnsavedJob(job.job_id, self._job_fields(job), tiles, fence))
        try:
            path = spool.write(
                spool.spool_dir(self.settings.data_dir), events, jobs, self._event_fences(events)
            )
        except OSError as e:
            log.error(
                "could not write the last checkpoint, nor the spool (%s); up to the checkpoint "
                "interval of merged work will be rendered again after a restart",
                e,
            )
            return
        log.warning(
            "the database is unreachable: kept the unsaved state of %d job%s in %s; it is "
            "written to the database at the next start",
            len(jobs), "" if len(jobs) == 1 else "s", path,
        )  # fmt: skip


class CheckpointRate:
    """Checkpoint bytes per second: a running mean over recent writes, for the drain's
    estimate of how long the last checkpoint will take."""

    def __init__(self, initial: float):
        self.value = initial

    def add(self, nbytes: int, seconds: float) -> None:
        if nbytes > 1 << 20 and seconds > 0:  # small writes measure latency, not throughput
            self.value = 0.7 * self.value + 0.3 * nbytes / seconds
