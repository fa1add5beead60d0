"""Per-pixel adaptive sampling (settings.adaptive pixel): each pixel stops on its own error, the
tile when every pixel has; a stopped pixel keeps its own mean and error in every output; the
decisions come from merged batches only, so the image does not depend on the workers."""

import numpy as np
import pytest
from test_scheduler import run_farm as scheduler_farm

from renderfarm.domain import channels, pixel_stops
from renderfarm.domain.continuation import continue_plan
from renderfarm.domain.jobspec import JobSettings
from renderfarm.domain.merge import DARK_FLOOR, NEVER, TileAccumulator
from renderfarm.domain.records import BatchResult
from renderfarm.domain.states import JobState, StopReason
from renderfarm.domain.tiling import PLANNED_FROM, batch_range
from renderfarm.infra import images

LUMA = np.array([0.2126, 0.7152, 0.0722])
PIXEL = channels.layout_for(pixel_adaptive=True)


def hashed(settings, rect, start, count):
    """Per (pixel, sample index) a deterministic uniform number in [0, 1): (count, h, w)."""
    ys, xs = np.mgrid[rect.y0 : rect.y0 + rect.height, rect.x0 : rect.x0 + rect.width]
    pixel = (ys * settings.width + xs).astype(np.uint64)
    idx = np.arange(start, start + count, dtype=np.uint64)[:, None, None]
    h = pixel[None] * np.uint64(0x9E3779B97F4A7C15) + idx * np.uint64(0xBF58476D1CE4E5B9)
    h ^= h >> np.uint64(31)
    h *= np.uint64(0xD6E8FEB86659FD93)
    h ^= h >> np.uint64(32)
    return (h >> np.uint64(11)).astype(np.float64) / 2.0**53


def noisy(settings, rect, start, count):
    """Per (pixel, sample index) values: noise amplitude by column (the left quarter nearly
    flat, the rest growing to the right), so pixels of one tile need very different sample
    counts."""
    u = hashed(settings, rect, start, count)
    xs = np.arange(rect.x0, rect.x0 + rect.width)[None, None, :]
    amplitude = np.where(xs < settings.width // 4, 0.01, 0.1 + 0.6 * xs / settings.width)
    value = 0.5 + amplitude * (u - 0.5)
    return np.repeat(value[..., None], 3, axis=-1)


def mask_of(lease) -> np.ndarray:
    """Task.active_pixels as a (h, w) bool array (every pixel when empty)."""
    n = lease.rect.pixels
    if not lease.active:
        return np.ones((lease.rect.height, lease.rect.width), bool)
    bits = np.unpackbits(np.frombuffer(lease.active, np.uint8), bitorder="little")
    assert len(lease.active) == (n + 7) // 8
    return bits[:n].astype(bool).reshape(lease.rect.height, lease.rect.width)


def render(settings, lease, idle_value=0.0, values=noisy):
    """A worker: the batch's sums for the pixels the task names; idle_value elsewhere (a worker
    renders nothing there and sends zeros; the server must not read them)."""
    samples = values(settings, lease.rect, lease.sample_start, lease.sample_count)
    y = samples @ LUMA
    on = mask_of(lease)
    rgb = np.where(on[..., None], samples.sum(axis=0), idle_value)
    m2 = np.where(on, ((y - y.mean(axis=0)) ** 2).sum(axis=0), idle_value)
    return BatchResult(
        job_id=lease.job_id, tile_index=lease.tile_index, batch_index=lease.batch_index,
        sample_start=lease.sample_start, sample_count=lease.sample_count, rect=lease.rect,
        rgb_sum=rgb, luminance_m2=m2, render_seconds=1e-3,
        coverage_sum=np.where(on, float(lease.sample_count), idle_value),
    )  # fmt: skip


SETTINGS = JobSettings(
    width=32, height=16, tile_size=16, noise_threshold=0.02, min_spp=16, max_spp=1024,
    adaptive="pixel",
)  # fmt: skip


def run_farm(settings, workers, seed, credit=3, reorder=True, idle_value=0.0, leases=None,
             values=noisy):  # fmt: skip
    """test_scheduler's fake farm, its workers rendering `values` with the tasks' masks."""
    return scheduler_farm(
        settings, workers, seed, credit, reorder, leases=leases,
        render=lambda s, lease: render(s, lease, idle_value, values),
    )  # fmt: skip


def test_a_stopped_pixel_keeps_its_own_mean_alpha_and_error():
    """Merged by hand with stops set by hand, against numpy over each pixel's own samples."""
    rng = np.random.default_rng(7)
    h, w = 3, 4
    stops = np.array([[7, 8, NEVER, 9], [7, NEVER, 10, 8], [NEVER, 9, 7, NEVER]], np.int32)
    acc = TileAccumulator(w, h, layout=PIXEL)
    acc.stop_batch = stops.copy()
    own: list[list[list[np.ndarray]]] = [[[] for _ in range(w)] for _ in range(h)]
    hits = np.zeros((h, w))
    for b in range(12):
        _, count = batch_range(b, 10_000)
        samples = rng.gamma(0.5, 1.0, size=(count, h, w, 3))
        hit = rng.random((count, h, w)) < 0.7
        y = samples @ LUMA
        on = stops >= b
        garbage = 1e9  # what a stopped pixel's values are must not matter
        acc.merge_batch(
            np.where(on[..., None], samples.sum(0), garbage),
            np.where(on, ((y - y.mean(0)) ** 2).sum(0), garbage),
            count,
            coverage_sum=np.where(on, hit.sum(0), garbage).astype(np.float32),
        )
        for j in range(h):
            for i in range(w):
                if on[j, i]:
                    own[j][i].append(samples[:, j, i])
                    hits[j, i] += hit[:, j, i].sum()
    mean = acc.rgb_sum / acc.samples
    alpha = acc.mean_alpha()
    variance = acc.variance_of_mean()
    for j in range(h):
        for i in range(w):
            batches = own[j][i]
            n = sum(len(b) for b in batches)
            assert acc.pixel_spp[j, i] == n
            every = np.concatenate(batches)
            np.testing.assert_allclose(mean[j, i], every.mean(0), rtol=1e-12)
            assert alpha[j, i] == pytest.approx(hits[j, i] / n, rel=1e-6)
            # The between-batch variance of the mean over the pixel's own batches.
            lum = every @ LUMA
            means = np.array([(b @ LUMA).mean() for b in batches])
            sizes = np.array([len(b) for b in batches])
            m2 = (sizes * (means - lum.mean()) ** 2).sum()
            assert variance[j, i] == pytest.approx(m2 / ((len(batches) - 1) * n), rel=1e-9)
    assert acc.spp_sum == pytest.approx(acc.pixel_spp.sum())


def test_pixels_stop_on_their_own_error_and_the_tile_when_all_have():
    leases = []
    job = run_farm(SETTINGS, workers=2, seed=3, leases=leases).jobs["j"]
    assert job.state == JobState.COMPLETED
    for tile in job.tiles:
        acc = tile.acc
        spp = acc.pixel_spp
        flat = tile.rect.x0 == 0  # holds the nearly flat quarter of the image
        if flat:
            # The flat columns stop at the first point a pixel can: after the ramp's 64 samples.
            assert (spp[:, :6] == 64).all()
        assert spp.max() > 2 * spp.min()
        assert tile.stop.reason == StopReason.CONVERGED
        # Noisier columns (to the right) got more samples.
        columns = spp.mean(axis=0)
        assert np.corrcoef(columns, np.arange(len(columns)))[0, 1] > 0.8
        # Every pixel stopped below the threshold by its smoothed error when it stopped: its
        # own frozen error is of that size (the RMS over the tile is below the threshold).
        rms = np.sqrt(np.mean(np.square(acc.relative_error())))
        assert rms < SETTINGS.noise_threshold
    # A task names the pixels it renders: from the first batch a pixel may sit out on, and then
    # only pixels still sampling; earlier tasks render every pixel.
    masked = [lease for lease in leases if lease.active]
    assert masked and all(lease.batch_index >= PLANNED_FROM for lease in masked)
    assert all(not lease.active for lease in leases if lease.batch_index < PLANNED_FROM)
    for lease in masked:
        acc = job.tiles[lease.tile_index].acc
        np.testing.assert_array_equal(mask_of(lease), acc.stop_batch >= lease.batch_index)
    # The job's mean spp counts each pixel's own samples.
    total = sum(t.acc.pixel_spp.sum() for t in job.tiles)
    assert job.samples_merged == total


@pytest.mark.parametrize("mode", ["pixel", "pixel_mse"])
def test_the_image_is_the_same_from_any_workers_in_any_order(mode):
    settings = JobSettings(**{**SETTINGS.to_dict(), "adaptive": mode})
    one = run_farm(settings, workers=1, seed=1, credit=1, reorder=False).jobs["j"]
    for workers, seed, idle in [(3, 2, 0.0), (4, 5, 123.0)]:
        many = run_farm(settings, workers=workers, seed=seed, idle_value=idle).jobs["j"]
        for a, b in zip(one.tiles, many.tiles, strict=True):
            for name in ("rgb_sum", "m2_between", "pixel_spp", "stop_batch", "coverage_sum"):
                np.testing.assert_array_equal(getattr(a.acc, name), getattr(b.acc, name))
            assert a.stop == b.stop


def true_errors(job) -> np.ndarray:
    """Every pixel's relative error against the true mean (noisy()'s expectation is 0.5), as
    the image (height, width)."""
    out = np.zeros((job.settings.height, job.settings.width))
    for t in job.tiles:
        r = t.rect
        out[r.y0 : r.y0 + r.height, r.x0 : r.x0 + r.width] = (
            (t.acc.rgb_sum / t.acc.samples) @ LUMA - 0.5
        ) / 0.5
    return out


def test_at_equal_samples_the_noisiest_pixels_are_far_less_noisy():
    """Against uniform sampling with (at most) the same total: the noisiest quarter of the
    image (the right-most columns) has a far lower true error, and the whole image's mean
    squared error is lower too (stopping every pixel at the same error spends the samples
    where the noise is, and what the flat quarter does not need goes to the noisy one)."""
    adaptive = run_farm(SETTINGS, workers=2, seed=3).jobs["j"]
    spp = adaptive.samples_merged // (SETTINGS.width * SETTINGS.height)
    uniform_settings = JobSettings(
        **{**SETTINGS.to_dict(), "noise_threshold": 0.0, "max_spp": int(spp), "adaptive": "tile"}
    )
    uniform = run_farm(uniform_settings, workers=2, seed=3).jobs["j"]
    assert uniform.samples_merged <= adaptive.samples_merged
    a, u = true_errors(adaptive), true_errors(uniform)
    assert np.mean(a**2) < np.mean(u**2)
    right = 3 * SETTINGS.width // 4
    assert np.sqrt(np.mean(a[:, right:] ** 2)) < 0.85 * np.sqrt(np.mean(u[:, right:] ** 2))


def test_the_spp_layer_and_exr_channel_count_each_pixels_samples():
    job = run_farm(SETTINGS, workers=2, seed=3).jobs["j"]
    tile = job.tiles[0]
    grey = images._grey_values("spp", tile.acc)
    np.testing.assert_array_equal(grey, tile.acc.pixel_spp)
    out = images._exr_band(tile.rect.width, tile.rect.height, [(tile.rect, tile.acc)])
    spp = out[..., images.EXR_CHANNELS.index("spp")]
    np.testing.assert_array_equal(spp, tile.acc.pixel_spp)
    rgb = out[..., :3].astype(np.float64)
    np.testing.assert_allclose(rgb, tile.acc.rgb_sum / tile.acc.samples, rtol=1e-6)
    assert images.arrays_needed("png", "spp", PIXEL) == ("pixel_spp",)


def test_a_checkpoint_keeps_each_pixels_state():
    job = run_farm(SETTINGS, workers=2, seed=3).jobs["j"]
    acc = job.tiles[1].acc
    back = TileAccumulator.from_bytes(
        acc.width, acc.height, bytes(acc.to_bytes()), acc.samples, acc.batches,
        layout=acc.layout, aovs=bytes(acc.aovs_to_bytes()),
    )  # fmt: skip
    np.testing.assert_array_equal(back.stop_batch, acc.stop_batch)
    np.testing.assert_array_equal(back.pixel_spp, acc.pixel_spp)
    assert back.spp_sum == acc.spp_sum


def test_a_continue_carries_on_only_where_no_decision_changes():
    old = SETTINGS
    more = JobSettings(**{**old.to_dict(), "max_spp": 2048})
    lower = JobSettings(**{**old.to_dict(), "noise_threshold": 0.01})
    basis = {PLANNED_FROM: (64, 32, 0.05, 64)}
    assert continue_plan(old, more, PLANNED_FROM, basis, pixels_stopped=True) is not None
    assert continue_plan(old, lower, PLANNED_FROM, basis, pixels_stopped=True) is None
    assert continue_plan(old, lower, PLANNED_FROM, basis, pixels_stopped=False) is not None


def test_dark_pixels_are_judged_on_absolute_error():
    """The smoothed error keeps merge's dark floor: a black pixel has error 0 and stops."""
    acc = TileAccumulator(3, 3, layout=PIXEL)
    for b in range(PLANNED_FROM):
        _, count = batch_range(b, 10_000)
        acc.merge_batch(np.zeros((3, 3, 3)), np.zeros((3, 3)), count)
    assert pixel_stops.smoothed_error(acc).max() == 0.0
    assert pixel_stops.stop_pixels(acc, 0.01, 16, PLANNED_FROM + 1) is None
    assert (acc.stop_batch == PLANNED_FROM).all()
    assert DARK_FLOOR > 0


def test_the_display_error_is_the_standard_error_through_the_srgb_encoding():
    """Against finite differences of the sRGB encoding (images.srgb_encode) at the mean less one
    standard error, over dark, mid, near-white and clipped pixels."""
    acc = TileAccumulator(5, 1, layout=PIXEL)
    means = np.array([0.001, 0.02, 0.3, 0.97, 3.0])
    acc.lum_mean = means.reshape(1, 5)
    acc.samples, acc.batches = 100, 10
    sigma = np.array([0.0005, 0.004, 0.02, 0.01, 0.5])  # standard errors of the means
    acc.m2_between = (sigma**2 * (acc.batches - 1) * acc.samples).reshape(1, 5)
    got = pixel_stops.display_error(acc, acc.variance_of_mean()).ravel()
    h = 1e-7
    low = means - sigma
    slope = (images.srgb_encode(low + h) - images.srgb_encode(low - h)) / (2 * h)
    np.testing.assert_allclose(got, sigma * slope, rtol=1e-4)
    assert got[-1] == 0.0  # brighter than white even one standard error down: clipped


def bright_and_dark(settings, rect, start, count):
    """Left half far brighter than white, right half dark grey, both with the same relative
    noise (uniform within +-40% of the level)."""
    u = hashed(settings, rect, start, count)
    xs = np.arange(rect.x0, rect.x0 + rect.width)[None, None, :]
    level = np.where(xs < settings.width // 2, 8.0, 0.2)
    return np.repeat((level * (1.0 + 0.8 * (u - 0.5)))[..., None], 3, axis=-1)


def test_the_display_metric_stops_clipped_pixels_at_once():
    spp = {}
    for metric in ("display", "relative"):
        threshold = 0.004 if metric == "display" else 0.02
        settings = JobSettings(
            **{**SETTINGS.to_dict(), "noise_metric": metric, "noise_threshold": threshold}
        )
        job = run_farm(settings, workers=2, seed=3, values=bright_and_dark).jobs["j"]
        image = np.zeros((settings.height, settings.width))
        for t in job.tiles:
            r = t.rect
            image[r.y0 : r.y0 + r.height, r.x0 : r.x0 + r.width] = t.acc.pixel_spp
        spp[metric] = image
    half = SETTINGS.width // 2
    # Display: the pixels brighter than white stop at the first point they can, and the grey
    # ones sample on; relative: both halves have the same relative noise, so alike.
    assert (spp["display"][:, : half - 1] == 64).all()
    assert spp["display"][:, half + 1 :].mean() > 2 * 64
    left, right = spp["relative"][:, : half - 1].mean(), spp["relative"][:, half + 1 :].mean()
    assert 0.5 < left / right < 2.0 and left > 2 * 64


def rare_events(settings, rect, start, count):
    """A dim grey (0.1, +-1%) that one sample in 300 sees a bright caustic (30) on top of:
    true mean 0.2. 64 samples of a pixel miss it four times in five."""
    u = hashed(settings, rect, start, count)
    v = hashed(settings, rect, start + 1_000_003, count)
    value = 0.1 + 0.002 * (u - 0.5) + np.where(v < 1.0 / 300.0, 30.0, 0.0)
    return np.repeat(value[..., None], 3, axis=-1)


def test_pixels_that_miss_a_rare_event_do_not_stop_on_their_lucky_estimate(monkeypatch):
    """A pixel's own estimate after 64 samples that saw no caustic says 1% noise; its tile's
    pixels, between them, have seen it. With the tile's estimate pooled in, every pixel's true
    error ends near the threshold; with the pixels' own estimates alone (PRIOR_DOF 0) most stop
    at 64 samples, half their true value."""
    settings = JobSettings(**{**SETTINGS.to_dict(), "noise_threshold": 0.3, "max_spp": 4096})
    errors = {}
    default = pixel_stops.PRIOR_DOF
    for prior in (default, 0.0):
        monkeypatch.setattr(pixel_stops, "PRIOR_DOF", prior)
        job = run_farm(settings, workers=2, seed=3, values=rare_events).jobs["j"]
        mean = np.concatenate([((t.acc.rgb_sum / t.acc.samples) @ LUMA).ravel()
                               for t in job.tiles])  # fmt: skip
        errors[prior] = np.sqrt(np.mean(((mean - 0.2) / 0.2) ** 2))
    pooled, own = errors[default], errors[0.0]
    print(f"true RMS relative error: pooled {pooled:.3f}, own estimates {own:.3f}")
    assert pooled < 1.5 * settings.noise_threshold
    assert own > 1.5 * pooled


# rare_contributions: a base of 0.01 plus contributions of 1.0 met with probability 0.05 a
# sample in the tiles' top halves (rows 0-7) and 0.5 in their bottom halves.
RARE_P = {"top": 0.05, "bottom": 0.5}


def rare_contributions(settings, rect, start, count):
    """Light that comes in contributions of one size, met more or less often: a dim top half
    (mean 0.06) and a bright bottom half (mean 0.51) in every tile, each pixel's variance per
    sample p (1 - p), about its mean (as for any count)."""
    u = hashed(settings, rect, start, count)
    ys = np.arange(rect.y0, rect.y0 + rect.height)[None, :, None]
    p = np.where(ys % 16 < 8, RARE_P["top"], RARE_P["bottom"])
    value = 0.01 + np.where(u < p, 1.0, 0.0)
    return np.repeat(value[..., None], 3, axis=-1)


def test_a_tiles_pooled_estimate_shares_its_variance_by_brightness_not_its_square(monkeypatch):
    """Stopping each pixel at one relative error t takes n = var / (m t)^2 samples: here
    p (1 - p) / (0.01 + p)^2 over t^2, 13.2 for the dim half against 0.96 for the bright one,
    13.7x. The pixels' own estimates alone (PRIOR_DOF 0) give about that; the tile's estimate
    pooled in must not change it much. Shared as one relative error for the tile, it would give
    the bright half the tile's mean (7.1 against its own 0.96) and the ratio would fall to
    about 3x; shared in proportion to the brightness (the variance of rare contributions of
    one size) each half gets about its own."""
    settings = JobSettings(**{**SETTINGS.to_dict(), "noise_threshold": 0.1, "max_spp": 16384})
    need = {half: p * (1 - p) / (0.01 + p) ** 2 for half, p in RARE_P.items()}
    want = need["top"] / need["bottom"]
    ratio, default = {}, pixel_stops.PRIOR_DOF
    for prior in (default, 0.0):
        monkeypatch.setattr(pixel_stops, "PRIOR_DOF", prior)
        job = run_farm(settings, workers=2, seed=3, values=rare_contributions).jobs["j"]
        counts = np.zeros((settings.height, settings.width))
        for t in job.tiles:
            r = t.rect
            counts[r.y0 : r.y0 + r.height, r.x0 : r.x0 + r.width] = t.acc.pixel_spp
        # Rows 0-6 and 9-15: the 3x3 neighbourhoods of rows 7 and 8 hold both halves.
        ratio[prior] = counts[:7].mean() / counts[9:].mean()
    pooled, own = ratio[default], ratio[0.0]
    print(f"dim / bright half's samples: pooled {pooled:.1f}, own estimates {own:.1f}, "
          f"by the variances {want:.1f}")  # fmt: skip
    # The batches' sizes round the bright half's count up: its own estimates give 0.6x.
    assert 0.5 * want < own < 1.5 * want
    assert 0.75 * own < pooled < 1.5 * own


def two_levels(settings, rect, start, count):
    """Uniform noise around 0.5 whose amplitude is 0.1 in the left half of the image and 0.4
    in the right half: per-sample standard deviations 1 : 4, variances 1 : 16."""
    u = hashed(settings, rect, start, count)
    xs = np.arange(rect.x0, rect.x0 + rect.width)[None, None, :]
    value = 0.5 + np.where(xs < settings.width // 2, 0.1, 0.4) * (u - 0.5)
    return np.repeat(value[..., None], 3, axis=-1)


def test_pixel_mse_gives_each_pixel_samples_in_proportion_to_its_noise():
    """adaptive pixel stops every pixel at one error, so its samples grow with the variance
    (16x on the noisy half); pixel_mse stops a pixel with n samples below threshold x
    sqrt(n / 64), so they grow with the standard deviation (4x: Neyman's allocation). For two
    halves of standard deviations 1 and 4 that makes the product of the image's MSE and its
    samples (the inverse of the efficiency at equal cost) 6.25 against 8.5 units: 1.36x."""
    spp, efficiency = {}, {}
    for mode in ("pixel", "pixel_mse"):
        settings = JobSettings(**{**SETTINGS.to_dict(), "noise_threshold": 0.005,
                                  "max_spp": 8192, "adaptive": mode})  # fmt: skip
        job = run_farm(settings, workers=2, seed=3, values=two_levels).jobs["j"]
        counts = np.zeros((settings.height, settings.width))
        for t in job.tiles:
            r = t.rect
            counts[r.y0 : r.y0 + r.height, r.x0 : r.x0 + r.width] = t.acc.pixel_spp
        half = settings.width // 2
        spp[mode] = counts[:, half:].mean() / counts[:, :half].mean()
        mse = np.mean(true_errors(job) ** 2)  # two_levels' mean is noisy()'s, 0.5
        efficiency[mode] = 1.0 / (mse * counts.sum())
        assert counts.min() >= pixel_stops.MSE_REFERENCE_SPP
    print(f"noisy / calm half's samples {spp}; efficiency pixel_mse / pixel "
          f"{efficiency['pixel_mse'] / efficiency['pixel']:.2f}")  # fmt: skip
    assert spp["pixel"] > 10.0
    assert 2.5 < spp["pixel_mse"] < 6.5
    assert efficiency["pixel_mse"] > 1.15 * efficiency["pixel"]


def test_the_pixel_mse_bound_is_the_threshold_until_64_samples_then_grows_as_their_root():
    assert pixel_stops.mse_bound(0.01, 16) == 0.01
    assert pixel_stops.mse_bound(0.01, 64) == 0.01
    assert pixel_stops.mse_bound(0.01, 256) == pytest.approx(0.02)
    assert pixel_stops.mse_bound(0.01, 4096) == pytest.approx(0.08)
