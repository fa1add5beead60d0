"""FarmService's database writes without a database: what they write, in which order, and
what happens when they are interrupted."""

from __future__ import annotations

import asyncio

from renderfarm.app.composition import build_farm_service
from renderfarm.domain.jobspec import JobSettings
from renderfarm.infra.config import Settings


class RecordingStore:
    """Records add_events calls; `during` runs once, inside the first write (as a merge that
    lands while the write awaits the database would)."""

    def __init__(self):
        self.log: list[tuple[str, object]] = []
        self.during = None

    async def add_events(self, batch, fences=None):
        self.log.append(("events", [(job, kind) for job, kind, _ in batch]))
        if self.during:
            hook, self.during = self.during, None
            hook()
        await asyncio.sleep(0)


def test_a_job_is_never_stored_finished_before_its_event(tmp_path):
    store = RecordingStore()
    service = build_farm_service(Settings(data_dir=tmp_path), store)

    async def persist(job_id, tiles):  # the job row with its final state
        store.log.append(("job", job_id))

    service._persist_job = persist
    service._forget_later = lambda job_id: None
    service._pending_events.append(("a", "tile_stopped", {}))

    def job_b_finishes():  # what _after_change does when a job finishes: both lists at once
        service._pending_events.append(("b", "job_finished", {}))
        service._pending_finishes.append("b")

    store.during = job_b_finishes
    assert asyncio.run(service.flush(force=True))
    order = [entry for entry in store.log if entry != ("events", [("b", "convergence")])]
    assert order == [
        ("events", [("a", "tile_stopped")]),
        ("events", [("b", "job_finished")]),
        ("job", "b"),
    ]
    # Everything that arrived during the flush was written by it.
    assert not service._pending_events and not service._pending_finishes


class StallingStore:
    """save_tiles waits until cancelled, as a write to a slow database would when the server
    stops."""

    def __init__(self):
        self.entered = asyncio.Event()

    async def save_tiles(self, job_id, rows, fence=None):
        self.entered.set()
        await asyncio.Event().wait()


def test_a_checkpoint_cancelled_mid_write_leaves_its_tiles_to_the_next(tmp_path):
    store = StallingStore()
    service = build_farm_service(Settings(data_dir=tmp_path), store)
    settings = JobSettings(width=16, height=16, tile_size=8, max_spp=4)
    job = service.scheduler.add_job("j", settings, "0" * 64)
    for t in job.tiles[:3]:
        t.dirty = True
    job.tiles[1].aovs_dirty = True

    async def interrupted():
        task = asyncio.create_task(service._persist_job("j", tiles=True))
        await store.entered.wait()
        task.cancel()
        try:
            await task
        except asyncio.CancelledError:
            pass

    asyncio.run(interrupted())
    # The next checkpoint (stop()'s last one) writes them: nothing merged is lost.
    assert [t.dirty for t in job.tiles] == [True, True, True, False]
    assert [t.aovs_dirty for t in job.tiles] == [False, True, False, False]
