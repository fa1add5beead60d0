"""FarmService with a job larger than its tile cache, without a database: checkpoints in chunks
with every tile, images from spilled tiles, a last checkpoint that gives up at its deadline."""

from __future__ import annotations

import asyncio
from datetime import UTC, datetime
from types import SimpleNamespace

import numpy as np
from test_scheduler import render

from renderfarm.app import checkpoints
from renderfarm.app.auth import LOCAL_USER
from renderfarm.app.composition import build_farm_service
from renderfarm.app.jobs import FarmService
from renderfarm.domain.jobspec import JobSettings
from renderfarm.infra.config import Settings
from renderfarm.infra.images import read_exr

JOB = JobSettings(width=256, height=192, tile_size=32, max_spp=8, noise_threshold=0)
TILE_BYTES = 76 * 32 * 32  # float64 RGB, mean, 2 M2; float32 coverage, albedo, normal


class RecordingStore:
    """Takes every write; save_tiles can be made to hang (a database that stopped answering)."""

    def __init__(self, hang: bool = False):
        self.saved: list[list] = []
        self.hang = hang

    async def save_tiles(self, job_id, rows, fence=None):
        if self.hang:
            await asyncio.Event().wait()
        self.saved.append(rows)

    async def update_job(self, job_id, fence=None, **fields):
        pass

    async def add_events(self, events, fences=None):
        pass

    async def get_job(self, job_id):  # what an image reads of the job's row: times, variants
        return SimpleNamespace(
            created_at=datetime(2026, 1, 2, tzinfo=UTC), finished_at=None, variants=[]
        )

    async def get_job_scene_source(self, job_id):  # the EXR header: not converted from USD
        return None

    async def get_scene_source(self, sha256):  # the EXR header: not converted from USD
        return None

    async def get_scene_info(self, sha256):  # the EXR header's camera: no scene stored
        return None

    async def read_scene(self, sha256, offset, length):  # the EXR header's metadata: none
        return b""


def farm(tmp_path, cache_mb: int, store=None) -> FarmService:
    service = build_farm_service(Settings(data_dir=tmp_path, tile_cache_mb=cache_mb), store)
    service.scheduler.add_job("j", JOB, "0" * 64)
    return service


def merge_batches(service: FarmService, batches: int) -> None:
    """Every tile's first `batches` batches, with albedo and normal sums."""
    sched = service.scheduler
    sched.add_worker("w", 1)
    job = sched.jobs["j"]
    for _ in range(len(job.tiles) * batches):
        (lease,) = sched.assign("w")
        result = render(JOB, lease)
        rgb = result.rgb_sum.astype(np.float32)
        from dataclasses import replace

        sched.complete(lease.task_id, replace(result, albedo_sum=rgb / 2, normal_sum=rgb / 4))


def test_a_large_checkpoint_is_written_in_chunks_holding_every_tile(tmp_path, monkeypatch):
    store = RecordingStore()
    service = farm(tmp_path, 1, store)  # 48 tiles of 76 KB: most of them go to the file
    merge_batches(service, 2)
    cache = service.scheduler.cache
    job = service.scheduler.jobs["j"]
    assert sum(not t.acc.resident for t in job.tiles) > len(job.tiles) // 2
    monkeypatch.setattr(checkpoints, "CHECKPOINT_CHUNK_BYTES", 5 * TILE_BYTES)
    asyncio.run(service._persist_job("j", tiles=True))
    assert [len(rows) for rows in store.saved] == [5] * 9 + [3]  # one transaction per chunk
    rows = [r for chunk in store.saved for r in chunk]
    assert sorted(r.tile_index for r in rows) == list(range(len(job.tiles)))
    for r in rows:
        acc = job.tiles[r.tile_index].acc
        cache.use(acc)
        assert bytes(r.accumulators) == bytes(acc.to_bytes())
        assert bytes(r.aovs) == bytes(acc.aovs_to_bytes())
    assert not any(t.dirty or t.aovs_dirty for t in job.tiles)


def test_images_of_a_spilled_job_are_those_of_one_in_ram(tmp_path):
    files = {}
    for name, cache_mb in (("ram", 64), ("spilled", 1)):
        service = farm(tmp_path / name, cache_mb, RecordingStore())
        merge_batches(service, 3)
        for fmt, layer, size in (("exr", "rgb", 0), ("png", "rgb", 0), ("png", "error", 100)):

            async def image(s=service, fmt=fmt, layer=layer, size=size) -> bytes:
                with await s.image_file("j", fmt, layer, LOCAL_USER, max_size=size) as f:
                    return f.read()

            data = asyncio.run(image())
            if fmt == "exr":  # its header has the time it was written: compare the channels
                (tmp_path / "a.exr").write_bytes(data)
                data = {c: v.tobytes() for c, v in read_exr(str(tmp_path / "a.exr")).items()}
            files[name, fmt, layer] = data
        # Nothing is left behind but the spilled job's tiles.
        left = sorted(p.name for p in (tmp_path / name / "scratch").iterdir())
        assert left == ([] if name == "ram" else ["j.tiles"])
    for fmt, layer in (("exr", "rgb"), ("png", "rgb"), ("png", "error")):
        assert files["ram", fmt, layer] == files["spilled", fmt, layer], (fmt, layer)


def test_the_last_checkpoint_gives_up_at_its_deadline_and_keeps_its_tiles_dirty(tmp_path):
    store = RecordingStore(hang=True)
    service = farm(tmp_path, 64, store)
    merge_batches(service, 1)

    async def stop():
        await asyncio.wait_for(service.stop(timeout_s=0.2), timeout=60)  # a hang fails here

    asyncio.run(stop())
    job = service.scheduler.jobs["j"]
    assert all(t.dirty for t in job.tiles)  # not written: rendered again after a restart
    assert not (tmp_path / "scratch").exists() or not list((tmp_path / "scratch").iterdir())
