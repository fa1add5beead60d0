"""Convergence history (image error against time) of live jobs, and the tile stops of a job."""

from __future__ import annotations

from typing import Any

from ..domain.states import JobState
from .auth import Caller
from .views import finite_or_none


class History:
    """Part of FarmService (jobs.py), whose __init__ sets the attributes used here."""

    HISTORY_POINTS = 2000

    def _sample_history(self) -> None:
        """One (elapsed, error, mean spp) point per running job and round, when it changed."""
        for job in self.scheduler.jobs.values():
            if job.state != JobState.RUNNING:
                continue
            p = self.scheduler.progress(job)
            points = self.history.setdefault(job.job_id, [])
            point = (round(p.elapsed_s, 3), finite_or_none(p.error), p.mean_spp)
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
        points.append((round(p.elapsed_s, 3), finite_or_none(p.error), p.mean_spp))

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
                "error": finite_or_none(t.stop.error),
                "reason": t.stop.reason.value,
            }
            for t in job.tiles
            if t.stop is not None
        ]
