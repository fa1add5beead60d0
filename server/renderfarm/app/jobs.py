"""FarmService: the one place where API calls, worker streams, the scheduler and the store meet.
This module is its facade (jobs: submit, read, list, cancel, delete, watch; scenes; the
background round); its other parts are mixins in the modules of app/ named in the class. Over
500 lines because the facade's methods are the API's operations, each short, one after another.

Everything runs on one asyncio event loop: the scheduler is plain Python without locks, merges
are vectorised numpy on tiles (tens of microseconds), and every database call is awaited, so a
slow database never blocks a merge. REST and gRPC handlers are thin: they parse, call a method
here, and map the exceptions of errors.py to status codes.

Durability: a submission is acknowledged only after its scene and job rows are committed. Merged
tiles are checkpointed every `checkpoint_interval_s` by a background task (only tiles that
changed), and immediately when a job finishes. On start, unfinished jobs resume from their
checkpoints. A finished job is reported finished only once its final state is stored (until
then a restart would resume it); a server stopped while the database is unreachable keeps what
it could not write in its spool (infra/spool.py) and writes it at its next start.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import math
import secrets
import threading
from collections import OrderedDict
from collections.abc import AsyncIterator
from datetime import datetime
from typing import Any

import psycopg
from psycopg_pool import PoolTimeout

from ..domain import light_groups
from ..domain.channels import CAPABILITY_PREFIX, job_layout
from ..domain.frames import frame_count, job_rects, resolve_animations
from ..domain.jobspec import JobSettings, check_variant_images, parse_settings
from ..domain.records import JobRun
from ..domain.scenes.environment import inspect_environment
from ..domain.scenes.validate import inspect_scene, job_variants
from ..domain.scheduler import Scheduler
from ..domain.states import JobState
from ..errors import Conflict, Forbidden, LeaseLost, NotFound, SettingsError, TooLarge
from ..infra import spool
from ..infra.config import Settings
from ..infra.memory_store import JobStore
from ..infra.store import JobRow
from ..infra.usd_import import UsdImport
from . import checkpoints
from .auth import Caller, check_caller
from .broadcast import Broadcast
from .collaborators import Clock, Ownership, SceneInspector, UsdConverter
from .history import History
from .job_cameras import JobCameras
from .job_control import JobControl
from .job_images import JobImages
from .job_mattes import JobMattes
from .job_movies import JobMovies
from .views import JobView, ProgressView, finite_or_none
from .worker_sessions import WorkerSession, WorkerSessions
from .write_behind import CheckpointRate, WriteBehind

log = logging.getLogger(__name__)


def _wants_light_groups(settings: JobSettings) -> bool:
    return "light_groups" in settings.aovs.split(",")


SCENE_CHUNK_BYTES = 1 << 20


class FarmService(
    JobControl, JobImages, JobMattes, JobCameras, JobMovies, WorkerSessions, WriteBehind, History
):
    """The job API facade: submit, read, list, cancel and delete jobs, watch them, serve scenes,
    and the background round. Its other parts, by concern: job_control.py (pause, resume,
    update, retry, continue), job_images.py (images), job_cameras.py (camera data),
    job_movies.py (preview movies), worker_sessions.py (worker streams), write_behind.py
    (database writes and checkpoints), history.py (convergence, stops).

    Collaborators, given to __init__ (docs/architecture.md, "Composition") and read by every
    part: settings, store, scheduler (its jobs, leases, workers and tile cache are the farm's
    live state), clock, ownership; scene_checker by this module (uploads) and job_cameras.py,
    usd_importer by this module only.
    `metrics` is set by the server after construction (api.metrics.Metrics reads the service)
    and read by worker_sessions.py.

    State set in __init__ (parts by module; * marks state shared between parts):

        attribute                 written by                         read by
        sessions *                worker_sessions                    jobs (_after_change, stop)
        names, created, owners *  jobs (submit, resume, delete,      jobs (views)
                                  forget), job_control (update,
                                  bring back)
        history *                 history (its points, sampled from  history, write_behind
                                  jobs' round and _after_change),      (convergence event,
                                  jobs (delete, forget), job_control   spool)
                                  (bring back drops it)
        _pending_events *         jobs (submit, _after_change),      write_behind (flush,
                                  job_control (update)                 spool)
        _pending_finishes *       jobs (_after_change), write_behind write_behind
                                  (flush pops)                         (_reported_state),
                                                                     job_control (bring back)
        _changed * (Broadcast)    notified by jobs, write_behind     waited on by jobs (watch),
                                                                     write_behind (stored)
        _waiting_dirty *          jobs, job_control, write_behind    jobs (_round)
        _generation *             job_control (bring back)           jobs (_forget_later)
        draining *                write_behind (drain)               jobs (_after_change)
        _stopping *               jobs (stop)                        job_images (writers stop)
        db_errors *               write_behind, worker_sessions      (nothing: a count kept)
        _reactivating             job_control                        job_control
        _tasks, ready             jobs                               jobs; ready by the API
        _last_checkpoint,         write_behind (jobs sets the first  write_behind
          _checkpoint_rate,         checkpoint time)
          _db_retry_at,
          _db_failures,
          database_ok
        _denoise_turn (Lock)      job_images                         job_images
        _movie_turn (Lock)        job_movies                         job_movies
        _cameras, _camera_runs    job_cameras                        job_cameras

    The parts also call one another: each checks access with the facade's get, and a change
    ends with the facade's _after_change; job_control uses _store_state, _reported_state and
    _dependency_state; write_behind's flush calls _forget_later; the background round calls
    history's and write_behind's methods. The write-behind state stays here rather than in a
    class of its own: the queues are filled by three parts and flushing them needs the
    scheduler, the history, _forget_later and _changed, so a separate class would take most of
    the service with it."""

    def __init__(
        self,
        settings: Settings,
        store: JobStore,
        *,
        scheduler: Scheduler,
        scene_checker: SceneInspector,
        usd_importer: UsdConverter,
        clock: Clock,
        ownership: Ownership,
    ):
        """Its collaborators are given (app/composition.build_farm_service makes the server's):
        the scheduler with its tile cache, the judge of uploaded scenes (the workers' own
        loader), the converter of USD uploads to glTF, the clock (unix time), which the
        scheduler reads too, and which jobs this server owns (collaborators.Ownership)."""
        self.settings = settings
        self.store = store
        self.scheduler = scheduler
        self.scene_checker = scene_checker
        self.usd_importer = usd_importer
        self.clock = clock
        self.ownership = ownership
        self._stopping = threading.Event()  # images being written give up when set
        # One image with a denoised layer at a time, from gathering its frame to its last row:
        # the memory checked at submission (jobspec.denoise_memory_bytes) is that of one.
        self._denoise_turn = asyncio.Lock()
        self._movie_turn = asyncio.Lock()  # one preview movie encoded at a time (job_movies.py)
        # Camera data (job_cameras.py): the loader's camera per (job, frame), least recently
        # used first, and the loader runs under way.
        self._cameras: OrderedDict[tuple[str, int | None], dict[str, Any]] = OrderedDict()
        self._camera_runs: dict[tuple[str, int | None], asyncio.Future] = {}
        self._checkpoint_rate = CheckpointRate(50e6)  # bytes/s; measured by every large checkpoint
        self.sessions: dict[str, WorkerSession] = {}
        self.names: dict[str, str] = {}  # job id -> name for live jobs
        self.created: dict[str, float] = {}  # job id -> created unix time for live jobs
        self.owners: dict[str, str] = {}  # job id -> owner (token name) for live jobs
        # Bumped each time a finished job comes back (retry, continue): a delayed forget of
        # its earlier run leaves the new one alone.
        self._generation: dict[str, int] = {}
        self._waiting_dirty = True  # waiting jobs' dependencies to be checked again
        self._reactivating: set[str] = set()  # retries and continues under way
        self._changed = Broadcast()
        self._tasks: list[asyncio.Task] = []
        self._last_checkpoint = clock()
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
        self.batches_merged = 0  # since start (worker_sessions; this replica's row)
        self.jobs_lost = 0  # dropped: another server holds them now (metrics)
        # A farm of several servers (ownership.shared): when to look next for jobs nobody
        # holds (the service's clock), and the forwarded job-control requests applied this
        # round, deleted once its writes are done (job_control.py).
        self._next_takeover = -float("inf")
        self._controls_applied: list[int] = []
        # Jobs this server hands to others to share the farm's jobs evenly: job id -> the
        # service's clock by which it lets go even with tasks still in flight.
        self._handing_off: dict[str, float] = {}
        self.jobs_handed_off = 0  # since start (metrics)

    # ------------------------------------------------------------------------- lifecycle
    async def start(self) -> None:
        await spool.replay(self.store, self.settings.data_dir)
        self.scheduler.cache.clear_directory()
        await self.store.mark_all_workers_disconnected()
        await self.ownership.heartbeat()  # a replica's row exists before it takes jobs
        await self._resume_unfinished()
        self._tasks.append(asyncio.create_task(self._background(), name="farm-background"))
        if self.ownership.shared:
            self._tasks.append(asyncio.create_task(self._keep_leases(), name="farm-leases"))
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
        else:
            # Everything is stored: other servers may take the jobs over at once.
            for job_id in list(self.scheduler.jobs):
                await self.ownership.release(job_id)
        await self.ownership.leave()
        self.scheduler.cache.close()
        for session in list(self.sessions.values()):
            session.outbox.put_nowait(None)

    async def _resume_unfinished(self) -> None:
        """At start: every unfinished job (a server alone), or in a farm of several servers
        those whose lease names this one (it crashed, or was restarted within the lease);
        the others' jobs and those nobody holds are shared out by _take_over."""
        for row in await self.store.unfinished_jobs():
            if row.id in self.scheduler.jobs:
                continue
            if self.ownership.shared:
                lease = await self.store.lease_of(row.id)
                if lease is None or lease[0] != self.ownership.replica_id:
                    continue
            if not await self.ownership.acquire(row.id):
                continue  # another server holds it and renders it
            await self._resume(row)
        await self._after_change()

    async def _take_over(self) -> None:
        """A farm of several servers: take the unfinished jobs no server holds a live lease on
        (their owner died, was cut off or stopped) and resume them from their last checkpoint,
        as a start does. Every job_lease_s / 4 of the service's clock."""
        now = self.clock()
        if not self.ownership.shared or now < self._next_takeover:
            return
        self._next_takeover = now + self.settings.job_lease_s / 4
        # A dependency may have completed on another server: waiting jobs look again.
        self._waiting_dirty |= any(
            j.state == JobState.WAITING for j in self.scheduler.jobs.values()
        )
        unheld = [j for j in await self.store.unleased_jobs() if j not in self.scheduler.jobs]
        fair, mine = await self._fair_share(len(unheld))
        taken = 0
        for job_id in unheld:
            if mine + taken >= fair:
                break  # the others' share: each live server takes up to its own
            if not await self.ownership.acquire(job_id):
                continue
            row = await self.store.get_job(job_id)  # read after the lease: its last checkpoint
            if row is None or JobState(row.state).finished:
                await self.ownership.release(job_id)
                continue
            await self._resume(row)
            taken += 1
        if taken:
            log.info("took over %d job%s nobody held", taken, "" if taken == 1 else "s")
            await self._after_change()
        self._choose_hand_offs(mine + taken - fair)

    async def _fair_share(self, unheld: int) -> tuple[int, int]:
        """(this server's fair share of the farm's unfinished jobs, the jobs it holds and
        keeps): the jobs held by live servers and those nobody holds, shared evenly among
        the live servers, rounded up. A server counts as live while its last heartbeat is
        younger than three quarters of the job lease (it renews every quarter), so the jobs
        of a server that died are shared among the others as soon as their leases expire."""
        me = self.ownership.replica_id
        rows = await self.store.list_replicas(live_s=0.75 * self.settings.job_lease_s)
        others = [r for r in rows if r["live"] and r["id"] != me]
        mine = sum(
            not j.state.finished and self.ownership.owns(j.job_id) and j.job_id not in
            self._handing_off for j in self.scheduler.jobs.values()
        )  # fmt: skip
        total = sum(r["jobs_owned"] for r in others) + mine + len(self._handing_off) + unheld
        return math.ceil(total / (len(others) + 1)), mine

    def _choose_hand_offs(self, excess: int) -> None:
        """Hand the newest of this server's jobs beyond its fair share to the others: no new
        tasks of them are leased, and once those in flight are merged (or a half job lease
        has passed) each is checkpointed and released (_hand_off), for a server below its
        share to take it over from that checkpoint, the same bits."""
        if excess <= 0:
            return
        candidates = sorted(
            (
                j.job_id for j in self.scheduler.jobs.values()
                if not j.state.finished and self.ownership.owns(j.job_id)
                and j.job_id not in self._handing_off
            ),
            key=lambda job_id: (self.created.get(job_id, 0.0), job_id),
            reverse=True,
        )  # fmt: skip
        deadline = self.clock() + self.settings.job_lease_s / 2
        for job_id in candidates[:excess]:
            self._handing_off[job_id] = deadline
            log.info("handing job %s to another server (more than this one's share)", job_id)

    def _may_lease(self, job_id: str) -> bool:
        """Tasks of the job may be leased here: this server owns it and keeps it."""
        return self.ownership.owns(job_id) and job_id not in self._handing_off

    async def _hand_off(self) -> None:
        """Let go of the jobs chosen by _choose_hand_offs whose tasks have come back (or whose
        time is up): their events and tiles are written, fenced, then the lease released."""
        for job_id, deadline in list(self._handing_off.items()):
            job = self.scheduler.jobs.get(job_id)
            if job is None or job.state.finished or not self.ownership.owns(job_id):
                del self._handing_off[job_id]  # finished, or no longer this server's anyway
                continue
            busy = any(lease.job_id == job_id for lease in self.scheduler.leases.values())
            if busy and self.clock() < deadline:
                continue
            events = [e for e in self._pending_events if e[0] == job_id]
            try:
                if events:
                    await self.store.add_events(events, self._event_fences(events))
                    written = set(map(id, events))
                    self._pending_events = [e for e in self._pending_events if id(e) not in written]
                await self._persist_job(job_id, tiles=True)
            except LeaseLost:
                del self._handing_off[job_id]
                self._drop_lost(job_id)
                continue
            except (psycopg.Error, PoolTimeout, OSError) as e:  # kept; chosen again later
                del self._handing_off[job_id]
                log.warning("could not hand job %s over: %s", job_id, e)
                continue
            del self._handing_off[job_id]
            await self.ownership.release(job_id)
            self._forget_here(job_id)
            self.jobs_handed_off += 1
            log.info("handed job %s over (checkpointed and released)", job_id)

    async def _resume(self, row: JobRow) -> None:
        """Bring an unfinished job this server now holds back from its checkpoint."""
        settings = JobSettings(**row.settings)
        # A chunk of tiles at a time, each put under the tile cache at once: a large job
        # comes back within the cache's RAM (the rest goes to its spill file).
        checkpoint, plans, bases, old_aovs = {}, {}, {}, []
        variants = tuple(row.variants)
        tiles = len(job_rects(settings, variants))
        tile_bytes = job_layout(settings).bytes_per_pixel() * settings.tile_size**2
        step = max(1, checkpoints.CHECKPOINT_CHUNK_BYTES // tile_bytes)
        for first in range(0, tiles, step):
            tile_rows = await self.store.load_tiles(row.id, first=first, count=step)
            restored = checkpoints.restore_tiles(settings, tile_rows, variants)
            for index, (_, acc) in restored.items():
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
            variants=variants,
        )
        # Its stops were recorded before the restart (or by its previous owner).
        self.scheduler.events = [e for e in self.scheduler.events if e.job_id != row.id]
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

    async def _background(self) -> None:
        while True:
            await asyncio.sleep(0.25)
            try:
                await self._round()
            except asyncio.CancelledError:
                raise
            except Exception:  # keep serving; the next round retries
                log.exception("background round failed")

    async def _keep_leases(self) -> None:
        """Renew the job leases on their own schedule too (heartbeat renews at most every
        quarter lease, whoever asks): a background round busy with a large checkpoint under a
        flood of results must not let them lapse, or the jobs would move for nothing."""
        while True:
            await asyncio.sleep(0.25)
            try:
                await self.ownership.heartbeat()
            except asyncio.CancelledError:
                raise
            except Exception:  # the next turn tries again
                log.exception("renewing the job leases failed")

    async def _round(self) -> None:
        """One background round: renew ownership, time limits and expired leases, the
        convergence history, new leases and cancels, due writes, waiting jobs."""
        await self.ownership.heartbeat()
        for job_id in self.ownership.take_lost():
            self._drop_lost(job_id)
        if self.ownership.shared and not self.store.unreachable:
            try:
                await self._apply_controls()
                await self._take_over()
            except (psycopg.Error, PoolTimeout, OSError) as e:  # the round goes on
                self.db_errors += 1
                log.warning("could not look for other servers' requests or jobs: %s", e)
        self.scheduler.tick()
        self._sample_history()
        await self._after_change()
        if await self.flush():
            await self._controls_stored()
        if self._handing_off and not self.store.unreachable:
            await self._hand_off()
            await self._after_change()
        if self._waiting_dirty:
            await self._check_waiting()

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
        check_caller(caller)
        require_tags = sorted(set(require_tags or []))
        settings = parse_settings(raw_settings, self.settings.limits())
        after = list(dict.fromkeys(after or []))  # in order, once each
        ready = await self._dependencies_ready(after, caller)
        settings = await self._environment(settings, environment_data, environment_filename)
        usd: UsdImport | None = None
        if scene_data is not None and scene_sha256:
            raise SettingsError("scene", "give either an uploaded scene or scene_sha256, not both")
        if scene_data is not None:
            if len(scene_data) > self.settings.max_upload_bytes:
                raise TooLarge(
                    "scene",
                    f"scene is {len(scene_data)} bytes, more than the server's limit of "
                    f"{self.settings.max_upload_bytes} bytes",
                )
            if self.usd_importer.is_usd(scene_data, filename):
                usd = await self.usd_importer.convert(scene_data, filename or "scene.usd")
                scene_data, filename = usd.glb, usd.filename
                settings = self._usd_camera_settings(settings, raw_settings, usd)
                settings = await self._usd_environment(settings, raw_settings, usd)
            info = inspect_scene(scene_data, filename or "scene", self.settings.max_upload_bytes)
            resolve_animations(settings.animation, info.animations)
            variants = job_variants(settings.variant, info.variants)
            settings = self._with_light_groups(settings, info.light_groups)
            check_variant_images(settings, len(variants), self.settings.limits())
            if await self.store.get_scene_info(info.sha256) is None:
                await self.scene_checker.check(scene_data, filename or "scene", info.sha256)
            await self.store.put_scene(info.sha256, info.format, filename or "scene", scene_data)
            if usd is not None:
                await self.store.put_scene_source(
                    info.sha256, "usd", usd.source_sha256, usd.source_filename
                )
            sha = info.sha256
        elif scene_sha256:
            sha = scene_sha256.strip().lower()
            stored = await self.store.get_scene_info(sha)
            # Environment maps share the table; only a glTF scene can be rendered as one.
            if stored is None or stored["format"] not in ("glb", "gltf"):
                raise NotFound(f"no stored scene with sha256 {sha}")
            filename = filename or stored["filename"]
            variants = ()
            # Names are checked against the stored scene's animations and variants, and its
            # light groups found.
            if settings.animation or settings.variant or _wants_light_groups(settings):
                data = await self.store.read_scene(sha, 0, stored["size_bytes"])
                info = inspect_scene(data, filename, max(len(data), 1))
                resolve_animations(settings.animation, info.animations)
                variants = job_variants(settings.variant, info.variants)
                settings = self._with_light_groups(settings, info.light_groups)
                check_variant_images(settings, len(variants), self.settings.limits())
        else:
            raise SettingsError(
                "scene", "a scene is required: upload a .glb/.gltf or give scene_sha256"
            )
        job_id = secrets.token_hex(6)
        if usd is not None:
            name = name or usd.source_filename
        name = (name or filename or "job").strip()[:200]
        tiles = len(job_rects(settings, variants))
        state = JobState.QUEUED if ready else JobState.WAITING
        row = await self.store.insert_job(
            job_id, name, settings.to_dict(), sha, tiles, owner=caller.owner, after=after,
            state=state.value, require_tags=require_tags, variants=list(variants),
            scene_source=None if usd is None else {"source_format": "usd",
                "source_sha256": usd.source_sha256, "source_filename": usd.source_filename},
        )  # fmt: skip
        # Stored and committed: only now does the job exist for the scheduler and the caller.
        if not await self.ownership.acquire(job_id):
            # Another server took it first (it looks for jobs nobody holds), or the lease
            # could not be written: a server that holds it renders it.
            log.info("job %s submitted here is rendered by another server", job_id)
            return await self.get(job_id, caller)
        self.owners[job_id] = caller.owner
        self.names[job_id] = name
        self.created[job_id] = row.created_at.timestamp()
        self.scheduler.add_job(
            job_id, settings, sha, state=state, after=tuple(after),
            require_tags=tuple(require_tags), variants=variants,
        )  # fmt: skip
        self._waiting_dirty = True  # a dependency may have completed since it was looked at
        if usd is not None:
            self._pending_events.append((job_id, "scene_converted", _usd_event(usd)))
        await self._after_change()
        return await self.get(job_id, caller)

    def _with_light_groups(
        self, settings: JobSettings, groups: dict[str, list[int]]
    ) -> JobSettings:
        """A job asking for light groups gets the scene's (domain/light_groups.py) in its
        settings, replacing any given, and is checked again with them (their memory):
        SettingsError naming settings.aovs for too many."""
        if not _wants_light_groups(settings):
            return settings
        light_groups.check_count(groups)
        raw = {**settings.to_dict(), "light_groups": light_groups.encode(groups)}
        return parse_settings(raw, self.settings.limits())

    async def _usd_environment(
        self, settings: JobSettings, raw: dict[str, Any] | None, usd: UsdImport
    ) -> JobSettings:
        """A USD dome light as the job's environment map, with its intensity and rotation,
        unless the submission names or uploads an environment of its own."""
        if usd.environment_data is None or settings.environment:
            return settings
        settings = await self._environment(settings, usd.environment_data, usd.environment_filename)
        raw = dict(raw or {})
        chosen = {k: v for k, v in usd.environment.items() if k not in raw}
        return parse_settings({**settings.to_dict(), **chosen}, self.settings.limits())

    def _usd_camera_settings(
        self, settings: JobSettings, raw: dict[str, Any] | None, usd: UsdImport
    ) -> JobSettings:
        """The USD camera's depth of field as the job's aperture_radius and focus_distance,
        unless the submission set either."""
        raw = dict(raw or {})
        if not usd.camera or "aperture_radius" in raw or "focus_distance" in raw:
            return settings
        return parse_settings({**settings.to_dict(), **usd.camera}, self.settings.limits())

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
                with contextlib.suppress(LeaseLost):  # dropped: its new owner checks it
                    await self._store_state(job.job_id)
        await self._after_change()

    async def _store_state(self, job_id: str) -> None:
        """Write a live job's row now (its state after a job-control change), so that a
        restart finds it as it is; the tiles follow with the next checkpoint. LeaseLost (as
        409) when another server holds the job now: it is dropped here."""
        try:
            await self._persist_job(job_id, tiles=False)
        except LeaseLost:
            self._drop_lost(job_id)
            raise

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

    def _shown_live(self, job_id: str) -> JobRun | None:
        """The job as this server holds it in memory, when that is the job as it is: in a farm
        of several servers, a finished job kept here after its lease was released may have
        been brought back by another server since, so its row is read instead."""
        job = self.scheduler.jobs.get(job_id)
        if job is None or not self.ownership.shared or self.ownership.epoch(job_id) >= 0:
            return job
        return None

    async def get(self, job_id: str, caller: Caller) -> JobView:
        check_caller(caller)
        job = self._shown_live(job_id)
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
        check_caller(caller)
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
            live = self._shown_live(row.id)
            views.append(self._live_view(live) if live is not None else self._row_view(row))
        token = f"{rows[-1].created_at.isoformat()}|{rows[-1].id}" if more else ""
        return views, token

    async def cancel(self, job_id: str, caller: Caller) -> JobView:
        view = await self.get(job_id, caller)  # raises NotFound / Forbidden
        job = self.scheduler.jobs.get(job_id)
        if job is None and self._elsewhere(view):
            return await self._forward(job_id, "cancel", {}, caller)
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
        holder = self.ownership.replica_id if self.ownership.shared else None
        if not await self.store.delete_job(job_id, replica_id=holder):
            raise NotFound(f"no job with id {job_id!r}")
        await self.ownership.release(job_id)
        self.scheduler.forget_job(job_id)
        self._forget_movies(job_id)
        for table in (self.history, self.names, self.created, self.owners):
            table.pop(job_id, None)
        self._waiting_dirty = True  # a job waiting for it fails

    # ----------------------------------------------------------------------- job control

    async def watch(self, job_id: str, caller: Caller) -> AsyncIterator[JobView]:
        """The job now, then after every visible change, until it is finished."""
        view = await self.get(job_id, caller)
        yield view
        last = view  # unchanged views are not sent again
        while not view.state.finished:
            job = self.scheduler.jobs.get(job_id)
            version = job.version if job else None
            with contextlib.suppress(TimeoutError):
                await self._changed.wait_for(
                    lambda seen=version: (
                        (self.scheduler.jobs.get(job_id) is None)
                        or self.scheduler.jobs[job_id].version != seen
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
                error=finite_or_none(p.error),
                eta_s=p.eta_s,
                samples_merged=p.samples_merged,
                elapsed_s=p.elapsed_s,
                frames_total=p.frames_total,
                frames_done=p.frames_done,
            ),
            error=job.error_message if state == JobState.FAILED else self._unplaced(job),
            created_unix_s=self.created.get(job.job_id, job.created),
            finished_unix_s=job.finished if state.finished else None,
            owner=self.owners.get(job.job_id, ""),
            after=job.after,
            require_tags=tuple(sorted(job.require_tags)),
            variants=job.variants,
            replica=self.ownership.replica_id if self.ownership.owns(job.job_id) else "",
        )

    def _unplaced(self, job: JobRun) -> str:
        """Why a queued job with required tags or outputs waits: no connected worker has the
        tags, or renders the outputs (a worker older than the outputs does not)."""
        if job.state != JobState.QUEUED or not job.requires:
            return ""
        if any(job.requires <= slot.tags for slot in self.scheduler.workers.values()):
            return ""
        rows = sorted(t.removeprefix(CAPABILITY_PREFIX) for t in job.requires - job.require_tags)
        tagged = any(job.require_tags <= slot.tags for slot in self.scheduler.workers.values())
        if rows and (tagged or not job.require_tags):
            return (
                "waiting for a worker that renders " + ", ".join(rows) + " (settings.aovs; "
                "workers older than the server do not: upgrade them)"
            )
        return "waiting for a worker with the tags " + ", ".join(sorted(job.require_tags))

    def _row_view(self, row: JobRow) -> JobView:
        settings = JobSettings(**row.settings)
        return JobView(
            id=row.id,
            name=row.name,
            state=JobState(row.state),
            settings=settings,
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
                frames_total=frame_count(settings, tuple(row.variants)),
                frames_done=row.frames_done,
            ),
            error=row.error,
            created_unix_s=row.created_at.timestamp(),
            finished_unix_s=row.finished_at.timestamp() if row.finished_at else None,
            owner=row.owner,
            after=tuple(row.after_jobs),
            require_tags=tuple(row.require_tags),
            variants=tuple(row.variants),
            replica=row.replica,
        )

    # -------------------------------------------------------------------------- images

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

    # ------------------------------------------------------------------------ replicas
    async def replicas(self) -> list[dict[str, Any]]:
        """The servers of the farm (GET /api/v1/replicas): each one's id, addresses, start,
        last heartbeat, jobs it holds and merge rate. A server alone lists itself."""
        if not self.ownership.shared:
            return [{
                "id": self.ownership.replica_id, "addresses": {}, "started_unix_s": None,
                "heartbeat_unix_s": self.clock(), "live": True,
                "jobs_owned": sum(not j.state.finished for j in self.scheduler.jobs.values()),
                "batches_merged": self.batches_merged, "merge_rate": None,
            }]  # fmt: skip
        rows = await self.store.list_replicas(live_s=2 * self.settings.job_lease_s)
        return [
            {
                "id": r["id"],
                "addresses": r["addresses"],
                "started_unix_s": r["started_at"].timestamp(),
                "heartbeat_unix_s": r["heartbeat_at"].timestamp(),
                "live": r["live"],
                "jobs_owned": r["jobs_owned"],
                "batches_merged": r["batches_merged"],
                "merge_rate": r["merge_rate"],
            }
            for r in rows
        ]

    def _drop_lost(self, job_id: str) -> None:
        """Another server holds the job now (its lease was taken over, or a write was refused
        by its fence): forget it here, with what was merged since its last checkpoint (the
        new owner renders that again from the checkpoint, the same batches, so the same
        bits). Its workers' tasks are cancelled; readers get its row from the database."""
        self._pending_events = [e for e in self._pending_events if e[0] != job_id]
        self._pending_finishes = [j for j in self._pending_finishes if j != job_id]
        if job_id not in self.scheduler.jobs:
            return
        log.warning("job %s is owned by another server now; dropped here", job_id)
        self.jobs_lost += 1
        self._forget_here(job_id)

    def _forget_here(self, job_id: str) -> None:
        """Forget a job another server holds now (lost, or handed over): its tasks on the
        workers are cancelled; readers get its row from the database."""
        self._handing_off.pop(job_id, None)
        self.scheduler.drop_job(job_id)
        self._forget_movies(job_id)
        for table in (self.history, self.names, self.created, self.owners):
            table.pop(job_id, None)
        self._generation[job_id] = self._generation.get(job_id, 0) + 1
        self._waiting_dirty = True

    # -------------------------------------------------------------------- after changes
    async def _after_change(self) -> None:
        """Send cancellations and new leases, store events, finish jobs, wake watchers."""
        # Only the workers with cancellations, then only those with room for a lease: a
        # result's change costs the same with ten workers connected or ten thousand.
        for worker_id in list(self.scheduler.cancellations):
            session = self.sessions.get(worker_id)
            cancels = self.scheduler.take_cancellations(worker_id) if session else []
            if cancels:
                session.outbox.put_nowait(("cancel", cancels))
        if not self.draining:
            for lease in self.scheduler.assign_free(self._may_lease, self.sessions.__contains__):
                self.sessions[lease.worker_id].outbox.put_nowait(
                    ("assign", lease, self.scheduler.jobs[lease.job_id])
                )
        events = self.scheduler.take_events()
        finished = [e.job_id for e in events if e.kind == "job_finished"]
        for job_id in finished:  # readers see the final point at once
            self._sample_history_final(job_id)
        # Stored by flush() from the background task: a slow or absent database never holds
        # up a merge or a worker stream.
        self._pending_events.extend((e.job_id, e.kind, e.data) for e in events)
        self._pending_finishes.extend(finished)
        self._changed.notify()

    def _forget_later(self, job_id: str) -> None:
        """Keep a finished job in memory for a minute (fast image requests), then drop it.
        A job that outgrew the tile cache gives its RAM back now (its checkpoint is written):
        its tiles go to its spill file, which its images read until it is dropped."""

        generation = self._generation.get(job_id, 0)

        async def forget() -> None:
            while self.scheduler.cache.evict_job(job_id, checkpoints.CHECKPOINT_CHUNK_BYTES):
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

    # ---------------------------------------------------------------------- durability


USD_EVENT_WARNINGS = 200


def _usd_event(usd: UsdImport) -> dict[str, Any]:
    """The job's record of its USD source: hash, file name, and what the conversion could not
    carry (one message per prim path and problem, at most USD_EVENT_WARNINGS)."""
    warnings = usd.warnings[:USD_EVENT_WARNINGS]
    if len(usd.warnings) > USD_EVENT_WARNINGS:
        warnings.append(f"{len(usd.warnings) - USD_EVENT_WARNINGS} more warnings left out")
    return {
        "source_format": "usd",
        "source_sha256": usd.source_sha256,
        "source_filename": usd.source_filename,
        "warnings": warnings,
        "camera": usd.camera,
    }
