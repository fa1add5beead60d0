"""Job settings validation: every refusal names the field."""

import pytest

from renderfarm.domain import channels
from renderfarm.domain.jobspec import JobSettings, Limits, parse_settings
from renderfarm.errors import SettingsError


def test_defaults():
    assert parse_settings({}) == JobSettings()
    assert parse_settings(None) == JobSettings()


def test_spp_is_an_alias_of_max_spp_and_min_spp_follows_it_down():
    s = parse_settings({"spp": 4})
    assert s.max_spp == 4 and s.min_spp == 4
    assert parse_settings({"max_spp": 4096}).min_spp == JobSettings().min_spp
    with pytest.raises(SettingsError) as e:
        parse_settings({"spp": 4, "max_spp": 8})
    assert e.value.field == "settings.spp"


def test_numbers_given_as_strings_or_integral_floats_are_accepted():
    s = parse_settings({"width": "320", "height": 240.0, "noise_threshold": "0.05"})
    assert (s.width, s.height, s.noise_threshold) == (320, 240, 0.05)


@pytest.mark.parametrize(
    "raw,field",
    [
        ({"exposure": 1}, "settings.exposure"),
        ({"max_spp": -4}, "settings.max_spp"),
        ({"max_spp": 0}, "settings.max_spp"),
        ({"width": 0}, "settings.width"),
        ({"width": 1.5}, "settings.width"),
        ({"width": True}, "settings.width"),
        ({"height": "tall"}, "settings.height"),
        ({"sampler": "magic"}, "settings.sampler"),
        ({"integrator": 3}, "settings.integrator"),
        ({"noise_threshold": float("nan")}, "settings.noise_threshold"),
        ({"noise_threshold": -0.1}, "settings.noise_threshold"),
        ({"min_spp": 64, "max_spp": 16}, "settings.min_spp"),
        ({"time_limit_s": -1}, "settings.time_limit_s"),
        ({"tile_size": 4}, "settings.tile_size"),
        ({"seed": -1}, "settings.seed"),
        ({"max_depth": 0}, "settings.max_depth"),
    ],
)
def test_bad_settings_name_the_field(raw, field):
    with pytest.raises(SettingsError) as e:
        parse_settings(raw)
    assert e.value.field == field
    assert field.split(".")[1] in e.value.message


def test_limits_are_settings():
    limits = Limits(max_width=1000, max_spp=64)
    with pytest.raises(SettingsError, match="1..1000"):
        parse_settings({"width": 1001}, limits)
    with pytest.raises(SettingsError, match="1..64"):
        parse_settings({"max_spp": 65}, limits)
    with pytest.raises(SettingsError, match="pixels"):
        parse_settings({"width": 5000, "height": 5000}, Limits(max_pixels=10**6))


def test_jobs_whose_accumulators_outgrow_the_memory_limit_are_refused_naming_width():
    # 1024 x 1024 with 64-pixel tiles: 76 bytes a pixel (float64 RGB, mean and two M2;
    # float32 coverage, albedo and normal) and 4 KB for each of the 256 tiles.
    need = (8 * 6 + 4 * 7) * 1024 * 1024 + 4096 * 256
    settings = {"width": 1024, "height": 1024, "tile_size": 64}
    assert parse_settings(settings, Limits(max_job_memory_bytes=need)).width == 1024
    with pytest.raises(SettingsError) as e:
        parse_settings(settings, Limits(max_job_memory_bytes=need - 1))
    assert e.value.field == "settings.width"
    assert "1024 x 1024" in e.value.message and "RENDERFARM_MAX_JOB_MEMORY_MB" in e.value.message
    # Smaller tiles cost more bookkeeping: the same image at 8-pixel tiles (16384 of them).
    with pytest.raises(SettingsError):
        parse_settings({**settings, "tile_size": 8}, Limits(max_job_memory_bytes=need))


def test_the_estimate_covers_what_a_job_really_holds():
    """76 bytes a pixel are the accumulator's arrays; 4 KB a tile bound the rest, measured
    with tracemalloc on a job whose tiles all merge batches and stop (no timing involved)."""
    import gc
    import tracemalloc

    import numpy as np

    from renderfarm.domain.jobspec import ACCUMULATOR_BYTES_PER_PIXEL, TILE_OVERHEAD_BYTES
    from renderfarm.domain.merge import TileAccumulator
    from renderfarm.domain.records import BatchResult
    from renderfarm.domain.scheduler import Scheduler

    acc = TileAccumulator(5, 3)
    arrays = channels.DEFAULT.array_names()
    assert sum(getattr(acc, a).nbytes for a in arrays) == ACCUMULATOR_BYTES_PER_PIXEL * 15

    settings = JobSettings(width=256, height=128, tile_size=8, max_spp=4, min_spp=4)
    sched = Scheduler(clock=lambda: 0.0)
    sched.add_worker("w", 64)
    ones = {n: np.ones(64 * n) for n in (1, 3)}
    gc.collect()
    tracemalloc.start()
    try:
        sched.add_job("j", settings, "scene")
        job = sched.jobs["j"]
        peak = 0
        for _ in range(len(job.tiles) * 4):
            for lease in sched.assign("w"):
                result = BatchResult(
                    "j", lease.tile_index, lease.batch_index, lease.sample_start,
                    lease.sample_count, lease.rect, ones[3], ones[1],
                )  # fmt: skip
                sched.complete(lease.task_id, result)
            sched.take_events()  # as the server does after every change
            peak = max(peak, tracemalloc.get_traced_memory()[0])
            if job.state.finished:
                break
    finally:
        tracemalloc.stop()
    assert job.state.finished
    pixels = settings.width * settings.height
    per_tile = (peak - ACCUMULATOR_BYTES_PER_PIXEL * pixels) / len(job.tiles)
    assert 0 < per_tile <= TILE_OVERHEAD_BYTES, per_tile


# ---- settings.shutter: motion blur (frames.parse_shutter)
@pytest.mark.parametrize(
    "text,interval",
    [
        ("", None),
        ("  ", None),
        ("0,0.5", (0.0, 0.5)),
        ("-0.25, 0.25", (-0.25, 0.25)),
        ("0,1", (0.0, 1.0)),
        ("-1,0", (-1.0, 0.0)),
    ],
)
def test_shutter_intervals(text, interval):
    from renderfarm.domain.frames import parse_shutter

    assert parse_shutter(text) == interval
    s = parse_settings({"frames": "1-10", "shutter": text})
    assert s.shutter == text.strip()


@pytest.mark.parametrize(
    "text,message",
    [
        ("0.5", "is not OPEN,CLOSE"),
        ("0,0.5,1", "is not OPEN,CLOSE"),
        ("a,b", "is not OPEN,CLOSE"),
        ("0.5,0.5", "must open before it closes"),
        ("0.5,0", "must open before it closes"),
        ("-1.5,0", "within [-1, 1]"),
        ("0,1.5", "within [-1, 1]"),
        ("-0.75,0.5", "at most one frame apart"),
        ("nan,1", "must open before it closes"),
    ],
)
def test_bad_shutters_name_the_setting(text, message):
    with pytest.raises(SettingsError) as e:
        parse_settings({"frames": "1-10", "shutter": text})
    assert e.value.field == "settings.shutter"
    assert message in str(e.value)


def test_a_shutter_needs_frames():
    with pytest.raises(SettingsError) as e:
        parse_settings({"shutter": "0,0.5"})
    assert e.value.field == "settings.shutter"
    assert "needs settings.frames" in str(e.value)
    assert parse_settings({"shutter": ""}).shutter == ""  # closed: fine for a still
