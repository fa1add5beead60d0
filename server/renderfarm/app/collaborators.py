"""What FarmService depends on besides its settings, store and scheduler, as interfaces it is
given (docs/architecture.md, "Composition"): the clock, the judge of uploaded scenes, the USD
converter and job ownership. app/composition.py builds the implementations a server runs with;
tests give fakes.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

from ..infra.usd_import import UsdImport

Clock = Callable[[], float]
"""Unix time in seconds (time.time). FarmService reads it for checkpoint intervals, the
database's retry backoff and workers' connect and heartbeat times; the scheduler it is given
should read the same clock (lease deadlines, time limits, elapsed times)."""


class SceneInspector(Protocol):
    """The judge of uploaded scenes: the workers' own loader (infra/scene_check.SceneChecker)."""

    async def check(self, data: bytes, filename: str, sha256: str) -> dict[str, Any]:
        """The loader's description of the scene, or SceneError naming the fault."""
        ...

    async def cameras(
        self,
        data: bytes,
        filename: str,
        times: list[float] | None,
        animation: str = "",
        shutter: str = "",
        fps: float = 24.0,
    ) -> list[dict[str, Any]]:
        """The camera the renderer sees each image through: the still's (times None) or the
        camera at each glTF time, posed by the animations `animation` selects (app/
        job_cameras.py asks it; domain/camera.py reads its answer)."""
        ...


class UsdConverter(Protocol):
    """USD uploads to glTF before they are inspected (infra/usd_import.UsdImporter)."""

    def is_usd(self, data: bytes | None, filename: str = "") -> bool: ...

    async def convert(self, data: bytes, filename: str) -> UsdImport: ...


class Ownership(Protocol):
    """Which jobs this server may render and write. A farm of one server owns every job
    (SoleOwner); a farm of several (#39) gives each job to one of them by a lease in the
    database, whose epoch fences the writes of a server that lost it (infra/leases.py,
    LeaseOwnership).

    owns, epoch, fence and take_lost are read on the merge and lease paths and must not wait;
    acquire, release and heartbeat may ask the database. FarmService acquires a job when it is
    submitted, resumed at start or taken over, retried or continued, releases it once its final
    state is stored, and calls heartbeat every background round."""

    replica_id: str
    """This server's name in the farm (RENDERFARM_REPLICA_ID), shown as a job's `replica`."""

    shared: bool
    """True when other servers may hold jobs of the same database: the service then looks
    for jobs nobody holds (takeover) and forwards job control to a job's owner."""

    def owns(self, job_id: str) -> bool:
        """Whether this server holds the job now: only then are its tasks leased to workers
        and its checkpoints written."""
        ...

    def epoch(self, job_id: str) -> int:
        """The fencing token of this server's hold on the job, for its writes to carry (-1
        when it holds none)."""
        ...

    def fence(self, job_id: str) -> tuple[str, int] | None:
        """What a write of the job by its owner carries to the store: (replica_id, epoch), so
        that the database refuses it (LeaseLost) once another server holds the job; None
        when nothing needs fencing (a server alone)."""
        ...

    def take_lost(self) -> list[str]:
        """The jobs whose hold heartbeat found taken over since the last call (another server
        holds them now): the service drops them from memory."""
        ...

    async def acquire(self, job_id: str) -> bool:
        """Take the job; True when this server holds it now, False when another one does."""
        ...

    async def release(self, job_id: str) -> None:
        """Let the job go. Must not raise for a database outage: the hold, no longer
        renewed, lapses."""
        ...

    async def leave(self) -> None:
        """This server stops (its jobs released): the others stop counting it. Must not raise
        for a database outage."""
        ...

    async def heartbeat(self) -> None:
        """Renew this server's holds (called a few times a second; it may renew less often).
        Must not raise for a database outage: a hold not renewed lapses, and owns says so."""
        ...


class SoleOwner:
    """The farm of one server: it owns every job, at one epoch that never changes, and its
    writes need no fence."""

    EPOCH = 0
    shared = False

    def __init__(self, replica_id: str = ""):
        self.replica_id = replica_id

    def owns(self, job_id: str) -> bool:
        return True

    def epoch(self, job_id: str) -> int:
        return self.EPOCH

    def fence(self, job_id: str) -> tuple[str, int] | None:
        return None

    def take_lost(self) -> list[str]:
        return []

    async def acquire(self, job_id: str) -> bool:
        return True

    async def release(self, job_id: str) -> None:
        pass

    async def heartbeat(self) -> None:
        pass

    async def leave(self) -> None:
        pass
