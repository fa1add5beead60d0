"""Job control of FarmService: pause, resume, update, retry and continue.

Each checks the caller's right to the job as cancel does, changes the state through the
scheduler's state machine (a refused change is 409 Conflict), writes the job's row at once (a
restart finds it as it is) and answers the job after the change.

In a farm of several servers (#39) a request for an unfinished job that another server owns is
forwarded through the database: a row in job_requests, which the owner applies in its next
background round (_apply_controls) and deletes once its writes are stored; the server that
took the request waits for that and answers the job as stored (docs/architecture.md,
"Ownership, leases and fencing"). Retry and continue need no forwarding: a finished job is held
by no one, and the server that takes the request takes the job.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import time
from typing import Any

from ..domain.continuation import CONTINUE_SETTINGS, continue_plan
from ..domain.jobspec import ALIASES, JobSettings, parse_settings
from ..domain.merge import NEVER
from ..domain.records import JobRun
from ..domain.scheduler import Scheduler
from ..domain.states import JobState, check_transition
from ..errors import Conflict, NotFound, SettingsError, TransitionError
from ..infra.store import DatabaseUnavailable
from . import checkpoints
from .auth import LOCAL_USER, Caller
from .views import JobView

log = logging.getLogger(__name__)

FORWARD_POLL_S = 0.1  # how often a forwarded request's row is looked at


class JobControl:
    """Part of FarmService (jobs.py), whose __init__ sets the attributes used here."""

    def _refused(self, job_id: str, state: JobState, action: str) -> Conflict:
        return Conflict(f"job {job_id} is {state.value}; it cannot be {action}")

    async def _live(self, job_id: str, caller: Caller, action: str) -> JobRun:
        view = await self.get(job_id, caller)  # raises NotFound / Forbidden
        job = self.scheduler.jobs.get(job_id)
        if job is None and self._elsewhere(view):
            raise _Forward(view)
        if job is None or self._reported_state(job) != job.state or job.state.finished:
            raise self._refused(job_id, view.state, action)
        return job

    async def pause(self, job_id: str, caller: Caller) -> JobView:
        try:
            job = await self._live(job_id, caller, "paused")
        except _Forward:
            return await self._forward(job_id, "pause", {}, caller)
        try:
            self.scheduler.pause_job(job_id)
        except TransitionError:
            raise self._refused(job_id, job.state, "paused") from None
        await self._after_change()
        await self._store_state(job_id)
        return await self.get(job_id, caller)

    async def resume(self, job_id: str, caller: Caller) -> JobView:
        try:
            job = await self._live(job_id, caller, "resumed")
        except _Forward:
            return await self._forward(job_id, "resume", {}, caller)
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
        if job_id not in self.scheduler.jobs and self._elsewhere(view):
            data = {"priority": priority, "name": name}
            return await self._forward(job_id, "update", data, caller)
        # The owner's write is fenced; a finished job's (no one holds it) is not.
        fence = self.ownership.fence(job_id) if self.ownership.epoch(job_id) >= 0 else None
        await self.store.update_job_spec(job_id, new_name, settings.to_dict(), fence=fence)
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
        renders again from its first sample (domain/continuation.py)."""
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
        variants = tuple(row.variants)
        for index, (_, acc) in checkpoints.restore_tiles(settings, tile_rows, variants).items():
            t = by_index[index]
            if settings == old:  # a retry: the tiles as they were
                checkpoint[index] = acc
                plans[index] = t.batch_plan or []
                bases[index] = t.plan_basis or []
                continue
            basis = {int(e[0]): tuple(e[1:]) for e in t.plan_basis or []}
            stopped = acc.stop_batch is not None and bool((acc.stop_batch != NEVER).any())
            kept = continue_plan(old, settings, acc.batches, basis, stopped)
            if kept is None:
                again.append(index)
                continue
            checkpoint[index] = acc
            plans[index] = kept[0]
            bases[index] = [[b, *kept[1][b]] for b in sorted(kept[1])]
        if not await self.ownership.acquire(job_id):  # another server brings it back
            raise self._refused(job_id, old_state, "brought back")
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
            variants=variants,
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
                render_again=again, tiles=kept_tiles, fence=self.ownership.fence(job_id),
            )  # fmt: skip
        except BaseException:
            # Not stored: the job stays as the database has it (finished, as it was).
            self.scheduler.jobs.pop(job_id, None)
            self.scheduler.cache.forget_job(job_id)
            self.scheduler.events = [e for e in self.scheduler.events if e.job_id != job_id]
            await self.ownership.release(job_id)
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

    # ------------------------------------------------------------- forwarded to the owner
    def _elsewhere(self, view: JobView) -> bool:
        """An unfinished job this server does not hold, in a farm of several: its owner (or
        whoever takes it over) applies control requests."""
        return self.ownership.shared and not view.state.finished

    async def _forward(
        self, job_id: str, action: str, data: dict[str, Any], caller: Caller
    ) -> JobView:
        """Ask the job's owner to apply `action` (the caller's right to the job is checked
        here) and wait until it has, at most twice the job lease and a few seconds (a dead
        owner's jobs are taken over within that); then the job as stored."""
        request_id = await self.store.request_control(job_id, action, data)
        deadline = time.monotonic() + 2 * self.settings.job_lease_s + 5.0
        while await self.store.control_pending(request_id):
            if time.monotonic() > deadline:
                await self.store.controls_done([request_id])
                raise DatabaseUnavailable(
                    f"the server that owns job {job_id} did not apply the request in time"
                )
            await asyncio.sleep(FORWARD_POLL_S)
        return await self.get(job_id, caller)

    async def _apply_controls(self) -> None:
        """The requests other servers forwarded for jobs this one holds, applied as this
        server's own requests would be (a refused one leaves the job as it is: the requester
        answers the job as stored). Their rows are deleted after the round's writes."""
        for request_id, job_id, action, data in await self.store.controls_for(
            self.ownership.replica_id
        ):
            if request_id in self._controls_applied:
                continue
            if job_id not in self.scheduler.jobs:
                continue  # not resumed here yet
            try:
                if action == "cancel":
                    self.scheduler.cancel_job(job_id)  # its final state: stored by flush
                    await self._after_change()
                elif action == "pause":
                    await self.pause(job_id, LOCAL_USER)
                elif action == "resume":
                    await self.resume(job_id, LOCAL_USER)
                elif action == "update":
                    await self.update(job_id, LOCAL_USER, data.get("priority"), data.get("name"))
            except (Conflict, SettingsError, NotFound, TransitionError) as e:
                log.info("forwarded %s of job %s refused: %s", action, job_id, e)
            self._controls_applied.append(request_id)

    async def _controls_stored(self) -> None:
        """The round's writes are stored (a cancel's final state too, by the flush before
        this): the forwarded requests applied are answered."""
        if self._controls_applied:
            await self.store.controls_done(self._controls_applied)
            self._controls_applied = []


class _Forward(Exception):
    """Raised by _live: the job is owned by another server; the request is forwarded."""

    def __init__(self, view: JobView):
        super().__init__(view.id)
        self.view = view
