"""Job ownership in a farm of several servers (#39): LeaseOwnership, the implementation of
app.collaborators.Ownership over the job_leases table (docs/architecture.md, "Ownership, leases
and fencing").

Each unfinished job is held by one replica through its lease row: (replica_id, epoch,
expires_at), expiry by the database's clock. acquire takes a job nobody holds (or that this
replica's id held before a restart) in one statement, at epoch + 1; heartbeat renews this
replica's leases every lease_s / 4 and forgets those it could not renew (another replica took
them over: take_lost names them); release lets a lease expire at once. Every write of an owner
carries fence() = (replica_id, epoch), which the store checks in the write's transaction, so
a replica that lost a job (paused, cut off, slow) cannot overwrite its successor's work.

owns() answers from memory: true until a local monotonic deadline computed from when the last
renewal was *sent*, minus a margin, so it turns false before the database's expiry (which
counts from when the renewal arrived) lets another replica take the job. That keeps a replica
from leasing a job's tasks after it may have lost it; correctness does not depend on it (the
fence does), only wasted work does.

One exception: a replica whose last heartbeat found no other live replica (`alone`, the farm of
one server) keeps owning its holds while the database is away, so that it goes on rendering
through an outage as a server alone always did (docs/operations.md, "Reliability"). Were a
replica to start during the outage and take the jobs once the database is back, the fence
refuses the first one's writes: its unsaved merges are lost, never the image.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import psycopg
from psycopg_pool import PoolTimeout

from .store import Fence, Store

log = logging.getLogger(__name__)

_DATABASE_ERRORS = (psycopg.Error, PoolTimeout, OSError)


@dataclass(frozen=True)
class Hold:
    epoch: int
    deadline: float  # local monotonic time until which owns() is true


class LeaseOwnership:
    """Ownership by leases in PostgreSQL (see the module's docstring)."""

    shared = True

    def __init__(
        self,
        store: Store,
        replica_id: str,
        *,
        lease_s: float = 8.0,
        addresses: dict[str, str] | None = None,
        monotonic: Callable[[], float] = time.monotonic,
        clock: Callable[[], float] = time.time,
    ):
        if not replica_id:
            raise ValueError("a replica needs an id")
        self.store = store
        self.replica_id = replica_id
        self.lease_s = lease_s
        self.renew_every_s = lease_s / 4
        # owns() turns false this long before the database's expiry (at the earliest): a
        # renewal that takes longer than lease_s / 2 to be answered leaves the job unowned.
        self.margin_s = lease_s / 4
        self.addresses = dict(addresses or {})
        self.merged: Callable[[], int] = lambda: 0  # batches merged since start (the service's)
        self.renewal_failures = 0
        # No other live replica at the last heartbeat: holds do not lapse (module docstring).
        self.alone = False
        self._monotonic = monotonic
        self._started = clock()
        self._holds: dict[str, Hold] = {}
        self._lost: list[str] = []
        self._next_renewal = -math.inf
        self._last_count: tuple[float, int] | None = None

    # ------------------------------------------------------------------ without waiting
    def owns(self, job_id: str) -> bool:
        hold = self._holds.get(job_id)
        return hold is not None and (self.alone or self._monotonic() < hold.deadline)

    def epoch(self, job_id: str) -> int:
        hold = self._holds.get(job_id)
        return -1 if hold is None else hold.epoch

    def fence(self, job_id: str) -> Fence:
        return (self.replica_id, self.epoch(job_id))

    def take_lost(self) -> list[str]:
        lost, self._lost = self._lost, []
        return lost

    def held(self) -> list[str]:
        """The jobs this replica holds (whether or not owns() is true for them now)."""
        return list(self._holds)

    # --------------------------------------------------------------- asking the database
    async def acquire(self, job_id: str) -> bool:
        if self.owns(job_id):
            return True  # renewed by heartbeat; taking it again would fence our own writes
        sent = self._monotonic()
        try:
            epoch = await self.store.acquire_lease(job_id, self.replica_id, self.lease_s)
        except _DATABASE_ERRORS as e:
            log.warning("could not take the lease of job %s: %s", job_id, e)
            return False
        if epoch is None:
            self._holds.pop(job_id, None)
            return False
        self._holds[job_id] = Hold(epoch, sent + self.lease_s - self.margin_s)
        log.info("replica %s holds job %s at epoch %d", self.replica_id, job_id, epoch)
        return True

    async def release(self, job_id: str) -> None:
        hold = self._holds.pop(job_id, None)
        if hold is None:
            return
        try:
            await self.store.release_lease(job_id, self.replica_id, hold.epoch)
        except _DATABASE_ERRORS as e:  # not renewed, it lapses
            log.warning("could not release the lease of job %s: %s", job_id, e)

    async def leave(self) -> None:
        """This replica stops: its row goes (the others no longer count it when they share
        the jobs). Its holds are released by the service before."""
        try:
            await self.store.remove_replica(self.replica_id)
        except _DATABASE_ERRORS as e:  # its heartbeat ages out instead
            log.warning("could not remove replica %s: %s", self.replica_id, e)

    async def heartbeat(self) -> None:
        """Renew the holds (at most every lease_s / 4) and this replica's row. A hold the
        database no longer has at its epoch is dropped and reported by take_lost; while the
        database is unreachable nothing is renewed and owns() turns false at the deadlines."""
        sent = self._monotonic()
        if sent < self._next_renewal:
            return
        self._next_renewal = sent + self.renew_every_s
        held = {job_id: hold.epoch for job_id, hold in self._holds.items()}
        try:
            renewed = await self.store.renew_leases(self.replica_id, held, self.lease_s)
        except _DATABASE_ERRORS as e:
            self.renewal_failures += 1
            log.warning("could not renew the leases of replica %s: %s", self.replica_id, e)
            return
        deadline = sent + self.lease_s - self.margin_s
        for job_id, epoch in held.items():
            current = self._holds.get(job_id)
            if current is None or current.epoch != epoch:
                continue  # released or taken again while the renewal was on its way
            if renewed.get(job_id) == epoch:
                self._holds[job_id] = Hold(epoch, deadline)
            else:
                del self._holds[job_id]
                self._lost.append(job_id)
                log.warning(
                    "replica %s lost job %s (epoch %d): another server holds it",
                    self.replica_id, job_id, epoch,
                )  # fmt: skip
        await self._record_replica(sent)

    async def _record_replica(self, now: float) -> None:
        merged = self.merged()
        rate = 0.0
        if self._last_count is not None and now > self._last_count[0]:
            rate = (merged - self._last_count[1]) / (now - self._last_count[0])
        self._last_count = (now, merged)
        try:
            others = await self.store.replica_heartbeat(
                self.replica_id, self.addresses, self._started, merged, rate, 2 * self.lease_s
            )
            self.alone = others == 0
        except _DATABASE_ERRORS as e:
            log.warning("could not record replica %s: %s", self.replica_id, e)
