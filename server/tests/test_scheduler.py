"""The scheduler as a spec: leases, in-order merging, stop rules, cancellation, determinism."""

import random

import numpy as np
import pytest

from renderfarm.domain import scheduler as scheduler_module
from renderfarm.domain.jobspec import JobSettings
from renderfarm.domain.records import BatchResult
from renderfarm.domain.scheduler import Scheduler
from renderfarm.domain.states import JobState, StopReason


class FakeClock:
    def __init__(self):
        self.now = 1000.0

    def __call__(self):
        return self.now


def pixel_samples(settings, rect, start, count):
    """A deterministic stand-in for the renderer: per (pixel, sample index) values whose noise
    depends on the pixel, so tiles converge at different rates."""
    ys, xs = np.mgrid[rect.y0 : rect.y0 + rect.height, rect.x0 : rect.x0 + rect.width]
    pixel = (ys * settings.width + xs).astype(np.uint64)
    idx = np.arange(start, start + count, dtype=np.uint64)[:, None, None]
    h = (pixel[None] * np.uint64(0x9E3779B97F4A7C15) + idx * np.uint64(0xBF58476D1CE4E5B9)) ^ (
        np.uint64(settings.seed) * np.uint64(0x94D049BB133111EB)
    )
    h ^= h >> np.uint64(31)
    h *= np.uint64(0xD6E8FEB86659FD93)
    h ^= h >> np.uint64(32)
    u = (h >> np.uint64(11)).astype(np.float64) / 2.0**53
    noise = np.where(xs < settings.width // 2, 0.05, 1.0)[None]  # left half easy, right half hard
    value = 0.5 + noise * (u - 0.5)
    return np.repeat(value[..., None], 3, axis=-1)


def render(settings, lease):
    samples = pixel_samples(settings, lease.rect, lease.sample_start, lease.sample_count)
    y = samples @ np.array([0.2126, 0.7152, 0.0722])
    return BatchResult(
        job_id=lease.job_id,
        tile_index=lease.tile_index,
        batch_index=lease.batch_index,
        sample_start=lease.sample_start,
        sample_count=lease.sample_count,
        rect=lease.rect,
        rgb_sum=samples.sum(axis=0),
        luminance_m2=((y - y.mean(axis=0)) ** 2).sum(axis=0),
        render_seconds=1e-3,
    )


def run_farm(settings, workers, seed, credit=3, reorder=True, render=render, leases=None):
    """Drive a job to completion with `workers` fake workers completing tasks in random order
    (render(settings, lease): a task's result; leases: a list that gets every lease)."""
    clock = FakeClock()
    sched = Scheduler(clock=clock)
    sched.add_job("j", settings, "scene")
    rng = random.Random(seed)
    outstanding = []
    for w in range(workers):
        sched.add_worker(f"w{w}", credit)
    for _ in range(100000):
        for w in range(workers):
            for lease in sched.assign(f"w{w}"):
                outstanding.append(lease)
                if leases is not None:
                    leases.append(lease)
        cancelled = {t for w in range(workers) for t in sched.take_cancellations(f"w{w}")}
        outstanding = [lease for lease in outstanding if lease.task_id not in cancelled]
        if sched.jobs["j"].state.finished:
            break
        assert outstanding, "the scheduler stalled"
        lease = outstanding.pop(rng.randrange(len(outstanding)) if reorder else 0)
        sched.complete(lease.task_id, render(settings, lease))
        clock.now += 0.01
    return sched


SETTINGS = JobSettings(
    width=48, height=32, tile_size=16, noise_threshold=0.01, min_spp=4, max_spp=256
)


def test_one_and_many_workers_give_the_same_image_and_spp():
    one = run_farm(SETTINGS, workers=1, seed=1, credit=1, reorder=False).jobs["j"]
    for workers, seed in [(3, 2), (3, 3), (5, 4)]:
        many = run_farm(SETTINGS, workers=workers, seed=seed).jobs["j"]
        assert many.state == JobState.COMPLETED
        for a, b in zip(one.tiles, many.tiles, strict=True):
            assert a.acc.samples == b.acc.samples
            np.testing.assert_array_equal(a.acc.rgb_sum, b.acc.rgb_sum)
            np.testing.assert_array_equal(a.acc.m2_between, b.acc.m2_between)
            assert a.stop == b.stop


def test_adaptive_stop_gives_easy_tiles_fewer_samples():
    job = run_farm(SETTINGS, workers=2, seed=5).jobs["j"]
    easy = [t.acc.samples for t in job.tiles if t.rect.x0 + t.rect.width <= 24]
    hard = [t.acc.samples for t in job.tiles if t.rect.x0 >= 24]
    assert max(easy) < min(hard)
    for t in job.tiles:
        assert t.stop.reason in (StopReason.CONVERGED, StopReason.MAX_SPP)
        if t.stop.reason == StopReason.CONVERGED:
            assert t.stop.error < SETTINGS.noise_threshold and t.stop.spp >= SETTINGS.min_spp


def test_zero_threshold_renders_max_spp_everywhere():
    s = JobSettings(width=20, height=20, tile_size=8, noise_threshold=0, max_spp=24)
    job = run_farm(s, workers=2, seed=1).jobs["j"]
    assert all(t.acc.samples == 24 and t.stop.reason == StopReason.MAX_SPP for t in job.tiles)
    assert job.samples_merged == 24 * 400


def test_first_leases_cover_every_tile_before_any_second_batch():
    sched = Scheduler(clock=FakeClock())
    sched.add_job("j", SETTINGS, "scene")
    sched.add_worker("w", len(sched.jobs["j"].tiles))
    leases = sched.assign("w")
    assert sorted(lease.tile_index for lease in leases) == list(range(len(leases)))
    assert {lease.batch_index for lease in leases} == {0}
    # tiles_previewed counts tiles with a merged batch: the preview is full-frame at the end.
    job = sched.jobs["j"]
    assert sched.progress(job).tiles_previewed == 0
    for k, lease in enumerate(leases):
        sched.complete(lease.task_id, render(SETTINGS, lease))
        assert sched.progress(job).tiles_previewed == k + 1
    assert sched.progress(job).tiles_previewed == len(job.tiles)


def test_out_of_order_batches_wait_and_duplicates_are_discarded():
    s = JobSettings(width=16, height=16, tile_size=16, noise_threshold=0, max_spp=16)
    sched = Scheduler(clock=FakeClock())
    sched.add_job("j", s, "scene")
    sched.add_worker("w", 4)
    b0, b1, b2, b3 = sched.assign("w")
    assert [b.batch_index for b in (b0, b1, b2, b3)] == [0, 1, 2, 3]
    assert sched.complete(b2.task_id, render(s, b2)) == "pending"
    assert sched.progress(sched.jobs["j"]).tiles_previewed == 0  # batch 2 waits for 0 and 1
    assert sched.complete(b0.task_id, render(s, b0)) == "merged"
    assert sched.jobs["j"].tiles[0].merged == 1
    assert sched.complete(b1.task_id, render(s, b1)) == "merged"
    assert sched.jobs["j"].tiles[0].merged == 3  # 1 and the waiting 2
    assert sched.complete(b1.task_id, render(s, b1)) == "duplicate"
    assert sched.jobs["j"].tiles[0].acc.samples == 4


def test_expired_lease_is_released_and_late_result_merged_once():
    clock = FakeClock()
    s = JobSettings(width=16, height=16, tile_size=16, noise_threshold=0, max_spp=1)
    sched = Scheduler(clock=clock, lease_s=10)
    sched.add_job("j", s, "scene")
    sched.add_worker("frozen", 1)
    sched.add_worker("alive", 1)
    (lease,) = sched.assign("frozen")
    assert sched.assign("alive") == []
    clock.now += 5
    sched.heartbeat("frozen")  # a heartbeat extends the lease
    clock.now += 9
    sched.tick()
    assert sched.assign("alive") == []
    clock.now += 2
    sched.tick()
    assert sched.take_cancellations("frozen") == [lease.task_id]
    (again,) = sched.assign("alive")
    assert again.batch_index == lease.batch_index and again.task_id != lease.task_id
    # The frozen worker wakes up and delivers first: merged, and the re-lease is cancelled.
    assert sched.complete(lease.task_id, render(s, lease)) == "merged"
    assert sched.take_cancellations("alive") == [again.task_id]
    assert sched.jobs["j"].state == JobState.COMPLETED
    assert sched.complete(again.task_id, render(s, again)) == "unknown job"
    assert sched.jobs["j"].tiles[0].acc.samples == 1


def test_a_worker_whose_lease_expired_is_leased_nothing_until_it_is_heard_from():
    """A hung worker stays connected: the batches its expired leases hand back must go to the
    live worker, not straight back to it (which would repeat every lease period)."""
    clock = FakeClock()
    s = JobSettings(width=32, height=16, tile_size=16, noise_threshold=0, max_spp=1)
    sched = Scheduler(clock=clock, lease_s=10)
    sched.add_job("j", s, "scene")
    sched.add_worker("hung", 2)
    (a, b) = sched.assign("hung")
    clock.now += 11
    sched.tick()
    assert sched.leases_expired == 2
    assert sched.assign("hung") == []  # no heartbeat since: nothing for it
    sched.add_worker("alive", 2)
    taken = sched.assign("alive")
    assert sorted(t.tile_index for t in taken) == sorted([a.tile_index, b.tile_index])
    sched.heartbeat("hung")  # it is back; the two batches are the live worker's now
    assert sched.assign("hung") == []
    for lease in taken:
        assert sched.complete(lease.task_id, render(s, lease)) == "merged"
    assert sched.jobs["j"].state == JobState.COMPLETED


def test_a_heartbeat_after_an_expiry_makes_the_worker_eligible_again():
    clock = FakeClock()
    s = JobSettings(width=16, height=16, tile_size=16, noise_threshold=0, max_spp=1)
    sched = Scheduler(clock=clock, lease_s=10)
    sched.add_job("j", s, "scene")
    sched.add_worker("w", 1)
    (lease,) = sched.assign("w")
    clock.now += 11
    sched.tick()
    assert sched.assign("w") == []
    sched.heartbeat("w")
    (again,) = sched.assign("w")
    assert again.batch_index == lease.batch_index


def test_worker_disconnect_requeues_its_batches():
    s = JobSettings(width=16, height=16, tile_size=8, noise_threshold=0, max_spp=1)
    sched = Scheduler(clock=FakeClock())
    sched.add_job("j", s, "scene")
    sched.add_worker("a", 4)
    lost = sched.assign("a")
    assert len(lost) == 4
    assert sorted(lease.task_id for lease in sched.remove_worker("a")) == sorted(
        lease.task_id for lease in lost
    )
    sched.add_worker("b", 4)
    again = sched.assign("b")
    assert sorted((x.tile_index, x.batch_index) for x in again) == sorted(
        (x.tile_index, x.batch_index) for x in lost
    )


def test_only_workers_with_room_for_a_lease_are_offered_tasks():
    """free_workers(): the workers whose leases are fewer than their credit, so that a change
    asks only them (FarmService._after_change); a full worker leaves it, and comes back when a
    result, a lost lease or a larger credit makes room; a worker that left is not in it."""
    s = JobSettings(width=32, height=32, tile_size=8, noise_threshold=0, max_spp=64)
    sched = Scheduler(clock=FakeClock())
    sched.add_job("j", s, "scene")
    sched.add_worker("a", 2)
    sched.add_worker("b", 3)
    assert sched.free_workers() == ["a", "b"]
    first = sched.assign("a")
    assert len(first) == 2 and sched.free_workers() == ["b"]
    assert len(sched.assign("b")) == 3 and sched.free_workers() == []
    assert sched.complete(first[0].task_id, render(s, first[0])) == "merged"
    assert sched.free_workers() == ["a"]
    assert len(sched.assign("a")) == 1 and sched.free_workers() == []
    assert sched.set_credit("b", 5) and sched.free_workers() == ["b"]
    sched.remove_worker("b")
    assert sched.free_workers() == []
    sched.set_worker_mode("a", "disabled")  # its leases handed back: room, but not active
    assert sched.free_workers() == ["a"] and sched.assign("a") == []


def test_converged_tile_cancels_its_speculative_batches():
    s = JobSettings(width=8, height=8, tile_size=8, noise_threshold=0.5, min_spp=1, max_spp=4096)
    sched = Scheduler(clock=FakeClock())
    sched.add_job("j", s, "scene")
    sched.add_worker("w", 4)
    leases = sched.assign("w")
    assert len(leases) == 4  # batch 0 plus speculation
    tile = sched.jobs["j"].tiles[0]
    done = 0
    while tile.stop is None:
        sched.complete(leases[done].task_id, render(s, leases[done]))
        done += 1
    assert tile.stop.reason == StopReason.CONVERGED and done < 4
    rest = leases[done:]
    assert sched.take_cancellations("w") == [x.task_id for x in rest]
    for lease in rest:
        assert sched.complete(lease.task_id, render(s, lease)) == "unknown job"


def test_time_limit_stops_every_tile():
    clock = FakeClock()
    s = JobSettings(
        width=16, height=16, tile_size=8, noise_threshold=0, max_spp=4096, time_limit_s=5
    )
    sched = Scheduler(clock=clock)
    sched.add_job("j", s, "scene")
    sched.add_worker("w", 2)
    for lease in sched.assign("w"):
        sched.complete(lease.task_id, render(s, lease))
    clock.now += 6
    sched.tick()
    job = sched.jobs["j"]
    assert job.state == JobState.COMPLETED
    assert all(t.stop.reason == StopReason.TIME_LIMIT for t in job.tiles)


def test_cancel_job_cancels_leases():
    sched = Scheduler(clock=FakeClock())
    sched.add_job("j", SETTINGS, "scene")
    sched.add_worker("w", 3)
    leases = sched.assign("w")
    sched.cancel_job("j")
    assert sched.jobs["j"].state == JobState.CANCELLED
    assert sorted(sched.take_cancellations("w")) == sorted(x.task_id for x in leases)
    assert sched.assign("w") == []


def test_priority_then_fair_share():
    sched = Scheduler(clock=FakeClock())
    sched.add_job("low", JobSettings(width=64, height=64, tile_size=16, priority=0), "s")
    sched.add_job("high", JobSettings(width=64, height=64, tile_size=16, priority=5), "s")
    sched.add_worker("w", 4)
    assert {x.job_id for x in sched.assign("w")} == {"high"}
    sched2 = Scheduler(clock=FakeClock())
    sched2.add_job("a", JobSettings(width=64, height=64, tile_size=16), "s")
    sched2.add_job("b", JobSettings(width=64, height=64, tile_size=16), "s")
    sched2.add_worker("w", 6)
    jobs = [x.job_id for x in sched2.assign("w")]
    assert jobs.count("a") == jobs.count("b") == 3


def test_non_retryable_failure_fails_job_when_no_worker_can_render():
    sched = Scheduler(clock=FakeClock())
    sched.add_job("j", SETTINGS, "scene")
    sched.add_worker("w", 1)
    (lease,) = sched.assign("w")
    sched.failed(lease.task_id, "scene load: bad accessor", retryable=False)
    job = sched.jobs["j"]
    assert job.state == JobState.FAILED
    assert "bad accessor" in job.error_message


def test_resume_from_checkpoint_gives_the_same_image_without_rerendering():
    s = JobSettings(width=16, height=16, tile_size=8, noise_threshold=0.02, min_spp=2, max_spp=64)
    reference = run_farm(s, workers=1, seed=0).jobs["j"]
    # A checkpoint holding the first 3 batches of every tile, as a crashed server left it.
    first = Scheduler(clock=FakeClock())
    first.add_job("j", s, "scene")
    first.add_worker("w", 1)
    for _ in range(3 * len(first.jobs["j"].tiles)):
        (lease,) = first.assign("w")
        first.complete(lease.task_id, render(s, lease))
    checkpoint = {t.index: t.acc for t in first.jobs["j"].tiles}
    merged_before = {i: acc.batches for i, acc in checkpoint.items()}
    assert min(merged_before.values()) >= 2
    resumed = Scheduler(clock=FakeClock())
    resumed.add_job("j", s, "scene", checkpoint=checkpoint, state=JobState.RUNNING)
    resumed.add_worker("w", 2)
    rendered = []
    while not resumed.jobs["j"].state.finished:
        for lease in resumed.assign("w"):
            rendered.append((lease.tile_index, lease.batch_index))
            resumed.complete(lease.task_id, render(s, lease))
    # Nothing merged before the crash is rendered again.
    assert all(b >= merged_before[t] for t, b in rendered)
    for a, b in zip(reference.tiles, resumed.jobs["j"].tiles, strict=True):
        np.testing.assert_array_equal(a.acc.rgb_sum, b.acc.rgb_sum)
        assert a.stop == b.stop


@pytest.mark.parametrize("bad_index", [99, -1])
def test_results_for_unknown_tiles_are_refused(bad_index):
    sched = Scheduler(clock=FakeClock())
    sched.add_job("j", SETTINGS, "scene")
    sched.add_worker("w", 1)
    (lease,) = sched.assign("w")
    r = render(SETTINGS, lease)
    bad = BatchResult(**{**r.__dict__, "tile_index": bad_index})
    assert sched.complete(lease.task_id, bad).startswith("mismatch")
    # The batch is not lost: it is leased again (the refusal counts as a failed task).
    (again,) = sched.assign("w")
    assert (again.tile_index, again.batch_index) == (lease.tile_index, lease.batch_index)
    assert sched.complete(again.task_id, render(SETTINGS, again)) == "merged"


@pytest.mark.parametrize("bad_value", [np.nan, np.inf])
def test_non_finite_results_are_refused_and_the_worker_is_kept_off(bad_value):
    """A NaN or infinity from a faulty worker never reaches a tile's sums: the result is
    refused, its batch leased again, and after max_task_failures such results the worker is
    kept off the job (which fails when no worker is left)."""
    sched = Scheduler(clock=FakeClock(), max_task_failures=2)
    sched.add_job("j", SETTINGS, "scene")
    sched.add_worker("bad", 1)
    for attempt in range(2):
        (lease,) = sched.assign("bad")
        assert lease.batch_index == 0 and lease.tile_index == 0
        r = render(SETTINGS, lease)
        field = "rgb_sum" if attempt == 0 else "luminance_m2"
        values = getattr(r, field).copy()
        values.flat[5] = bad_value
        outcome = sched.complete(lease.task_id, BatchResult(**{**r.__dict__, field: values}))
        assert outcome == "mismatch: non-finite values"
        assert sched.jobs["j"].tiles[0].merged == 0 and sched.jobs["j"].tiles[0].acc.samples == 0
    assert "bad" in sched.jobs["j"].excluded_workers
    assert sched.jobs["j"].state == JobState.FAILED


PLANNED = JobSettings(width=32, height=16, tile_size=16, noise_threshold=0.04, max_spp=1024)


def test_planned_batches_stop_hard_tiles_near_the_threshold_with_fewer_samples(monkeypatch):
    planned = run_farm(PLANNED, workers=2, seed=7).jobs["j"]
    monkeypatch.setattr(scheduler_module, "PLANNED_FROM", 10**9)  # the fixed schedule only
    fixed = run_farm(PLANNED, workers=2, seed=7).jobs["j"]
    hard = [i for i, t in enumerate(planned.tiles) if t.rect.x0 >= 16]
    for job in (planned, fixed):
        for i in hard:
            stop = job.tiles[i].stop
            assert stop.reason == StopReason.CONVERGED and stop.spp > 64  # past the ramp
            assert stop.error < PLANNED.noise_threshold
    # The fixed schedule can only stop at 64 + 64 k samples; the plan cuts the last batch to
    # what the error predicts, so the stop lands closer to the threshold.
    assert all(fixed.tiles[i].stop.spp % 64 == 0 for i in hard)
    for i in hard:
        assert planned.tiles[i].stop.spp < fixed.tiles[i].stop.spp
        assert planned.tiles[i].stop.error > fixed.tiles[i].stop.error
        assert planned.tiles[i].stop.error > 0.85 * PLANNED.noise_threshold


def test_resume_mid_plan_renders_the_planned_batches():
    """A checkpoint taken while tiles have planned batches, restored with its plans, finishes
    with the image and stops of an uninterrupted run."""
    reference = run_farm(PLANNED, workers=1, seed=0).jobs["j"]
    first = Scheduler(clock=FakeClock())
    first.add_job("j", PLANNED, "scene")
    first.add_worker("w", 2)
    job = first.jobs["j"]
    for _ in range(10000):  # until every live tile is past the ramp (its batches are planned)
        if all(t.stopped or t.merged >= 8 for t in job.tiles):
            break
        for lease in first.assign("w"):
            first.complete(lease.task_id, render(PLANNED, lease))
    live = [t for t in job.tiles if not t.stopped]
    assert live and all(Scheduler.planned_batches(t) for t in live)
    checkpoint = {t.index: t.acc for t in job.tiles}
    plans = {t.index: Scheduler.planned_batches(t) for t in live}
    resumed = Scheduler(clock=FakeClock())
    resumed.add_job("j", PLANNED, "scene", checkpoint=checkpoint, plans=plans,
                    state=JobState.RUNNING)  # fmt: skip
    resumed.add_worker("w", 3)
    while not resumed.jobs["j"].state.finished:
        for lease in resumed.assign("w"):
            resumed.complete(lease.task_id, render(PLANNED, lease))
    for a, b in zip(reference.tiles, resumed.jobs["j"].tiles, strict=True):
        np.testing.assert_array_equal(a.acc.rgb_sum, b.acc.rgb_sum)
        assert a.stop == b.stop


ETA_SETTINGS = JobSettings(width=32, height=32, tile_size=16, noise_threshold=0, max_spp=64)


def _two_first_batches(settings):
    """Four 16x16 tiles; batch 0 (1 spp) of tiles 0 and 1 merged at t=1000 and t=1002, read at
    t=1004: 256 samples merged in the 4 s since the first merge, 64 samples/s."""
    clock = FakeClock()
    sched = Scheduler(clock=clock)
    job = sched.add_job("j", settings, "scene")
    sched.add_worker("w", 2)
    first, second = sched.assign("w")
    assert sched.progress(job).eta_s is None  # nothing merged
    clock.now = 1000.0
    sched.complete(first.task_id, render(settings, first))
    clock.now = 1001.0
    assert sched.progress(job).eta_s is None  # one batch: no rate yet
    clock.now = 1002.0
    sched.complete(second.task_id, render(settings, second))
    clock.now = 1004.0
    return sched, job


def test_eta_is_the_samples_still_needed_over_the_recent_sample_rate():
    sched, job = _two_first_batches(ETA_SETTINGS)
    # Without a noise threshold every tile renders 64 spp: tiles 0 and 1 need 63 more, tiles 2
    # and 3 all 64, of 256 pixels each, at 64 samples/s.
    assert sched.progress(job).eta_s == pytest.approx((63 + 63 + 64 + 64) * 256 / 64)


def test_eta_with_a_noise_threshold_uses_each_tiles_error():
    settings = JobSettings(
        width=32, height=32, tile_size=16, noise_threshold=0.1, min_spp=16, max_spp=64
    )
    sched, job = _two_first_batches(settings)
    # Error falls as 1/sqrt(spp): tile 0 (1 spp, error 0.6) reaches 0.1 at 36 spp; tile 1
    # (error 0.2) at 4, raised to min_spp 16; tiles 2 and 3 have no estimate and are taken to
    # need the mean of those, 26 spp.
    job.tiles[0].error, job.tiles[1].error = 0.6, 0.2
    assert sched.progress(job).eta_s == pytest.approx((35 + 15 + 26 + 26) * 256 / 64)


def test_eta_under_pixel_mse_lets_the_bound_grow_with_the_samples():
    settings = JobSettings(width=32, height=32, tile_size=16, noise_threshold=0.1, min_spp=16,
                           max_spp=64, adaptive="pixel_mse")  # fmt: skip
    sched, job = _two_first_batches(settings)
    # A pixel with n samples stops below 0.1 sqrt(n / 64): error 0.6 at 1 spp falls as
    # 0.6 / sqrt(n) and meets the bound at n = 8 x 0.6 / 0.1 = 48; error 0.2 at n = 16; tiles
    # 2 and 3, not yet rendered, need their mean, 32.
    job.tiles[0].error, job.tiles[1].error = 0.6, 0.2
    assert sched.progress(job).eta_s == pytest.approx((47 + 15 + 32 + 32) * 256 / 64)
