"""Tiles out of RAM (spill.TileCache): bit-identical merges, copy-on-write slots, cleanup."""

from __future__ import annotations

import os

import numpy as np
import pytest
from test_scheduler import FakeClock, render

from renderfarm.domain import channels
from renderfarm.domain.jobspec import JobSettings
from renderfarm.domain.merge import TileAccumulator
from renderfarm.domain.scheduler import Scheduler
from renderfarm.infra.spill import TileCache

ARRAYS = channels.STATS_ARRAYS + channels.WINDOWED_ARRAYS
SETTINGS = JobSettings(
    width=72, height=40, tile_size=16, noise_threshold=0.01, min_spp=4, max_spp=128
)
PIXEL = 76  # bytes of a pixel's accumulators (float64 RGB, mean, 2 M2; float32 coverage, AOVs)
TILE_BYTES = PIXEL * 16 * 16  # one full tile's accumulators


def with_aovs(result):
    """The scheduler's fake render with albedo and normal sums (so the AOVs spill too),
    a function of the batch's samples like the rest of it."""
    from dataclasses import replace

    rgb = result.rgb_sum.astype(np.float32)
    return replace(result, albedo_sum=rgb * 0.5, normal_sum=rgb * 0.25)


def finish(sched: Scheduler, seed: int = 5) -> Scheduler:
    """Drive job j to completion with one fake worker, completing tasks in a fixed order."""
    sched.add_worker("w", 6)
    order = np.random.default_rng(seed)
    for _ in range(100000):
        sched.assign("w")
        if sched.jobs["j"].state.finished:
            return sched
        leases = list(sched.leases.values())
        assert leases, "the scheduler stalled"
        lease = leases[order.integers(len(leases))]
        sched.complete(lease.task_id, with_aovs(render(SETTINGS, lease)))
    raise AssertionError("the job did not finish")


def run(cache: TileCache | None) -> Scheduler:
    sched = Scheduler(clock=FakeClock(), cache=cache)
    sched.add_job("j", SETTINGS, "scene")
    return finish(sched)


def assert_same_tiles(a: Scheduler, b: Scheduler, cache: TileCache) -> None:
    ja, jb = a.jobs["j"], b.jobs["j"]
    assert [t.stop for t in ja.tiles] == [t.stop for t in jb.tiles]
    for ta, tb in zip(ja.tiles, jb.tiles, strict=True):
        assert (ta.acc.samples, ta.acc.batches) == (tb.acc.samples, tb.acc.batches)
        assert ta.error == tb.error  # the same float, not merely close
        for x, y in zip(arrays_of(None, ta.acc), arrays_of(cache, tb.acc), strict=True):
            assert x.dtype == y.dtype and x.tobytes() == y.tobytes()


def arrays_of(cache: TileCache | None, acc: TileAccumulator) -> list[np.ndarray]:
    if cache is not None:
        cache.use(acc)
    return [getattr(acc, name) for name in ARRAYS]


def test_spilled_tiles_merge_bit_for_bit_as_in_ram(tmp_path):
    in_ram = run(None)
    cache = TileCache(tmp_path / "scratch", budget_bytes=3 * TILE_BYTES)
    spilled = run(cache)
    tiles = len(spilled.jobs["j"].tiles)
    assert cache.evictions > 2 * tiles, "a budget of three tiles sends tiles to the file"
    assert cache.resident_bytes <= 3 * TILE_BYTES
    assert (tmp_path / "scratch" / "j.tiles").exists()
    assert_same_tiles(in_ram, spilled, cache)


def merged_acc(rng, samples=(1, 1, 2, 4)) -> TileAccumulator:
    acc = TileAccumulator(16, 8)
    for n in samples:
        acc.merge_batch(
            rng.random((8, 16, 3)) * n,
            rng.random((8, 16)),
            n,
            rng.random((8, 16, 3), dtype=np.float32),
            rng.random((8, 16, 3), dtype=np.float32),
        )
    return acc


def test_an_evicted_tiles_snapshot_outlives_later_merges_and_evictions(tmp_path):
    """A checkpoint or image reads an evicted tile's slot in another thread while the loop
    goes on: the slot it holds is never overwritten, later evictions take other slots."""
    rng = np.random.default_rng(1)
    cache = TileCache(tmp_path, budget_bytes=1)  # everything but the tile in use is evicted
    acc, other = merged_acc(rng), merged_acc(rng)
    cache.register("j", acc, 16)
    cache.register("j", other, 16)  # evicts acc: its arrays go to the file
    assert not acc.resident
    expected = [getattr(merged_acc(np.random.default_rng(1)), n).copy() for n in ARRAYS]
    stats, aovs = acc.snapshot(), acc.aov_snapshot()
    # The loop brings the tile back, merges a batch and evicts it again, twice.
    for _ in range(2):
        cache.use(acc)
        acc.merge_batch(rng.random((8, 16, 3)), rng.random((8, 16)), 8)
        cache.use(other)
    assert not acc.resident
    got = TileAccumulator.snapshot_arrays(stats) + TileAccumulator.snapshot_arrays(aovs)
    for x, y in zip(expected, got, strict=True):
        assert x.tobytes() == y.tobytes()
    # The accumulator itself has its newest arrays: two merges on top of the first four.
    cache.use(acc)
    assert acc.batches == 6 and acc.samples == 24


def test_checkpoint_bytes_of_an_evicted_tile_are_those_of_the_tile(tmp_path):
    rng = np.random.default_rng(2)
    acc = merged_acc(rng)
    want = (bytes(acc.to_bytes()), bytes(acc.aovs_to_bytes()))
    cache = TileCache(tmp_path, budget_bytes=1)
    cache.register("j", acc, 16)
    cache.register("j", merged_acc(rng), 16)
    assert not acc.resident
    got_stats = TileAccumulator.snapshot_bytes(acc.snapshot())
    got_aovs = TileAccumulator.snapshot_bytes(acc.aov_snapshot())
    assert (bytes(got_stats), bytes(got_aovs)) == want


def test_slots_are_reused_once_nobody_reads_them(tmp_path):
    rng = np.random.default_rng(3)
    cache = TileCache(tmp_path, budget_bytes=1)
    accs = [merged_acc(rng) for _ in range(3)]
    for acc in accs:
        cache.register("j", acc, 16)
    for _ in range(20):  # evicting and reloading without readers: no growth
        for acc in accs:
            cache.use(acc)
            acc.merge_batch(rng.random((8, 16, 3)), rng.random((8, 16)), 1)
    assert cache._files["j"].slots <= len(accs) + 1


def fd_count() -> int:
    return len(os.listdir("/proc/self/fd"))


def test_forgetting_a_job_removes_its_file_and_frees_its_ram(tmp_path):
    rng = np.random.default_rng(4)
    cache = TileCache(tmp_path / "scratch", budget_bytes=2 * PIXEL * 16 * 8)
    fds = fd_count()
    for job in ("a", "b"):
        for _ in range(4):
            cache.register(job, merged_acc(rng), 16)
    assert sorted(p.name for p in (tmp_path / "scratch").iterdir()) == ["a.tiles", "b.tiles"]
    cache.forget_job("a")
    assert [p.name for p in (tmp_path / "scratch").iterdir()] == ["b.tiles"]
    assert all(acc.spill.home.job_id == "b" for acc in cache._lru)
    cache.close()
    assert list((tmp_path / "scratch").iterdir()) == []
    assert cache.resident_bytes == 0
    assert fd_count() == fds


def test_a_removed_file_stays_readable_for_snapshots_taken_before(tmp_path):
    rng = np.random.default_rng(6)
    cache = TileCache(tmp_path, budget_bytes=1)
    acc = merged_acc(rng)
    want = bytes(acc.to_bytes())
    fds = fd_count()
    cache.register("j", acc, 16)
    cache.register("j", merged_acc(rng), 16)
    snapshot = acc.snapshot()
    cache.forget_job("j")  # a delete while a checkpoint thread has yet to read it
    assert not (tmp_path / "j.tiles").exists()
    assert bytes(TileAccumulator.snapshot_bytes(snapshot)) == want
    assert fd_count() == fds  # the last reader closed the file


def test_finished_jobs_give_their_ram_back_a_chunk_at_a_time(tmp_path):
    rng = np.random.default_rng(7)
    cache = TileCache(tmp_path, budget_bytes=5 * PIXEL * 16 * 8)
    for _ in range(8):  # three of them spill
        cache.register("j", merged_acc(rng), 16)
    assert cache.resident_bytes == 5 * PIXEL * 16 * 8
    assert cache.evict_job("j", limit_bytes=2 * PIXEL * 16 * 8)  # more is left
    assert cache.resident_bytes == 3 * PIXEL * 16 * 8
    assert not cache.evict_job("j", limit_bytes=10 * PIXEL * 16 * 8)
    assert cache.resident_bytes == 0
    assert not cache.evict_job("never-spilled", limit_bytes=1)


def test_clear_directory_removes_what_a_crashed_server_left(tmp_path):
    scratch = tmp_path / "scratch"
    scratch.mkdir()
    (scratch / "old.tiles").write_bytes(b"x" * 100)
    (scratch / "tmpimage.exr").write_bytes(b"x")
    TileCache(scratch, budget_bytes=1).clear_directory()
    assert not scratch.exists() or list(scratch.iterdir()) == []


@pytest.mark.parametrize("budget_tiles", [1, 4])
def test_restored_tiles_spill_as_they_come_and_resume_alike(tmp_path, budget_tiles):
    """Resuming from checkpoints under a small budget: the tiles go to the file as they are
    registered, and the resumed job finishes with the same statistics as one never stopped."""
    in_ram = run(None)
    # Checkpoints part of the way: three batches a tile, dispatched as the scheduler likes.
    sched = Scheduler(clock=FakeClock())
    sched.add_job("j", SETTINGS, "scene")
    sched.add_worker("w", 1)
    for _ in range(len(sched.jobs["j"].tiles) * 3):
        (lease,) = sched.assign("w")
        sched.complete(lease.task_id, with_aovs(render(SETTINGS, lease)))
    job = sched.jobs["j"]
    assert all(t.merged for t in job.tiles) and not job.state.finished
    checkpoint = {
        t.index: TileAccumulator.from_bytes(
            t.rect.width, t.rect.height, bytes(t.acc.to_bytes()), t.acc.samples,
            t.acc.batches, aovs=bytes(t.acc.aovs_to_bytes()),
        )
        for t in job.tiles
    }  # fmt: skip
    plans = {t.index: Scheduler.planned_batches(t) for t in job.tiles}
    budget = budget_tiles * TILE_BYTES
    cache = TileCache(tmp_path, budget_bytes=budget)
    for acc in checkpoint.values():
        cache.register("j", acc, SETTINGS.tile_size)
        assert cache.resident_bytes <= budget
    resumed = Scheduler(clock=FakeClock(), cache=cache)
    resumed.add_job("j", SETTINGS, "scene", checkpoint=checkpoint, state=job.state, plans=plans)
    assert cache.resident_bytes <= budget and cache.evictions > 0
    for ta, tb in zip(job.tiles, resumed.jobs["j"].tiles, strict=True):
        assert ta.error == tb.error
    assert_same_tiles(in_ram, finish(resumed), cache)
