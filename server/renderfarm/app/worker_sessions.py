"""Workers as FarmService sees them: a session per connected worker stream (its outbox of
assignments and cancellations, its heartbeat figures), hello and goodbye, results and failures
handed to the scheduler, and the operator's drain/disable/enable.
"""

from __future__ import annotations

import asyncio
import logging
import secrets
import time
from dataclasses import dataclass, field
from typing import Any

import psycopg
from psycopg_pool import PoolTimeout

from ..domain.records import BatchResult
from ..errors import Forbidden, NotFound, Unauthenticated
from .auth import Caller, check_caller

log = logging.getLogger(__name__)


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
    # The rows of the channel table it renders (Hello.channels; None: every row).
    renders: tuple[str, ...] | None = None
    tasks_done: int = 0


class WorkerSessions:
    """Part of FarmService (jobs.py), whose __init__ sets the attributes used here."""

    async def worker_hello(
        self,
        worker_id: str,
        hostname: str,
        cores: int,
        max_in_flight: int,
        version: str,
        token: str,
        tags: list[str] | None = None,
        renders: list[str] | None = None,
    ) -> WorkerSession:
        """A worker connects: its session. renders: the rows of the channel table it renders
        (Hello.channels; an empty list: those every job has, as workers from before the field
        render; None: every row, for callers inside the server)."""
        if self.settings.worker_token and not secrets.compare_digest(
            token.encode(), self.settings.worker_token.encode()
        ):
            raise Unauthenticated("wrong or missing worker token")
        worker_id = (worker_id or f"worker-{secrets.token_hex(3)}")[:100]
        if worker_id in self.sessions:  # a reconnect racing its old stream, or a clash
            old = self.sessions.pop(worker_id)
            old.outbox.put_nowait(None)
            self.scheduler.remove_worker(worker_id)
        now = self.clock()
        session = WorkerSession(
            worker_id, hostname[:200], max(1, cores), version[:50],
            connected_unix_s=now, last_heartbeat_unix_s=now,
        )  # fmt: skip
        session.tags = tuple(tags or ())
        self.sessions[worker_id] = session
        session.renders = None if renders is None else tuple(renders)
        self.scheduler.add_worker(
            worker_id, max(1, min(max_in_flight or cores + 2, 256)), tags=session.tags,
            renders=session.renders,
        )  # fmt: skip
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
        self,
        session: WorkerSession,
        samples_per_s: float,
        rays_per_s: float,
        busy: int,
        max_in_flight: int = 0,
    ) -> None:
        session.last_heartbeat_unix_s = self.clock()
        session.samples_per_s, session.rays_per_s, session.busy_threads = (
            samples_per_s,
            rays_per_s,
            busy,
        )
        self.scheduler.heartbeat(session.worker_id)
        # A worker that serves several servers says how many tasks it wants from this one now
        # (workers.proto, Heartbeat.max_in_flight); more credit means more leases at once.
        if max_in_flight and self.scheduler.set_credit(
            session.worker_id, max(1, min(max_in_flight, 256))
        ):
            await self._after_change()

    async def worker_result(self, session: WorkerSession, task_id: str, result: BatchResult) -> str:
        outcome = self._take_result(session, task_id, result)
        await self._after_change()
        return outcome

    async def worker_results(
        self, session: WorkerSession, results: list[tuple[str, BatchResult]]
    ) -> list[str]:
        """Several results of one message (workers.proto, TileResults), each taken as if it
        had come alone, in order; the farm changes (new leases, events, wake-ups) once."""
        outcomes = [self._take_result(session, task_id, result) for task_id, result in results]
        await self._after_change()
        return outcomes

    def _take_result(self, session: WorkerSession, task_id: str, result: BatchResult) -> str:
        started = time.perf_counter()
        self.scheduler.task_warnings(session.worker_id, result)  # whatever becomes of the result
        # The pixels the task rendered: its mask's (per-pixel adaptive sampling) or the rect's.
        lease = self.scheduler.leases.get(task_id)
        pixels = lease.pixels if lease is not None else result.rect.pixels
        outcome = self.scheduler.complete(task_id, result)
        if self.metrics is not None:
            self.metrics.merge_seconds.observe(time.perf_counter() - started)
            self.metrics.task_completed(outcome)
            self.metrics.task_seconds.observe(result.render_seconds)
            if outcome in ("merged", "pending"):
                self.metrics.samples_merged.inc(result.sample_count * pixels)
        if outcome in ("merged", "pending"):
            self.batches_merged += 1
        session.tasks_done += 1
        if outcome not in ("merged", "pending"):
            log.debug("result %s of job %s discarded: %s", task_id, result.job_id, outcome)
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
        check_caller(caller)
        if not caller.admin:
            raise Forbidden("only an admin token may drain, disable or enable workers")
        if worker_id not in self.sessions:
            raise NotFound(f"no connected worker with id {worker_id!r}")
        back = self.scheduler.set_worker_mode(worker_id, mode)
        log.info("worker %s set %s (%d tasks handed back)", worker_id, mode, len(back))
        await self._after_change()
        return next(w for w in self.workers() if w["id"] == worker_id)
