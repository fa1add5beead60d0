"""Animation jobs in the scheduler: one tile grid per frame, the first frame previewed first and
frames filled in order, each frame stopping on its own, and progress and events per frame."""

from __future__ import annotations

import random

import numpy as np
import pytest
from test_scheduler import FakeClock, render

from renderfarm.domain.frames import (
    frame_count,
    frame_slot,
    job_frames,
    job_rects,
    variant_file_names,
)
from renderfarm.domain.jobspec import (
    JobSettings,
    Limits,
    SettingsError,
    check_variant_images,
    parse_settings,
)
from renderfarm.domain.scheduler import Scheduler
from renderfarm.domain.states import JobState
from renderfarm.domain.tiling import tile_grid
from renderfarm.errors import NotFound

ANIMATION = JobSettings(
    width=48, height=32, tile_size=16, noise_threshold=0.01, min_spp=4, max_spp=64,
    frames="1-5x2",
)  # fmt: skip
PER_FRAME = 6  # 3 x 2 tiles of 16 px


def frame_render(settings, job, lease):
    """The fake renderer with the frame in its seed, as workers mix it into theirs."""
    frame = job.frames[lease.tile_index // job.tiles_per_frame]
    seeded = JobSettings(**{**settings.to_dict(), "seed": 1000 + frame})
    with np.errstate(over="ignore"):  # the hash wraps around on purpose
        return render(seeded, lease)


def run(settings, workers, seed, credit=3, reorder=True):
    clock = FakeClock()
    sched = Scheduler(clock=clock)
    job = sched.add_job("j", settings, "scene")
    rng = random.Random(seed)
    outstanding = []
    events = []
    for w in range(workers):
        sched.add_worker(f"w{w}", credit)
    for _ in range(100000):
        for w in range(workers):
            outstanding += sched.assign(f"w{w}")
        cancelled = {t for w in range(workers) for t in sched.take_cancellations(f"w{w}")}
        outstanding = [lease for lease in outstanding if lease.task_id not in cancelled]
        events += sched.take_events()
        if job.state.finished:
            break
        assert outstanding, "the scheduler stalled"
        lease = outstanding.pop(rng.randrange(len(outstanding)) if reorder else 0)
        sched.complete(lease.task_id, frame_render(settings, job, lease))
        clock.now += 0.01
    return sched, job, events + sched.take_events()


def test_every_frame_has_its_own_tile_grid_in_frame_order():
    rects = job_rects(ANIMATION)
    grid = tile_grid(48, 32, 16)
    assert len(grid) == PER_FRAME and rects == grid * 3
    job = Scheduler(clock=FakeClock()).add_job("j", ANIMATION, "scene")
    assert job.frames == (1, 3, 5) and job.tiles_per_frame == PER_FRAME
    assert [t.slot for t in job.tiles] == [0] * 6 + [1] * 6 + [2] * 6
    assert [frame_slot(ANIMATION, f) for f in (1, 3, 5)] == [0, 1, 2]
    with pytest.raises(NotFound):
        frame_slot(ANIMATION, 2)  # not in 1-5x2


def test_the_first_frame_previews_first_then_the_next_frames_in_order():
    sched = Scheduler(clock=FakeClock())
    sched.add_job("j", ANIMATION, "scene")
    sched.add_worker("w", PER_FRAME)
    first = sched.assign("w")
    assert sorted(lease.tile_index for lease in first) == list(range(PER_FRAME))
    assert {lease.batch_index for lease in first} == {0}
    # With more room, an idle tile of the next frame goes before a second batch of this one.
    sched.add_worker("v", PER_FRAME + 2)
    more = sched.assign("v")
    assert [lease.tile_index // PER_FRAME for lease in more] == [1] * PER_FRAME + [2, 2]


def test_one_and_three_workers_give_the_same_frames():
    _, one, _ = run(ANIMATION, workers=1, seed=1, credit=1, reorder=False)
    _, many, _ = run(ANIMATION, workers=3, seed=7)
    assert one.state == many.state == JobState.COMPLETED
    for a, b in zip(one.tiles, many.tiles, strict=True):
        assert a.acc.samples == b.acc.samples and a.stop == b.stop
        np.testing.assert_array_equal(a.acc.rgb_sum, b.acc.rgb_sum)
    # Frames differ: the frame is in every random number.
    assert not np.array_equal(one.tiles[0].acc.rgb_sum, one.tiles[PER_FRAME].acc.rgb_sum)


def test_each_frame_finishes_on_its_own_with_an_event_and_progress():
    sched, job, events = run(ANIMATION, workers=1, seed=1, credit=1, reorder=False)
    finished = [e.data["frame"] for e in events if e.kind == "frame_finished"]
    assert finished == [1, 3, 5]  # one worker, in order: frames are filled in order
    stops = [e for e in events if e.kind == "tile_stopped"]
    assert len(stops) == 18
    assert all(e.data["frame"] == job.frames[e.data["tile"] // PER_FRAME] for e in stops)
    p = sched.progress(job)
    assert (p.frames_total, p.frames_done, p.tiles_total) == (3, 3, 18)
    for slot, number in enumerate((1, 3, 5)):
        f = sched.frame_progress(job, slot)
        assert (f.frame, f.state, f.tiles_done, f.tiles_total) == (number, "done", 6, 6)
        tiles = job.tiles[slot * PER_FRAME : (slot + 1) * PER_FRAME]
        spp = sum(t.acc.samples * t.rect.pixels for t in tiles) / (48 * 32)
        assert f.mean_spp == pytest.approx(spp)


def test_mean_spp_is_per_pixel_of_one_frame():
    s = JobSettings(width=16, height=16, tile_size=8, noise_threshold=0, max_spp=8, frames="1-4")
    sched, job, _ = run(s, workers=2, seed=3)
    assert job.samples_merged == 4 * 16 * 16 * 8
    assert sched.progress(job).mean_spp == pytest.approx(8.0)


def test_settings_take_a_frame_list_and_refuse_a_bad_one_naming_the_setting():
    assert parse_settings({"frames": "1-3", "fps": 30}).frames == "1-3"
    for bad in ("3-1", "1-", "0-1000000"):
        with pytest.raises(SettingsError) as e:
            parse_settings({"frames": bad})
        assert e.value.field == "settings.frames", bad
    # Every frame's accumulators count against the job memory limit: one 256 x 256 frame fits
    # in 64 MB, 200 of them do not.
    limits = Limits(max_job_memory_bytes=64 << 20)
    parse_settings({"width": 256, "height": 256}, limits)
    with pytest.raises(SettingsError) as e:
        parse_settings({"frames": "1-200", "width": 256, "height": 256}, limits)
    assert e.value.field == "settings.frames"
    assert "split the range" in str(e.value)


def test_small_frames_are_sent_whole_unless_a_tile_size_is_given():
    def tiles(raw):
        s = parse_settings(raw)
        return s.tile_size, len(tile_grid(s.width, s.height, s.tile_size))

    # 128 x 96 and 128 x 128 frames are single chunks; a still of that size keeps 64-pixel tiles.
    assert tiles({"frames": "1-10", "width": 128, "height": 96}) == (128, 1)
    assert tiles({"frames": "1-10", "width": 128, "height": 128}) == (128, 1)
    assert tiles({"width": 128, "height": 96}) == (64, 4)
    # Over 16384 pixels, or a tile size given: tiles as asked.
    assert tiles({"frames": "1-10", "width": 129, "height": 128}) == (64, 6)
    assert tiles({"frames": "1-10", "width": 128, "height": 96, "tile_size": 32}) == (32, 12)
    # A thin frame of 16384 pixels is still one tile, within the largest tile side.
    assert tiles({"frames": "1-10", "width": 512, "height": 32}) == (512, 1)
    assert tiles({"frames": "1-10", "width": 1024, "height": 16})[1] > 1


def test_a_still_is_one_frame():
    sched = Scheduler(clock=FakeClock())
    job = sched.add_job("j", JobSettings(width=32, height=32, tile_size=16), "scene")
    assert job.frames is None and job.frame_count == 1
    assert sched.progress(job).frames_total == 1
    assert sched.frame_progress(job, 0).frame == 0


def run_variants(settings, variants, workers=2, seed=5):
    """A job of every variant (settings.variant "all") through the scheduler, each variant's
    tiles rendered with the variant's index in the seed (a still of a different scene)."""
    clock = FakeClock()
    sched = Scheduler(clock=clock)
    job = sched.add_job("j", settings, "scene", variants=variants)
    rng = random.Random(seed)
    outstanding, events = [], []
    for w in range(workers):
        sched.add_worker(f"w{w}", 2)
    while not job.state.finished:
        for w in range(workers):
            outstanding += sched.assign(f"w{w}")
        cancelled = {t for w in range(workers) for t in sched.take_cancellations(f"w{w}")}
        outstanding = [lease for lease in outstanding if lease.task_id not in cancelled]
        events += sched.take_events()
        assert outstanding, "the scheduler stalled"
        lease = outstanding.pop(rng.randrange(len(outstanding)))
        slot = lease.tile_index // job.tiles_per_frame
        seeded = JobSettings(**{**settings.to_dict(), "seed": 2000 + slot})
        with np.errstate(over="ignore"):
            sched.complete(lease.task_id, render(seeded, lease))
        clock.now += 0.01
    return sched, job, events + sched.take_events()


def test_a_job_of_every_variant_has_an_image_per_variant_as_frames_are():
    s = JobSettings(width=32, height=16, tile_size=16, noise_threshold=0, max_spp=4, variant="all")
    names = ("Red", "Blue", "all")
    assert job_frames(s, names) == (0, 1, 2)
    assert frame_count(s) == 1 and frame_count(s, names) == 3  # the names come with the job
    assert len(job_rects(s, names)) == 3 * 2
    assert frame_slot(s, 2, names) == 2 and frame_slot(s, None, names) == 0
    with pytest.raises(NotFound, match="variants 0..2"):
        frame_slot(s, 3, names)
    sched, job, events = run_variants(s, names)
    assert job.state == JobState.COMPLETED and job.variants == names
    p = sched.progress(job)
    assert (p.frames_total, p.frames_done, p.tiles_total) == (3, 3, 6)
    assert [(f.frame, f.variant, f.state) for f in map(lambda i: sched.frame_progress(job, i),
            range(3))] == [(0, "Red", "done"), (1, "Blue", "done"), (2, "all", "done")]  # fmt: skip
    finished = sorted((e.data["frame"], e.data["variant"]) for e in events
                      if e.kind == "frame_finished")  # fmt: skip
    assert finished == [(0, "Red"), (1, "Blue"), (2, "all")]
    stops = [e.data for e in events if e.kind == "tile_stopped"]
    assert len(stops) == 6
    assert all(d["variant"] == names[d["tile"] // 2] == names[d["frame"]] for d in stops)
    # A still keeps its events as they were: no frame, no variant.
    still = JobSettings(width=16, height=16, tile_size=16, noise_threshold=0, max_spp=1)
    _, _, events = run_variants(still, ())
    assert all("variant" not in e.data and "frame" not in e.data for e in events
               if e.kind == "tile_stopped")  # fmt: skip


def test_variant_all_is_refused_with_frames_and_held_to_the_frames_limits():
    assert parse_settings({"variant": "all"}).variant == "all"
    assert parse_settings({"variant": "All"}).variant == "All"  # a name: the keyword is "all"
    with pytest.raises(SettingsError) as e:
        parse_settings({"variant": "all", "frames": "1-3"})
    assert e.value.field == "settings.variant" and "settings.frames" in str(e.value)
    s = parse_settings({"variant": "all", "width": 256, "height": 256})
    check_variant_images(s, 3, Limits(max_job_memory_bytes=64 << 20))
    with pytest.raises(SettingsError) as e:  # every variant's accumulators count
        check_variant_images(s, 200, Limits(max_job_memory_bytes=64 << 20))
    assert e.value.field == "settings.variant" and "200 variants" in str(e.value)
    with pytest.raises(SettingsError) as e:
        check_variant_images(s, 11, Limits(max_frames=10))
    assert e.value.field == "settings.variant" and "RENDERFARM_MAX_FRAMES" in str(e.value)


def test_variant_file_names_are_safe_and_unique():
    names = ["Red", "Dark blue", "", "Red", "../x", "ünï"]
    assert variant_file_names(names) == ["Red", "Dark_blue", "2", "3_Red", "x", "n"]


def test_failed_tasks_and_worker_warnings_go_to_the_task_log():
    """task_failed names the worker, the error, the tile, batch and frame; task_warning events
    record each distinct message of a worker once per job, at most TASK_LOG_MAX of them."""
    from dataclasses import replace

    from renderfarm.domain.records import TASK_LOG_MAX

    sched = Scheduler(clock=FakeClock())
    job = sched.add_job("j", ANIMATION, "scene")
    sched.add_worker("w", 1)
    (lease,) = sched.assign("w")
    sched.failed(lease.task_id, "scene load: out of memory", retryable=True)
    (event,) = [e for e in sched.take_events() if e.kind == "task_failed"]
    slot = lease.tile_index // PER_FRAME
    assert event.data == {
        "worker": "w", "error": "scene load: out of memory", "retryable": True,
        "tile": lease.tile_index, "batch": lease.batch_index, "frame": job.frames[slot],
    }  # fmt: skip
    (lease,) = sched.assign("w")
    result = replace(frame_render(ANIMATION, job, lease), warnings=("texture ignored",) * 2)
    sched.task_warnings("w", result)
    sched.task_warnings("w2", result)  # another worker, the same message: logged already
    warnings = [e for e in sched.take_events() if e.kind == "task_warning"]
    assert [(e.data["worker"], e.data["message"]) for e in warnings] == [("w", "texture ignored")]
    assert warnings[0].data["tile"] == lease.tile_index
    many = replace(result, warnings=tuple(f"w{i}" for i in range(2 * TASK_LOG_MAX)))
    sched.task_warnings("w", many)
    logged = [e.data["message"] for e in sched.take_events() if e.kind == "task_warning"]
    assert len(logged) == TASK_LOG_MAX
    assert logged[-1].startswith(f"more than {TASK_LOG_MAX} warnings")
