"""FarmService: the one place where API calls, worker streams, the scheduler and the store meet.

Everything runs on one asyncio event loop: the scheduler is plain Python without locks, merges
are vectorised numpy on tiles (tens of microseconds), and every database call is awaited, so a
slow database never blocks a merge. REST and gRPC handlers are thin: they parse, call a method
here, and map the errors below to status codes.

Durability: a submission is acknowledged only after its scene and job rows are committed. Merged
tiles are checkpointed every `checkpoint_interval_s` by a background task (only tiles that
changed), and immediately when a job finishes. On start, unfinished jobs resume from their
checkpoints. A finished job is reported finished only once its final state is stored (until
then a restart would resume it); a server stopped while the database is unreachable keeps what
it could not write in its spool (spool.py) and writes it at its next start.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import importlib.metadata
import json
import logging
import math
import os
import secrets
import tempfile
import threading
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
import psycopg
from psycopg_pool import PoolTimeout

from ..domain.jobspec import ALIASES, JobSettings, parse_settings
from ..domain.merge import TileAccumulator
from ..domain.scenes.validate import inspect_environment, inspect_scene
from ..domain.scheduler import (
    CONTINUE_SETTINGS,
    BatchResult,
    JobRun,
    Lease,
    Scheduler,
    continue_plan,
)
from ..domain.states import JobState, StopReason, check_transition
from ..domain.tiling import Rect, tile_grid
from ..errors import (
    Conflict,
    Forbidden,
    NotFound,
    SceneError,
    SettingsError,
    TooLarge,
    TransitionError,
    Unauthenticated,
)
from ..infra import images, spool
from ..infra.config import Settings
from ..infra.scene_check import SceneChecker
from ..infra.spill import TileCache
from ..infra.store import DatabaseUnavailable, JobRow, Store, TileRow
from .auth import Caller

log = logging.getLogger(__name__)

SCENE_CHUNK_BYTES = 1 << 20
STORED_WAIT_S = 5.0  # how long a cancel waits for its final state to be stored
MAX_IMAGE_SIZE = 1 << 16  # largest max_size of a PNG preview


@dataclass(frozen=True)
class ProgressView:
    tiles_total: int
    tiles_done: int
    tiles_previewed: int
    mean_spp: float
    error: float | None
    eta_s: float | None
    samples_merged: int
    elapsed_s: float


@dataclass(frozen=True)
class JobView:
    """A job as the APIs show it (REST JSON and the gRPC Job message are built from this)."""

    id: str
    name: str
    state: JobState
    settings: JobSettings
    scene_sha256: str
    progress: ProgressView
    error: str
    created_unix_s: float
    finished_unix_s: float | None
    owner: str = ""
    after: tuple[str, ...] = ()  # ids of the jobs it waits for
    require_tags: tuple[str, ...] = ()  # only workers with all these tags render it

    def to_json(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "name": self.name,
            "state": self.state.value,
            "settings": self.settings.to_dict(),
            "scene_sha256": self.scene_sha256,
            "progress": self.progress.__dict__,
            "error": self.error,
            "created_unix_s": self.created_unix_s,
            "finished_unix_s": self.finished_unix_s,
            "owner": self.owner,
            "after": list(self.after),
            "require_tags": list(self.require_tags),
        }


@dataclass
class WorkerSession:
    worker_id: str
    hostname: str
    cores: int
    version: str
    outbox: asyncio.Queue = field(default_factory=asyncio.Queue)
    connected_unix_s: float = field(default_factory=time.time)
    last_heartbeat_unix_s: float = field(default_factory=time.time)
    samples_per_s: float = 0.0
    rays_per_s: float = 0.0
    busy_threads: int = 0
    tags: tuple[str, ...] = ()  # announced in its Hello (--tag)
    tasks_done: int = 0


def _finite_or_none(x: float) -> float | None:
    return x if math.isfinite(x) else None


class FarmService:
    def __init__(self, settings: Settings, store: Store):
        self.settings = settings
        self.store = store
        # Tiles past the RAM budget wait in DATA_DIR/scratch (spill.py), as do images being
        # written.
        cache = TileCache(settings.data_dir / "scratch", settings.tile_cache_mb * 2**20)
        self.scheduler = Scheduler(
            clock=time.time,
            lease_s=settings.lease_s,
            max_task_failures=settings.max_task_failures,
            cache=cache,
        )
        self._stopping = threading.Event()  # images being written give up when set
        # One image with a denoised layer at a time, from gathering its frame to its last row:
        # the memory checked at submission (jobspec.denoise_memory_bytes) is that of one.
        self._denoise_turn = asyncio.Lock()
        self._checkpoint_rate = _Rate(50e6)  # bytes/s; measured by every large checkpoint
        self.sessions: dict[str, WorkerSession] = {}
        self.names: dict[str, str] = {}  # job id -> name for live jobs
        self.created: dict[str, float] = {}  # job id -> created unix time for live jobs
        self.owners: dict[str, str] = {}  # job id -> owner (token name) for live jobs
        # Bumped each time a finished job comes back (retry, continue): a delayed forget of
        # its earlier run leaves the new one alone.
        self._generation: dict[str, int] = {}
        self._waiting_dirty = True  # waiting jobs' dependencies to be checked again
        self._reactivating: set[str] = set()  # retries and continues under way
        self._changed = asyncio.Condition()
        self._tasks: list[asyncio.Task] = []
        self._last_checkpoint = time.time()
        self.metrics = None  # a metrics.Metrics, set by the server
        # Writes that must reach the database but may not block merging: flushed by the
        # background task, retried with backoff while the database is away.
        self._pending_events: list[tuple[str | None, str, dict[str, Any]]] = []
        self._pending_finishes: list[str] = []
        self._db_retry_at = 0.0
        self._db_failures = 0
        self.db_errors = 0  # failed database operations since start (metrics)
        self.database_ok = True
        self.draining = False
        # Convergence history of live jobs: (elapsed s, relative error or None, mean spp).
        self.history: dict[str, list[tuple[float, float | None, float]]] = {}
        self.ready = False
        # Every new uploaded scene goes through the workers' own loader before it is stored.
        from ..infra.worker_binary import find_worker_binary  # noqa: PLC0415 (localfarm imports the client)

        self.scene_checker = SceneChecker(
            settings.scene_inspector or find_worker_binary(),
            settings.scene_limits(),
            Path(settings.data_dir) / "tmp",
        )

    # ------------------------------------------------------------------------- lifecycle
    async def start(self) -> None:
        await spool.replay(self.store, self.settings.data_dir)
        self.scheduler.cache.clear_directory()
        await self.store.mark_all_workers_disconnected()
        await self._resume_unfinished()
        self._tasks.append(asyncio.create_task(self._background(), name="farm-background"))
        self.ready = True

    async def stop(self, timeout_s: float | None = None) -> None:
        """Write the last checkpoint (within timeout_s, at least 1 s, when given: what is not
        written by then is rendered again after a restart) and let go of everything."""
        self.ready = False
        self._stopping.set()
        for task in self._tasks:
            task.cancel()
        for task in self._tasks:
            with contextlib.suppress(asyncio.CancelledError):
                await task
        try:
            timeout = None if timeout_s is None else max(1.0, timeout_s)
            written = await asyncio.wait_for(self.flush(force=True), timeout)
        except TimeoutError:
            written = False
        if not written:
            # Whatever is not stored goes to the spool, replayed at the next start; the
            # spilled tiles are read from the cache's files, which close() then removes.
            self._spool_unsaved()
        self.scheduler.cache.close()
        for session in list(self.sessions.values()):
            session.outbox.put_nowait(None)

    async def _resume_unfinished(self) -> None:
        for row in await self.store.unfinished_jobs():
            settings = JobSettings(**row.settings)
            # A chunk of tiles at a time, each put under the tile cache at once: a large job
            # comes back within the cache's RAM (the rest goes to its spill file).
            checkpoint, plans, bases, old_aovs = {}, {}, {}, []
            tiles = len(tile_grid(settings.width, settings.height, settings.tile_size))
            tile_bytes = TileAccumulator.BYTES_PER_PIXEL * settings.tile_size**2
            step = max(1, CHECKPOINT_CHUNK_BYTES // tile_bytes)
            for first in range(0, tiles, step):
                tile_rows = await self.store.load_tiles(row.id, first=first, count=step)
                for index, (_, acc) in _restore_tiles(settings, tile_rows).items():
                    self.scheduler.cache.register(row.id, acc, settings.tile_size)
                    checkpoint[index] = acc
                plans.update({t.tile_index: t.batch_plan for t in tile_rows if t.batch_plan})
                bases.update({t.tile_index: t.plan_basis for t in tile_rows if t.plan_basis})
                old_aovs += [t.tile_index for t in tile_rows if t.aovs is None and t.samples > 0]
            self.scheduler.add_job(
                row.id,
                settings,
                row.scene_sha256,
                checkpoint=checkpoint,
                plans=plans,
                bases=bases,
                state=JobState(row.state),
                elapsed_s=row.elapsed_s,
                after=tuple(row.after_jobs),
                require_tags=tuple(row.require_tags),
            )
            self.scheduler.take_events()  # the stops were recorded before the restart
            for index in old_aovs:
                # A checkpoint from before the AOVs were stored apart: the next one writes
                # them in their own column (later ones leave that column alone).
                tile = self.scheduler.jobs[row.id].tiles[index]
                tile.dirty = tile.aovs_dirty = True
            self.names[row.id] = row.name
            self.created[row.id] = row.created_at.timestamp()
            self.owners[row.id] = row.owner
            merged = sum(acc.batches for acc in checkpoint.values())
            log.info("resumed job %s from its checkpoint (%d batches merged)", row.id, merged)
        await self._after_change()

    async def _background(self) -> None:
        while True:
            await asyncio.sleep(0.25)
            try:
                self.scheduler.tick()
                self._sample_history()
                await self._after_change()
                await self.flush()
                if self._waiting_dirty:
                    await self._check_waiting()
            except asyncio.CancelledError:
                raise
            except Exception:  # keep serving; the next round retries
                log.exception("background round failed")

    async def flush(self, force: bool = False) -> bool:
        """Write pending events, finished jobs and due checkpoints. While the database is away
        this keeps everything in memory and tries again with exponential backoff (0.5 s
        doubling to 10 s); merging and serving workers go on meanwhile. True when all written."""
        now = time.time()
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
                    await self.store.add_events(batch)
                    del self._pending_events[: len(batch)]
                for _ in range(finishes):
                    job_id = self._pending_finishes[0]
                    await self._persist_job(job_id, tiles=True)
                    points = self.history.get(job_id, [])
                    await self.store.add_events([(job_id, "convergence", {"points": points})])
                    self._pending_finishes.pop(0)
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
            self._db_retry_at = time.time() + delay
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
        return 0.5 + _dirty_bytes(dirty) / self._checkpoint_rate.value

    # ---------------------------------------------------------------------------- jobs
    async def submit(
        self,
        *,
        scene_data: bytes | None,
        scene_sha256: str | None,
        filename: str,
        name: str,
        raw_settings: dict[str, Any] | None,
        environment_data: bytes | None = None,
        environment_filename: str = "",
        after: list[str] | None = None,
        caller: Caller,
        require_tags: list[str] | None = None,
    ) -> JobView:
        _check_caller(caller)
        require_tags = sorted(set(require_tags or []))
        settings = parse_settings(raw_settings, self.settings.limits())
        after = list(dict.fromkeys(after or []))  # in order, once each
        ready = await self._dependencies_ready(after, caller)
        settings = await self._environment(settings, environment_data, environment_filename)
        if scene_data is not None and scene_sha256:
            raise SettingsError("scene", "give either an uploaded scene or scene_sha256, not both")
        if scene_data is not None:
            if len(scene_data) > self.settings.max_upload_bytes:
                raise TooLarge(
                    "scene",
                    f"scene is {len(scene_data)} bytes, more than the server's limit of "
                    f"{self.settings.max_upload_bytes} bytes",
                )
            info = inspect_scene(scene_data, filename or "scene", self.settings.max_upload_bytes)
            if await self.store.get_scene_info(info.sha256) is None:
                await self.scene_checker.check(scene_data, filename or "scene", info.sha256)
            await self.store.put_scene(info.sha256, info.format, filename or "scene", scene_data)
            sha = info.sha256
        elif scene_sha256:
            sha = scene_sha256.strip().lower()
            stored = await self.store.get_scene_info(sha)
            # Environment maps share the table; only a glTF scene can be rendered as one.
            if stored is None or stored["format"] not in ("glb", "gltf"):
                raise NotFound(f"no stored scene with sha256 {sha}")
            filename = filename or stored["filename"]
        else:
            raise SettingsError(
                "scene", "a scene is required: upload a .glb/.gltf or give scene_sha256"
            )
        job_id = secrets.token_hex(6)
        name = (name or filename or "job").strip()[:200]
        tiles = len(tile_grid(settings.width, settings.height, settings.tile_size))
        state = JobState.QUEUED if ready else JobState.WAITING
        row = await self.store.insert_job(
            job_id, name, settings.to_dict(), sha, tiles, owner=caller.owner, after=after,
            state=state.value, require_tags=require_tags,
        )  # fmt: skip
        # Stored and committed: only now does the job exist for the scheduler and the caller.
        self.owners[job_id] = caller.owner
        self.names[job_id] = name
        self.created[job_id] = row.created_at.timestamp()
        self.scheduler.add_job(
            job_id, settings, sha, state=state, after=tuple(after), require_tags=tuple(require_tags)
        )
        self._waiting_dirty = True  # a dependency may have completed since it was looked at
        await self._after_change()
        return await self.get(job_id, caller)

    async def _dependencies_ready(self, after: list[str], caller: Caller) -> bool:
        """Check the jobs a submission names in `after`: each must exist and be the caller's
        to see (else 400 naming `after`, like an unknown id: another owner's jobs are not
        revealed), and must still be able to complete. True when all have completed."""
        ready = True
        for dep in after:
            try:
                view = await self.get(dep, caller)
            except (NotFound, Forbidden):
                raise SettingsError("after", f"after: no job with id {dep[:80]!r}") from None
            if view.state in (JobState.FAILED, JobState.CANCELLED):
                raise SettingsError(
                    "after", f"after: job {dep} is {view.state.value}; it will never complete"
                )
            ready &= view.state == JobState.COMPLETED
        return ready

    async def _dependency_state(self, dep: str) -> JobState | None:
        """A dependency's state as the APIs report it; None when it was deleted."""
        live = self.scheduler.jobs.get(dep)
        if live is not None:
            return self._reported_state(live)
        row = await self.store.get_job(dep)
        return None if row is None else JobState(row.state)

    async def _check_waiting(self) -> None:
        """Queue each waiting job whose dependencies have all completed; fail each one with a
        dependency that failed, was cancelled or was deleted (the reason names it)."""
        self._waiting_dirty = False
        for job in [j for j in self.scheduler.jobs.values() if j.state == JobState.WAITING]:
            problem, ready = "", True
            for dep in job.after:
                state = await self._dependency_state(dep)
                if state is None:
                    problem = f"dependency {dep} was deleted"
                elif state in (JobState.FAILED, JobState.CANCELLED):
                    what = "failed" if state == JobState.FAILED else "was cancelled"
                    problem = f"dependency {dep} {what}"
                ready &= state == JobState.COMPLETED
                if problem:
                    break
            if job.state != JobState.WAITING:  # changed while the database answered
                continue
            if problem:
                self.scheduler.fail_job(job.job_id, problem)
            elif ready:
                self.scheduler.release_job(job.job_id)
                await self._store_state(job.job_id)
        await self._after_change()

    async def _store_state(self, job_id: str) -> None:
        """Write a live job's row now (its state after a job-control change), so that a
        restart finds it as it is; the tiles follow with the next checkpoint."""
        await self._persist_job(job_id, tiles=False)

    async def _environment(
        self, settings: JobSettings, data: bytes | None, filename: str
    ) -> JobSettings:
        """Store an uploaded environment map, or check that the referenced one is stored."""
        if data:
            sha, fmt = inspect_environment(data, filename, self.settings.max_upload_bytes)
            if settings.environment and settings.environment != sha:
                raise SettingsError(
                    "settings.environment", "an environment map was uploaded and another named"
                )
            await self.store.put_scene(sha, fmt, filename or f"environment.{fmt}", data)
            return dataclasses.replace(settings, environment=sha)
        if settings.environment:
            info = await self.store.get_scene_info(settings.environment)
            if info is None or info["format"] not in ("hdr", "exr"):
                raise NotFound(f"no stored environment map with sha256 {settings.environment}")
        return settings

    async def get(self, job_id: str, caller: Caller) -> JobView:
        _check_caller(caller)
        job = self.scheduler.jobs.get(job_id)
        if job is not None:
            view = self._live_view(job)
        else:
            row = await self.store.get_job(job_id)
            if row is None:
                raise NotFound(f"no job with id {job_id!r}")
            view = self._row_view(row)
        if not caller.may_access(view.owner):
            raise Forbidden(f"job {job_id} belongs to another owner")
        return view

    async def list(
        self, state: JobState | None, page_size: int, page_token: str, caller: Caller
    ) -> tuple[list[JobView], str]:
        _check_caller(caller)
        page_size = max(1, min(page_size or 50, 500))
        after = None
        if page_token:
            try:
                stamp, _, last_id = page_token.partition("|")
                after = (datetime.fromisoformat(stamp), last_id)
            except ValueError:
                raise SettingsError(
                    "page_token", "page_token is not one this server issued"
                ) from None
        owner = None if caller.admin else caller.owner  # admins see every owner's jobs
        rows = await self.store.list_jobs(
            state.value if state else None, page_size + 1, after, owner=owner
        )
        more = len(rows) > page_size
        rows = rows[:page_size]
        views = []
        for row in rows:
            live = self.scheduler.jobs.get(row.id)
            views.append(self._live_view(live) if live is not None else self._row_view(row))
        token = f"{rows[-1].created_at.isoformat()}|{rows[-1].id}" if more else ""
        return views, token

    async def cancel(self, job_id: str, caller: Caller) -> JobView:
        view = await self.get(job_id, caller)  # raises NotFound / Forbidden
        job = self.scheduler.jobs.get(job_id)
        if job is None:
            return view  # already finished: cancelling is a no-op
        self.scheduler.cancel_job(job_id)
        await self._after_change()
        await self._until_stored(job_id)
        return await self.get(job_id, caller)

    async def delete(self, job_id: str, caller: Caller) -> None:
        """Delete a finished job and its stored data (tiles, events, its scene if unshared).
        A job still queued or running must be cancelled first."""
        await self.get(job_id, caller)  # raises NotFound / Forbidden
        job = self.scheduler.jobs.get(job_id)
        if job is not None and not self._reported_state(job).finished:
            state = self._reported_state(job).value
            raise Conflict(f"job {job_id} is {state}; cancel it before deleting it")
        if not await self.store.delete_job(job_id):
            raise NotFound(f"no job with id {job_id!r}")
        self.scheduler.forget_job(job_id)
        for table in (self.history, self.names, self.created, self.owners):
            table.pop(job_id, None)
        self._waiting_dirty = True  # a job waiting for it fails

    # ----------------------------------------------------------------------- job control
    # Each checks the caller's right to the job as cancel does, changes the state through the
    # scheduler's state machine (a refused change is 409 Conflict), writes the job's row at
    # once (a restart finds it as it is) and answers the job after the change.
    def _refused(self, job_id: str, state: JobState, action: str) -> Conflict:
        return Conflict(f"job {job_id} is {state.value}; it cannot be {action}")

    async def _live(self, job_id: str, caller: Caller, action: str) -> JobRun:
        view = await self.get(job_id, caller)  # raises NotFound / Forbidden
        job = self.scheduler.jobs.get(job_id)
        if job is None or self._reported_state(job) != job.state or job.state.finished:
            raise self._refused(job_id, view.state, action)
        return job

    async def pause(self, job_id: str, caller: Caller) -> JobView:
        job = await self._live(job_id, caller, "paused")
        try:
            self.scheduler.pause_job(job_id)
        except TransitionError:
            raise self._refused(job_id, job.state, "paused") from None
        await self._after_change()
        await self._store_state(job_id)
        return await self.get(job_id, caller)

    async def resume(self, job_id: str, caller: Caller) -> JobView:
        job = await self._live(job_id, caller, "resumed")
        if job.state != JobState.PAUSED:
            raise self._refused(job_id, job.state, "resumed")
        self.scheduler.resume_job(job_id)
        await self._after_change()
        await self._store_state(job_id)
        return await self.get(job_id, caller)

    async def update(
        self, job_id: str, caller: Caller, priority: Any = None, name: str | None = None
    ) -> JobView:
        """A new priority or name, in any state (validated as at submission)."""
        view = await self.get(job_id, caller)
        settings = view.settings
        if priority is not None:
            try:  # the priority alone: limits changed since the submission do not matter
                checked = parse_settings({"priority": priority}, self.settings.limits())
            except SettingsError as e:
                message = e.message.replace("settings.priority", "priority")
                raise SettingsError("priority", message) from None
            settings = dataclasses.replace(settings, priority=checked.priority)
        new_name = view.name if name is None else (name.strip()[:200] or view.name)
        await self.store.update_job_spec(job_id, new_name, settings.to_dict())
        job = self.scheduler.jobs.get(job_id)
        if job is not None:
            self.names[job_id] = new_name
            self.scheduler.update_job(job_id, settings, new_name)
        else:
            data = {"priority": settings.priority, "name": new_name}
            self._pending_events.append((job_id, "job_updated", data))
        await self._after_change()
        return await self.get(job_id, caller)

    async def retry(self, job_id: str, caller: Caller) -> JobView:
        """A failed job is queued again with every batch it merged: results are identified
        by (job, tile, batch) and merged in order, so what was merged is what a run without
        the failure would have merged. The workers it had excluded may try it again."""
        view = await self.get(job_id, caller)
        if view.state != JobState.FAILED:
            raise self._refused(job_id, view.state, "retried")
        after = view.after
        ready = True
        for dep in after:
            ready &= await self._dependency_state(dep) == JobState.COMPLETED
        state = JobState.QUEUED if ready else JobState.WAITING
        await self._reactivate(job_id, view.settings, state, "job_retried", {})
        return await self.get(job_id, caller)

    async def continue_(
        self, job_id: str, caller: Caller, raw_settings: dict[str, Any] | None
    ) -> JobView:
        """Carry a completed job on to a higher max_spp or a lower noise_threshold. The result
        equals, bit for bit, a job submitted with the new settings from the start: tiles whose
        merged batches those settings would have planned alike carry on; any other tile
        renders again from its first sample (scheduler.continue_plan)."""
        view = await self.get(job_id, caller)
        old = view.settings
        raw = {}
        for key, value in (raw_settings or {}).items():
            name = ALIASES.get(key, key)
            if name not in CONTINUE_SETTINGS:
                raise SettingsError(
                    f"settings.{key}",
                    f"settings.{key} cannot change in a continue: only "
                    f"{' and '.join(CONTINUE_SETTINGS)} can (a new job renders anything else)",
                )
            raw[name] = value
        # Each alone first (type, range), so that a lower max_spp is named as such rather
        # than as the min_spp it would fall under.
        parse_settings({k: raw[k] for k in raw if k != "max_spp"}, self.settings.limits())
        if "max_spp" in raw:
            alone = parse_settings({"max_spp": raw["max_spp"]}, self.settings.limits())
            if alone.max_spp < old.max_spp:
                raise SettingsError(
                    "settings.max_spp",
                    f"settings.max_spp must be at least the job's {old.max_spp}",
                )
        new = parse_settings({**old.to_dict(), **raw}, self.settings.limits())
        if new.max_spp < old.max_spp:
            raise SettingsError(
                "settings.max_spp", f"settings.max_spp must be at least the job's {old.max_spp}"
            )
        if new.noise_threshold > old.noise_threshold:
            raise SettingsError(
                "settings.noise_threshold",
                f"settings.noise_threshold must be at most the job's {old.noise_threshold:g}",
            )
        if new == old:
            raise SettingsError(
                "settings",
                "a continue needs a higher settings.max_spp or a lower settings.noise_threshold",
            )
        if old.time_limit_s > 0:
            # A time limit stops tiles by the clock: no fresh job is certain to match them.
            raise SettingsError(
                "settings.time_limit_s",
                "a job with a time limit cannot be continued (its image depends on the clock)",
            )
        if view.state != JobState.COMPLETED:
            raise self._refused(job_id, view.state, "continued")
        changed = {k: getattr(new, k) for k in CONTINUE_SETTINGS}
        await self._reactivate(job_id, new, JobState.QUEUED, "job_continued", {"settings": changed})
        return await self.get(job_id, caller)

    async def _reactivate(
        self, job_id: str, settings: JobSettings, state: JobState, kind: str, data: dict
    ) -> None:
        """Bring a finished job back from its stored checkpoint, under `settings`."""
        if job_id in self._reactivating:
            raise Conflict(f"job {job_id} is being retried or continued already")
        self._reactivating.add(job_id)
        try:
            await self._bring_back(job_id, settings, state, kind, data)
        finally:
            self._reactivating.discard(job_id)

    async def _bring_back(
        self, job_id: str, settings: JobSettings, state: JobState, kind: str, data: dict
    ) -> None:
        row = await self.store.get_job(job_id)
        if row is None:
            raise NotFound(f"no job with id {job_id!r}")
        old_state = JobState(row.state)
        try:
            check_transition(old_state, state)
        except TransitionError:
            raise self._refused(job_id, old_state, "brought back") from None
        old = JobSettings(**row.settings)
        tile_rows = await self.store.load_tiles(job_id)
        by_index = {r.tile_index: r for r in tile_rows}
        checkpoint, plans, bases, again = {}, {}, {}, []
        for index, (_, acc) in _restore_tiles(settings, tile_rows).items():
            t = by_index[index]
            if settings == old:  # a retry: the tiles as they were
                checkpoint[index] = acc
                plans[index] = t.batch_plan or []
                bases[index] = t.plan_basis or []
                continue
            basis = {int(e[0]): tuple(e[1:]) for e in t.plan_basis or []}
            kept = continue_plan(old, settings, acc.batches, basis)
            if kept is None:
                again.append(index)
                continue
            checkpoint[index] = acc
            plans[index] = kept[0]
            bases[index] = [[b, *kept[1][b]] for b in sorted(kept[1])]
        live = self.scheduler.jobs.get(job_id)
        if live is not None and not (live.state.finished and job_id not in self._pending_finishes):
            raise self._refused(job_id, self._reported_state(live), "brought back")
        self.scheduler.forget_job(job_id)  # its finished run, if still in memory
        if again:
            data = {**data, "tiles_rendered_again": len(again)}
        job = self.scheduler.add_job(
            job_id, settings, row.scene_sha256, checkpoint=checkpoint, plans=plans, bases=bases,
            state=state, elapsed_s=row.elapsed_s, after=tuple(row.after_jobs),
            transition=(old_state, kind, data), require_tags=tuple(row.require_tags),
        )  # fmt: skip
        kept_tiles = [
            (t.index, None if t.stopped else Scheduler.planned_batches(t) or None,
             Scheduler.plan_basis(t) or None, t.stop)
            for t in job.tiles
            if t.merged
        ]  # fmt: skip
        try:
            await self.store.reactivate_job(
                job_id, settings=settings.to_dict(), state=state.value, elapsed_s=row.elapsed_s,
                render_again=again, tiles=kept_tiles,
            )  # fmt: skip
        except BaseException:
            # Not stored: the job stays as the database has it (finished, as it was).
            self.scheduler.jobs.pop(job_id, None)
            self.scheduler.cache.forget_job(job_id)
            self.scheduler.events = [e for e in self.scheduler.events if e.job_id != job_id]
            raise
        for tile in job.tiles:  # stored just now; the accumulators are those of the checkpoint
            tile.dirty = tile.aovs_dirty = False
        self._generation[job_id] = self._generation.get(job_id, 0) + 1
        self.names[job_id] = row.name
        self.created[job_id] = row.created_at.timestamp()
        self.owners[job_id] = row.owner
        self.history.pop(job_id, None)
        self._waiting_dirty = True
        await self._after_change()

    async def watch(self, job_id: str, caller: Caller) -> AsyncIterator[JobView]:
        """The job now, then after every visible change, until it is finished."""
        view = await self.get(job_id, caller)
        yield view
        last = view  # unchanged views are not sent again
        while not view.state.finished:
            job = self.scheduler.jobs.get(job_id)
            version = job.version if job else None
            async with self._changed:
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(
                        self._changed.wait_for(
                            lambda seen=version: (
                                (self.scheduler.jobs.get(job_id) is None)
                                or self.scheduler.jobs[job_id].version != seen
                            )
                        ),
                        timeout=5.0,
                    )
            view = await self.get(job_id, caller)
            if view != last:
                yield view
                last = view

    async def events(self, job_id: str, caller: Caller) -> list[dict[str, Any]]:
        await self.get(job_id, caller)
        rows = await self.store.list_events(job_id)
        return [
            {"id": r["id"], "kind": r["kind"], "data": r["data"], "at": r["at"].timestamp()}
            for r in rows
        ]

    def _live_view(self, job: JobRun) -> JobView:
        p = self.scheduler.progress(job)
        state = self._reported_state(job)
        return JobView(
            id=job.job_id,
            name=self.names.get(job.job_id, ""),
            state=state,
            settings=job.settings,
            scene_sha256=job.scene_sha256,
            progress=ProgressView(
                tiles_total=p.tiles_total,
                tiles_done=p.tiles_done,
                tiles_previewed=p.tiles_previewed,
                mean_spp=p.mean_spp,
                error=_finite_or_none(p.error),
                eta_s=p.eta_s,
                samples_merged=p.samples_merged,
                elapsed_s=p.elapsed_s,
            ),
            error=job.error_message if state == JobState.FAILED else self._unplaced(job),
            created_unix_s=self.created.get(job.job_id, job.created),
            finished_unix_s=job.finished if state.finished else None,
            owner=self.owners.get(job.job_id, ""),
            after=job.after,
            require_tags=tuple(sorted(job.require_tags)),
        )

    def _unplaced(self, job: JobRun) -> str:
        """Why a queued job with required tags waits: no connected worker has them all."""
        if job.state != JobState.QUEUED or not job.require_tags:
            return ""
        if any(job.require_tags <= slot.tags for slot in self.scheduler.workers.values()):
            return ""
        return "waiting for a worker with the tags " + ", ".join(sorted(job.require_tags))

    def _row_view(self, row: JobRow) -> JobView:
        return JobView(
            id=row.id,
            name=row.name,
            state=JobState(row.state),
            settings=JobSettings(**row.settings),
            scene_sha256=row.scene_sha256,
            progress=ProgressView(
                tiles_total=row.tiles_total,
                tiles_done=row.tiles_done,
                tiles_previewed=row.tiles_previewed,
                mean_spp=row.mean_spp,
                error=row.error_estimate,
                eta_s=0.0 if JobState(row.state).finished else None,
                samples_merged=row.samples_merged,
                elapsed_s=row.elapsed_s,
            ),
            error=row.error,
            created_unix_s=row.created_at.timestamp(),
            finished_unix_s=row.finished_at.timestamp() if row.finished_at else None,
            owner=row.owner,
            after=tuple(row.after_jobs),
            require_tags=tuple(row.require_tags),
        )

    # -------------------------------------------------------------------------- images
    async def image_file(
        self,
        job_id: str,
        fmt: str,
        layer: str,
        caller: Caller,
        max_size: int = 0,
        compression: str = "zip",
        _denoise_turn_held: bool = False,
    ) -> BinaryIO:
        """The image written to a scratch file, returned open for reading (the file is
        already unlinked: closing it frees the space). Written one row of tiles at a time
        (images.ImageWriter), from memory while the job is held, else from the database."""
        _check_caller(caller)
        if fmt not in ("png", "exr"):
            raise SettingsError("format", f"unknown image format {fmt!r}; use png or exr")
        if layer not in images.LAYERS:
            raise SettingsError(
                "layer", f"unknown layer {layer!r}; one of {', '.join(images.LAYERS)}"
            )
        if not 0 <= max_size <= MAX_IMAGE_SIZE:
            raise SettingsError("max_size", f"max_size must be in 0..{MAX_IMAGE_SIZE}")
        if compression not in images.EXR_COMPRESSIONS:
            raise SettingsError(
                "compression",
                f"unknown compression {compression[:40]!r}; one of "
                f"{', '.join(images.EXR_COMPRESSIONS)}",
            )
        view = await self.get(job_id, caller)  # raises NotFound / Forbidden
        job = self.scheduler.jobs.get(job_id)
        row = await self.store.get_job(job_id)
        if row is None:
            raise NotFound(f"no job with id {job_id!r}")
        settings = job.settings if job is not None else JobSettings(**row.settings)
        if layer == "denoised" and fmt == "png" and not settings.denoise:
            raise SettingsError(
                "layer",
                f"job {job_id} was submitted without settings.denoise: it has no denoised layer",
            )
        if settings.denoise and (fmt == "exr" or layer == "denoised") and not _denoise_turn_held:
            async with self._denoise_turn:
                return await self.image_file(
                    job_id, fmt, layer, caller, max_size, compression, _denoise_turn_held=True
                )
        # The EXR's DateTime: when the job finished (when it was submitted while it runs).
        stamp = (row.finished_at or row.created_at).timestamp()
        rects = tile_grid(settings.width, settings.height, settings.tile_size)
        cols = math.ceil(settings.width / settings.tile_size)
        rows = len(rects) // cols
        names = images.arrays_needed(fmt, layer)

        async def band(r: int) -> images.Band:
            """Row r of tiles with their arrays (read in a thread: from RAM, a spill file or
            the database)."""
            live = self.scheduler.jobs.get(job_id)
            if live is not None:  # snapshots on the loop (cheap), arrays read in the thread
                views = [(t.rect, images.TileView.of(t.rect, t.acc, names)) for t in
                         live.tiles[r * cols : (r + 1) * cols]]  # fmt: skip
                return await asyncio.to_thread(
                    lambda: [(rect, v and v.accumulator()) for rect, v in views]
                )
            stored = await self.store.load_tiles(job_id, first=r * cols, count=cols)
            if not stored and await self.store.get_job(job_id) is None:
                raise NotFound(f"no job with id {job_id!r}")  # deleted meanwhile
            return await asyncio.to_thread(_band_from_rows, settings, rects, r * cols, cols, stored)

        top = 1.0
        if fmt == "png" and layer in images.GREY_LAYERS:  # normalised: a pass for the maximum
            top = -math.inf
            for r in range(rows):
                top = max(top, await asyncio.to_thread(images.layer_maximum, layer, await band(r)))
        denoised = None
        if settings.denoise and (fmt == "exr" or layer == "denoised"):
            # A first pass gathers the frame Open Image Denoise needs whole (images.py).
            frame = images.DenoiseFrame(settings.width, settings.height)
            for r in range(rows):
                await asyncio.to_thread(frame.add_band, rects[r * cols].height, await band(r))
            denoised = await asyncio.to_thread(frame.denoise)
            del frame
        attributes = exr_attributes(view) if fmt == "exr" else None
        scratch = self.scheduler.cache.directory
        scratch.mkdir(parents=True, exist_ok=True)
        fd, path = tempfile.mkstemp(suffix=f".{fmt}", dir=scratch)
        os.close(fd)
        writer = None
        try:
            writer = await asyncio.to_thread(
                images.ImageWriter, path, fmt, settings.width, settings.height, layer, max_size,
                top, self._stopping, compression, stamp, denoised, attributes,
            )  # fmt: skip
            for r in range(rows):
                tiles = await band(r)
                await asyncio.to_thread(
                    writer.write_band, rects[r * cols].height, tiles, r == rows - 1
                )
            await asyncio.to_thread(writer.close)
            f = open(path, "rb")  # noqa: SIM115 (the caller closes it)
        except BaseException:
            # The writer may still be in its thread (this task was cancelled while it wrote a
            # band): close and remove it there, after that band, without waiting here.
            asyncio.get_running_loop().run_in_executor(None, _discard_image, writer, path)
            raise
        os.unlink(path)
        return f

    async def image(
        self,
        job_id: str,
        fmt: str,
        layer: str,
        caller: Caller,
        max_size: int = 0,
        max_bytes: int | None = None,
        compression: str = "zip",
    ) -> bytes:
        """The image as bytes (for gRPC's one message); TooLarge past max_bytes."""
        with await self.image_file(job_id, fmt, layer, caller, max_size, compression) as f:
            size = os.fstat(f.fileno()).st_size
            if max_bytes is not None and size > max_bytes:
                raise TooLarge(
                    "format",
                    f"the {fmt} image is {size} bytes, more than one message may hold "
                    f"({max_bytes}); GET /api/v1/jobs/{job_id}/image.{fmt} streams it",
                )
            return await asyncio.to_thread(f.read)

    # -------------------------------------------------------------------------- scenes
    async def scene_info(self, sha256: str) -> dict[str, Any]:
        info = await self.store.get_scene_info(sha256.strip().lower())
        if info is None:
            raise NotFound(f"no stored scene with sha256 {sha256}")
        return info

    async def scene_chunks(self, sha256: str) -> AsyncIterator[tuple[int, bytes]]:
        info = await self.scene_info(sha256)
        offset = 0
        while offset < info["size_bytes"]:
            data = await self.store.read_scene(info["sha256"], offset, SCENE_CHUNK_BYTES)
            if not data:
                break
            yield offset, data
            offset += len(data)

    # ------------------------------------------------------------------------- workers
    async def worker_hello(
        self,
        worker_id: str,
        hostname: str,
        cores: int,
        max_in_flight: int,
        version: str,
        token: str,
        tags: list[str] | None = None,
    ) -> WorkerSession:
        if self.settings.worker_token and not secrets.compare_digest(
            token.encode(), self.settings.worker_token.encode()
        ):
            raise Unauthenticated("wrong or missing worker token")
        worker_id = (worker_id or f"worker-{secrets.token_hex(3)}")[:100]
        if worker_id in self.sessions:  # a reconnect racing its old stream, or a clash
            old = self.sessions.pop(worker_id)
            old.outbox.put_nowait(None)
            self.scheduler.remove_worker(worker_id)
        session = WorkerSession(worker_id, hostname[:200], max(1, cores), version[:50])
        session.tags = tuple(tags or ())
        self.sessions[worker_id] = session
        self.scheduler.add_worker(
            worker_id, max(1, min(max_in_flight or cores + 2, 256)), tags=session.tags
        )
        try:  # the worker table is informational: a database outage must not keep workers out
            await self.store.worker_connected(
                worker_id, session.hostname, session.cores, session.version
            )
        except (psycopg.Error, PoolTimeout, OSError) as e:
            self.db_errors += 1
            log.warning("could not record worker %s: %s", worker_id, e)
        log.info("worker %s connected (%d cores)", worker_id, session.cores)
        await self._after_change()
        return session

    async def worker_gone(self, session: WorkerSession) -> None:
        if self.sessions.get(session.worker_id) is not session:
            return
        del self.sessions[session.worker_id]
        lost = self.scheduler.remove_worker(session.worker_id)
        log.info("worker %s disconnected, %d tasks re-queued", session.worker_id, len(lost))
        try:
            await self.store.worker_disconnected(session.worker_id)
        except (psycopg.Error, PoolTimeout, OSError) as e:
            self.db_errors += 1
            log.warning("could not record that worker %s left: %s", session.worker_id, e)
        await self._after_change()

    async def worker_heartbeat(
        self, session: WorkerSession, samples_per_s: float, rays_per_s: float, busy: int
    ) -> None:
        session.last_heartbeat_unix_s = time.time()
        session.samples_per_s, session.rays_per_s, session.busy_threads = (
            samples_per_s,
            rays_per_s,
            busy,
        )
        self.scheduler.heartbeat(session.worker_id)

    async def worker_result(self, session: WorkerSession, task_id: str, result: BatchResult) -> str:
        started = time.perf_counter()
        outcome = self.scheduler.complete(task_id, result)
        if self.metrics is not None:
            self.metrics.merge_seconds.observe(time.perf_counter() - started)
            self.metrics.tasks_completed.labels(outcome.split(":")[0]).inc()
            self.metrics.task_seconds.observe(result.render_seconds)
            if outcome in ("merged", "pending"):
                self.metrics.samples_merged.inc(result.sample_count * result.rect.pixels)
        session.tasks_done += 1
        if outcome not in ("merged", "pending"):
            log.debug("result %s of job %s discarded: %s", task_id, result.job_id, outcome)
        await self._after_change()
        return outcome

    async def worker_failed(
        self, session: WorkerSession, task_id: str, error: str, retryable: bool
    ):
        log.warning("worker %s failed task %s: %s", session.worker_id, task_id, error)
        self.scheduler.failed(task_id, error[:2000], retryable)
        await self._after_change()

    def workers(self) -> list[dict[str, Any]]:
        return [
            {
                "id": s.worker_id,
                "hostname": s.hostname,
                "cores": s.cores,
                "version": s.version,
                "connected_unix_s": s.connected_unix_s,
                "last_heartbeat_unix_s": s.last_heartbeat_unix_s,
                "tasks_in_flight": len(self.scheduler.workers.get(s.worker_id).leases)
                if s.worker_id in self.scheduler.workers
                else 0,
                "tasks_done": s.tasks_done,
                "tasks_failed": self.scheduler.record(s.worker_id).tasks_failed,
                "recent_errors": list(self.scheduler.record(s.worker_id).errors),
                "state": self.scheduler.worker_state(s.worker_id),
                "tags": list(s.tags),
                "samples_per_s": s.samples_per_s,
                "rays_per_s": s.rays_per_s,
                "busy_threads": s.busy_threads,
            }
            for s in self.sessions.values()
        ]

    async def set_worker_mode(self, worker_id: str, mode: str, caller: Caller) -> dict[str, Any]:
        """Operator control (docs/operators.md): drain, disable or enable a connected worker.
        Admins only: one user's call would change what every user's jobs render on. The mode
        is kept for the id across reconnects while the server runs (in memory, not stored)."""
        _check_caller(caller)
        if not caller.admin:
            raise Forbidden("only an admin token may drain, disable or enable workers")
        if worker_id not in self.sessions:
            raise NotFound(f"no connected worker with id {worker_id!r}")
        back = self.scheduler.set_worker_mode(worker_id, mode)
        log.info("worker %s set %s (%d tasks handed back)", worker_id, mode, len(back))
        await self._after_change()
        return next(w for w in self.workers() if w["id"] == worker_id)

    # -------------------------------------------------------------------- after changes
    async def _after_change(self) -> None:
        """Send cancellations and new leases, store events, finish jobs, wake watchers."""
        for worker_id, session in self.sessions.items():
            cancels = self.scheduler.take_cancellations(worker_id)
            if cancels:
                session.outbox.put_nowait(("cancel", cancels))
            if self.draining:
                continue
            for lease in self.scheduler.assign(worker_id):
                session.outbox.put_nowait(("assign", lease, self.scheduler.jobs[lease.job_id]))
        events = self.scheduler.take_events()
        finished = [e.job_id for e in events if e.kind == "job_finished"]
        for job_id in finished:  # readers see the final point at once
            self._sample_history_final(job_id)
        # Stored by flush() from the background task: a slow or absent database never holds
        # up a merge or a worker stream.
        self._pending_events.extend((e.job_id, e.kind, e.data) for e in events)
        self._pending_finishes.extend(finished)
        async with self._changed:
            self._changed.notify_all()

    def _forget_later(self, job_id: str) -> None:
        """Keep a finished job in memory for a minute (fast image requests), then drop it.
        A job that outgrew the tile cache gives its RAM back now (its checkpoint is written):
        its tiles go to its spill file, which its images read until it is dropped."""

        generation = self._generation.get(job_id, 0)

        async def forget() -> None:
            while self.scheduler.cache.evict_job(job_id, CHECKPOINT_CHUNK_BYTES):
                await asyncio.sleep(0)  # a chunk at a time: merges of other jobs go on
            await asyncio.sleep(60)
            if self._generation.get(job_id, 0) != generation:
                return  # retried or continued since: that run is forgotten when it finishes
            self.scheduler.forget_job(job_id)
            self.history.pop(job_id, None)
            self.names.pop(job_id, None)
            self.created.pop(job_id, None)
            self.owners.pop(job_id, None)

        self._tasks.append(asyncio.create_task(forget()))
        self._tasks = [t for t in self._tasks if not t.done()]

    async def checkpoint(self, force: bool = False) -> None:
        """Write every tile merged since the last checkpoint, and each live job's progress.

        Under very heavy merge load a checkpoint can take a while to serialise; the next one
        then waits at least 4x as long as this one took, so checkpoints never take more than
        about a fifth of the server's time (the interval setting is a target, not a promise)."""
        started = time.time()
        for job in list(self.scheduler.jobs.values()):
            if job.state.finished and not force:
                continue
            await self._persist_job(job.job_id, tiles=True)
        took = time.time() - started
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
        for chunk in _chunks([t for t in job.tiles if t.dirty] if tiles else []):
            snapshots, taken = [], []  # taken: (tile, whether its AOVs were snapshotted too)
            for t in chunk:
                if t.dirty:
                    snapshots.append(_tile_snapshot(t, t.aovs_dirty))
                    taken.append((t, t.aovs_dirty))
                    t.dirty = t.aovs_dirty = False
            started = time.monotonic()
            try:
                rows = await asyncio.to_thread(lambda s=snapshots: [_tile_row(*x) for x in s])
                await self.store.save_tiles(job_id, rows)
            except BaseException:
                # Not written (a database error, or the task cancelled mid-checkpoint by
                # stop(), whose final checkpoint must then write these tiles): write them again.
                for t, aovs in taken:
                    t.dirty = True
                    t.aovs_dirty |= aovs
                raise
            self._checkpoint_rate.add(_dirty_bytes(chunk, taken), time.monotonic() - started)
        await self.store.update_job(job_id, **self._job_fields(job))

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
            "error_estimate": _finite_or_none(p.error),
            "tiles_done": p.tiles_done,
            "tiles_previewed": p.tiles_previewed,
        }

    # ---------------------------------------------------------------------- durability
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
        async with self._changed:
            self._changed.notify_all()

    async def _until_stored(self, job_id: str) -> None:
        """Wait for the background writer to store a finished job's final state; while the
        database does not take it the caller is told to retry (DatabaseUnavailable)."""
        async with self._changed:
            try:
                await asyncio.wait_for(
                    self._changed.wait_for(lambda: job_id not in self._pending_finishes),
                    timeout=STORED_WAIT_S,
                )
            except TimeoutError:
                raise DatabaseUnavailable(
                    f"database unavailable: job {job_id} is stopped, but its final state is "
                    "not stored yet"
                ) from None

    def _spool_unsaved(self) -> None:
        """The final flush failed: keep whatever is not stored in the spool, replayed at the
        next start (spool.py). Synchronous, so no merge lands between snapshot and file."""
        events = list(self._pending_events)
        for job_id in self._pending_finishes:  # what flush() writes after a finished job
            events.append((job_id, "convergence", {"points": self.history.get(job_id, [])}))
        jobs = []
        for job in self.scheduler.jobs.values():
            if job.state.finished and job.job_id not in self._pending_finishes:
                continue  # stored already
            tiles = [_tile_row(*_tile_snapshot(t, t.aovs_dirty)) for t in job.tiles if t.dirty]
            jobs.append(spool.UnsavedJob(job.job_id, self._job_fields(job), tiles))
        try:
            path = spool.write(spool.spool_dir(self.settings.data_dir), events, jobs)
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

    HISTORY_POINTS = 2000

    def _sample_history(self) -> None:
        """One (elapsed, error, mean spp) point per running job and round, when it changed."""
        for job in self.scheduler.jobs.values():
            if job.state != JobState.RUNNING:
                continue
            p = self.scheduler.progress(job)
            points = self.history.setdefault(job.job_id, [])
            point = (round(p.elapsed_s, 3), _finite_or_none(p.error), p.mean_spp)
            if not points or points[-1][1:] != point[1:]:
                points.append(point)
            if len(points) > self.HISTORY_POINTS:  # keep the first point, thin the rest
                del points[1::2]

    def _sample_history_final(self, job_id: str) -> None:
        job = self.scheduler.jobs.get(job_id)
        if job is None or job.started is None:
            return
        p = self.scheduler.progress(job)
        points = self.history.setdefault(job_id, [])
        points.append((round(p.elapsed_s, 3), _finite_or_none(p.error), p.mean_spp))

    async def convergence(self, job_id: str, caller: Caller) -> list[dict[str, Any]]:
        """Image error against time: live from memory, afterwards from the event log."""
        await self.get(job_id, caller)
        points = self.history.get(job_id)
        if points is None:
            for event in reversed(await self.store.list_events(job_id)):
                if event["kind"] == "convergence":
                    points = [tuple(p) for p in event["data"]["points"]]
                    break
        return [{"t": t, "error": e, "mean_spp": n} for t, e, n in points or []]

    async def stops(self, job_id: str) -> list[dict[str, Any]]:
        """Every tile stop of the job: tile, last merged batch, spp, error, reason."""
        if job_id in self.scheduler.jobs:
            return self.stop_records(job_id)
        return [
            {
                "tile": t.tile_index,
                "batch": t.stop_batch,
                "spp": t.stop_spp,
                "error": t.stop_error,
                "reason": t.stop_reason,
            }
            for t in await self.store.load_tiles(job_id)
            if t.stop_reason is not None
        ]

    def stop_records(self, job_id: str) -> list[dict[str, Any]]:
        job = self.scheduler.jobs.get(job_id)
        if job is None:
            return []
        return [
            {
                "tile": t.index,
                "batch": t.stop.batch_index,
                "spp": t.stop.spp,
                "error": _finite_or_none(t.stop.error),
                "reason": t.stop.reason.value,
            }
            for t in job.tiles
            if t.stop is not None
        ]


def _check_caller(caller: Any) -> None:
    """Every job operation names its caller: there is no default identity to fall back on
    (one would grant the local admin's rights to a handler that forgot to pass it)."""
    if not isinstance(caller, Caller):
        raise TypeError(f"FarmService needs the caller (an auth.Caller), got {caller!r}")


def _restore_tiles(
    settings: JobSettings, rows: list[TileRow]
) -> dict[int, tuple[Rect, TileAccumulator]]:
    """Checkpointed tiles of a job as accumulators, by tile index."""
    rects = tile_grid(settings.width, settings.height, settings.tile_size)
    restored = {}
    for t in rows:
        rect = rects[t.tile_index]
        acc = TileAccumulator.from_bytes(
            rect.width,
            rect.height,
            t.accumulators,
            t.samples,
            t.batches,
            t.nonfinite,
            iid=settings.sampler == "independent",
            aovs=t.aovs,
        )
        restored[t.tile_index] = (rect, acc)
    return restored


CHECKPOINT_CHUNK_BYTES = 32 * 2**20


def _chunks(tiles: list) -> list[list]:
    """Tiles in runs of about CHECKPOINT_CHUNK_BYTES of accumulators (at least one each)."""
    chunks, chunk, size = [], [], 0
    for t in tiles:
        if chunk and size + t.acc.nbytes > CHECKPOINT_CHUNK_BYTES:
            chunks.append(chunk)
            chunk, size = [], 0
        chunk.append(t)
        size += t.acc.nbytes
    return chunks + [chunk] if chunk else chunks


def _dirty_bytes(tiles, taken=None) -> int:
    """Bytes a checkpoint writes for these tiles (statistics, and AOVs where they changed)."""
    aovs = [a for _, a in taken] if taken is not None else [t.aovs_dirty for t in tiles]
    per_pixel = TileAccumulator.BYTES_PER_PIXEL
    return sum(
        t.rect.pixels * (per_pixel if with_aovs else per_pixel * 2 // 3)
        for t, with_aovs in zip(tiles, aovs, strict=True)
    )


class _Rate:
    """Checkpoint bytes per second: a running mean over recent writes, for the drain's
    estimate of how long the last checkpoint will take."""

    def __init__(self, initial: float):
        self.value = initial

    def add(self, nbytes: int, seconds: float) -> None:
        if nbytes > 1 << 20 and seconds > 0:  # small writes measure latency, not throughput
            self.value = 0.7 * self.value + 0.3 * nbytes / seconds


def renderer_version() -> str:
    """The renderfarm release that rendered a job (the server's package; workers are built
    from the same release and report it in their hello)."""
    try:
        return importlib.metadata.version("renderfarm")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


def exr_attributes(view: JobView) -> dict[str, str | float]:
    """The job's record in its EXR header (README "Outputs"): its settings as JSON, scene,
    renderer version, mean spp and estimated error (absent while unknown). No wall-clock
    time: the EXR stays a function of the job."""
    attributes: dict[str, str | float] = {
        "renderfarm:settings": json.dumps(view.settings.to_dict(), sort_keys=True),
        "renderfarm:scene_sha256": view.scene_sha256,
        "renderfarm:version": renderer_version(),
        "renderfarm:mean_spp": float(view.progress.mean_spp),
    }
    if view.progress.error is not None:
        attributes["renderfarm:error"] = float(view.progress.error)
    return attributes


def _band_from_rows(
    settings: JobSettings, rects: list[Rect], first: int, count: int, rows: list[TileRow]
) -> images.Band:
    """A row of tiles from their checkpoints (a tile without one has no samples)."""
    by_index = {t.tile_index: t for t in rows}
    iid = settings.sampler == "independent"
    band: images.Band = []
    for index in range(first, first + count):
        rect, t = rects[index], by_index.get(index)
        acc = None
        if t is not None and t.samples > 0:
            acc = TileAccumulator.from_bytes(
                rect.width, rect.height, t.accumulators, t.samples, t.batches, t.nonfinite,
                iid=iid, aovs=t.aovs,
            )  # fmt: skip
        band.append((rect, acc))
    return band


def _discard_image(writer: images.ImageWriter | None, path: str) -> None:
    if writer is not None:
        with contextlib.suppress(Exception):
            writer.abandon()
    with contextlib.suppress(OSError):
        os.unlink(path)


def _tile_snapshot(t, with_aovs: bool) -> tuple:
    acc = t.acc
    aovs = acc.aov_snapshot() if with_aovs else None
    plan = None if t.stopped else Scheduler.planned_batches(t) or None
    basis = Scheduler.plan_basis(t) or None
    return (
        t.index, acc.samples, acc.batches, acc.nonfinite, t.error, acc.snapshot(), aovs, t.stop,
        plan, basis,
    )  # fmt: skip


def _tile_row(
    index, samples, batches, nonfinite, error, arrays, aovs, stop, plan, basis
) -> TileRow:
    return TileRow(
        tile_index=index,
        samples=samples,
        batches=batches,
        nonfinite=nonfinite,
        error=error,
        accumulators=TileAccumulator.snapshot_bytes(arrays),
        stop_batch=stop.batch_index if stop else None,
        stop_spp=stop.spp if stop else None,
        stop_error=stop.error if stop else None,
        stop_reason=stop.reason.value if stop else None,
        aovs=None if aovs is None else TileAccumulator.snapshot_bytes(aovs, "<f4"),
        batch_plan=plan,
        plan_basis=basis,
    )


def decode_result(msg) -> BatchResult:
    """A TileResult protobuf message as numpy arrays (little-endian, row-major)."""
    rect = Rect(msg.rect.x0, msg.rect.y0, msg.rect.width, msg.rect.height)
    n = rect.pixels
    # Each read of a bytes field copies it out of the message: read each once.
    rgb_raw, m2_raw = msg.rgb_sum, msg.luminance_m2
    albedo_raw, normal_raw = msg.albedo_sum, msg.normal_sum
    # float32 (what workers send) or float64, told apart by length.
    rgb = np.frombuffer(rgb_raw, dtype="<f4" if len(rgb_raw) == 12 * n else "<f8")
    m2 = np.frombuffer(m2_raw, dtype="<f4" if len(m2_raw) == 4 * n else "<f8")
    # AOVs are float32; absent, or of the wrong size, they are left out.
    albedo = np.frombuffer(albedo_raw, dtype="<f4") if len(albedo_raw) == 12 * n else None
    normal = np.frombuffer(normal_raw, dtype="<f4") if len(normal_raw) == 12 * n else None
    return BatchResult(
        job_id=msg.job_id,
        tile_index=msg.tile_index,
        batch_index=msg.batch_index,
        sample_start=msg.sample_start,
        sample_count=msg.sample_count,
        rect=rect,
        rgb_sum=rgb,
        luminance_m2=m2,
        albedo_sum=albedo,
        normal_sum=normal,
        nonfinite=msg.nonfinite_samples,
        render_seconds=msg.render_seconds,
        rays=msg.rays,
    )


__all__ = [
    "FarmService",
    "JobView",
    "Lease",
    "SceneError",
    "SettingsError",
    "StopReason",
    "WorkerSession",
    "decode_result",
]
