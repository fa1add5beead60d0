"""The progressive merge equals the statistics of all samples computed at once (to 1e-12)."""

import itertools

import numpy as np
import pytest

from renderfarm.domain import channels
from renderfarm.domain.merge import DARK_FLOOR, TileAccumulator
from renderfarm.domain.tiling import AOV_SAMPLES, batch_count, batch_range

H, W = 3, 5


def luminance(rgb):
    """Rec. 709 luminance, the reference for the merge's own (_kernels.c)."""
    return np.asarray(rgb, dtype=np.float64) @ np.array([0.2126, 0.7152, 0.0722])


def _batches(rng, max_spp):
    """Random per-sample RGB for every batch of the schedule: list of (samples[S,H,W,3])."""
    out = []
    for b in range(batch_count(max_spp)):
        _, count = batch_range(b, max_spp)
        # Heavy-tailed values, like a path tracer's fireflies, stress the numerics.
        out.append(rng.lognormal(mean=-1.0, sigma=1.5, size=(count, H, W, 3)))
    return out


def _batch_payload(samples):
    y = luminance(samples)
    m2 = ((y - y.mean(axis=0)) ** 2).sum(axis=0)  # two-pass within-batch M2, as a reference
    return samples.sum(axis=0), m2, samples.shape[0]


def _merged(batches, order):
    acc = TileAccumulator(W, H)
    for i in order:
        acc.merge_batch(*_batch_payload(batches[i]))
    return acc


def _close(a, b):
    np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * np.max(np.abs(b)))


@pytest.mark.parametrize("max_spp", [2, 16, 100, 300])
def test_merge_equals_all_samples_at_once(max_spp):
    rng = np.random.default_rng(max_spp)
    batches = _batches(rng, max_spp)
    acc = _merged(batches, range(len(batches)))
    every = np.concatenate(batches)
    y = luminance(every)
    _close(acc.rgb_sum, every.sum(axis=0))
    _close(acc.lum_mean, y.mean(axis=0))
    _close(acc.m2_within + acc.m2_between, ((y - y.mean(axis=0)) ** 2).sum(axis=0))
    means = np.stack([luminance(b).mean(axis=0) for b in batches])
    sizes = np.array([b.shape[0] for b in batches])[:, None, None]
    _close(acc.m2_between, (sizes * (means - y.mean(axis=0)) ** 2).sum(axis=0))
    assert acc.samples == max_spp and acc.batches == len(batches)


def test_merge_order_does_not_matter():
    rng = np.random.default_rng(7)
    batches = _batches(rng, 40)
    reference = _merged(batches, range(len(batches)))
    orders = list(itertools.islice(itertools.permutations(range(len(batches))), 0, 720, 37))
    orders.append(tuple(reversed(range(len(batches)))))
    for order in orders:
        acc = _merged(batches, order)
        for name in ("rgb_sum", "lum_mean", "m2_within", "m2_between"):
            _close(getattr(acc, name), getattr(reference, name))


def test_error_estimate_uses_between_batch_variance():
    rng = np.random.default_rng(3)
    batches = _batches(rng, 64)
    acc = _merged(batches, range(len(batches)))
    b = len(batches)
    expected = acc.m2_between / (b - 1) / 64
    _close(acc.variance_of_mean(), expected)
    # Standard error over the brightness less one standard error (merge.py's definition).
    rel = np.sqrt(expected) / np.maximum(acc.lum_mean - np.sqrt(expected), DARK_FLOOR)
    assert acc.tile_error() == pytest.approx(float(np.sqrt(np.mean(rel**2))), rel=1e-12)


def test_single_batch_falls_back_to_within_batch_variance():
    rng = np.random.default_rng(4)
    samples = rng.random((8, H, W, 3))
    acc = TileAccumulator(W, H)
    acc.merge_batch(*_batch_payload(samples))
    y = luminance(samples)
    _close(acc.variance_of_mean(), y.var(axis=0, ddof=1) / 8)
    one = TileAccumulator(W, H)
    one.merge_batch(*_batch_payload(samples[:1]))
    assert np.isinf(one.tile_error())


def test_between_batch_error_is_calibrated_for_independent_batches():
    # For i.i.d. samples the estimated variance of the mean must match the true one on average:
    # uniform samples have variance 1/12 per channel, so luminance variance is sum(w^2)/12.
    rng = np.random.default_rng(11)
    acc_vars = []
    for _ in range(200):
        acc = TileAccumulator(W, H)
        for b in range(batch_count(128)):
            _, count = batch_range(b, 128)
            acc.merge_batch(*_batch_payload(rng.random((count, H, W, 3))))
        acc_vars.append(acc.variance_of_mean().mean())
    true = float((np.array([0.2126, 0.7152, 0.0722]) ** 2).sum() / 12 / 128)
    assert np.mean(acc_vars) == pytest.approx(true, rel=0.1)


ALL_ARRAYS = ("rgb_sum", "lum_mean", "m2_within", "m2_between", "albedo_sum", "normal_sum")
LEGACY_STATS = ("rgb_sum", "lum_mean", "m2_within", "m2_between")  # before the coverage


def test_checkpoint_round_trip():
    rng = np.random.default_rng(5)
    acc = TileAccumulator(W, H)
    hits = np.zeros((H, W))
    for samples in _batches(rng, 20):
        aov = rng.random((H, W, 3)).astype(np.float32)
        batch_hits = rng.integers(0, samples.shape[0] + 1, (H, W)).astype(np.float32)
        hits += batch_hits
        acc.merge_batch(*_batch_payload(samples), aov, -aov, 0, batch_hits)
    assert np.any(acc.albedo_sum != 0) and np.any(acc.normal_sum != 0)
    # The alpha is the share of samples that hit: the hits summed over batches / samples.
    np.testing.assert_array_equal(acc.mean_alpha(), hits / 20)
    back = TileAccumulator.from_bytes(
        W, H, acc.to_bytes(), acc.samples, acc.batches, aovs=acc.aovs_to_bytes()
    )
    for name in (*ALL_ARRAYS, "coverage_sum"):
        np.testing.assert_array_equal(getattr(back, name), getattr(acc, name))
    # Without the AOV blob: statistics restored, AOVs zero.
    bare = TileAccumulator.from_bytes(W, H, acc.to_bytes(), acc.samples, acc.batches)
    np.testing.assert_array_equal(bare.rgb_sum, acc.rgb_sum)
    assert not np.any(bare.albedo_sum)
    # The format before the AOVs were split off: all six arrays in one blob, float64; and the
    # split format before the coverage. Both restore fully covered (alpha 1).
    legacy = b"".join(getattr(acc, name).astype("<f8").tobytes() for name in ALL_ARRAYS)
    old = TileAccumulator.from_bytes(W, H, legacy, acc.samples, acc.batches)
    for name in ALL_ARRAYS:
        np.testing.assert_array_equal(getattr(old, name), getattr(acc, name))
    assert (old.mean_alpha() == 1).all()
    split = b"".join(getattr(acc, name).astype("<f8").tobytes() for name in LEGACY_STATS)
    old = TileAccumulator.from_bytes(W, H, split, acc.samples, acc.batches)
    for name in LEGACY_STATS:
        np.testing.assert_array_equal(getattr(old, name), getattr(acc, name))
    assert (old.mean_alpha() == 1).all()
    with pytest.raises(ValueError):
        TileAccumulator.from_bytes(W, H, acc.to_bytes()[:-8], 1, 1)
    with pytest.raises(ValueError):
        TileAccumulator.from_bytes(W, H, acc.to_bytes(), 1, 1, aovs=b"\0" * 8)


@pytest.mark.parametrize("wire", [np.float64, np.float32])
@pytest.mark.parametrize("iid", [False, True])
@pytest.mark.parametrize("max_spp", [1, 2, 40])
def test_tile_error_is_the_rms_of_the_pixel_errors(iid, max_spp, wire):
    """tile_error(), and merge_batch()'s return (the same error computed in the merge's own
    pass), are the RMS of relative_error(), the per-pixel definition in numpy, at every stage
    (inf while no estimate exists)."""
    rng = np.random.default_rng(11)
    acc = TileAccumulator(W, H, iid=iid)
    for samples in _batches(rng, max_spp):
        rgb, m2, count = _batch_payload(samples)
        returned = acc.merge_batch(rgb.astype(wire), m2.astype(wire), count)
        rel = acc.relative_error()
        expected = float(np.sqrt(np.mean(rel * rel)))
        if np.isinf(expected):
            assert acc.tile_error() == float("inf") and returned == float("inf")
        else:
            assert acc.tile_error() == pytest.approx(expected, rel=1e-12)
            assert returned == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize("dtype", [np.float32, np.float64, ">f4", np.int32])
def test_all_finite_finds_every_nan_and_infinity(dtype):
    """all_finite() (one C pass for what results carry) agrees with numpy's isfinite at every
    position of a tile-sized array, for NaN, +inf and -inf, and for the largest finite value."""
    from renderfarm.domain.merge import all_finite

    values = np.linspace(-3.0, 3.0, 64 * 64 * 3).astype(dtype)
    assert all_finite(values)
    if np.dtype(dtype).kind != "f":
        return
    big = values.copy()
    big[17] = np.finfo(big.dtype).max
    assert all_finite(big)
    for bad in (np.nan, np.inf, -np.inf):
        for at in (0, 1, 4095, values.size - 1):
            broken = values.copy()
            broken[at] = bad
            assert not all_finite(broken) and not np.isfinite(broken).all()


def test_float32_batches_merge_as_their_float64_values():
    """The wire carries float32 sums; merging them equals merging the same values as float64."""
    rng = np.random.default_rng(12)
    a, b = TileAccumulator(W, H), TileAccumulator(W, H)
    for samples in _batches(rng, 100):
        rgb, m2, count = _batch_payload(samples)
        rgb32, m232 = rgb.astype(np.float32), m2.astype(np.float32)
        a.merge_batch(rgb32, m232, count)
        b.merge_batch(rgb32.astype(np.float64), m232.astype(np.float64), count)
    for name in channels.STATS_ARRAYS:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert a.rgb_sum.dtype == np.float64


def test_aovs_are_means_over_the_first_aov_samples():
    """Batches after AOV_SAMPLES samples do not change albedo or normal, even if they carry
    them; the means divide by the samples that did."""
    acc = TileAccumulator(W, H)
    total = np.zeros((H, W, 3))
    for b in range(batch_count(200)):
        start, count = batch_range(b, 200)
        albedo = np.full((H, W, 3), float(b + 1)) * count  # batch b's albedo is b + 1
        if start < AOV_SAMPLES:
            total += albedo
        acc.merge_batch(np.ones((H, W, 3)) * count, np.zeros((H, W)), count, albedo, -albedo)
    assert acc.samples == 200 and acc.aov_samples == AOV_SAMPLES
    # Batches 0-4 hold 1, 1, 2, 4, 8 samples: (1 + 2 + 2*3 + 4*4 + 8*5) / 16.
    np.testing.assert_allclose(acc.mean_albedo(), 65 / 16)
    np.testing.assert_allclose(acc.mean_albedo(), total / AOV_SAMPLES)
    np.testing.assert_allclose(acc.mean_normal(), -65 / 16)
    short = TileAccumulator(W, H)
    short.merge_batch(np.ones((H, W, 3)) * 2, np.zeros((H, W)), 2, np.full((H, W, 3), 3.0))
    np.testing.assert_allclose(short.mean_albedo(), 1.5)


def test_bad_batches_are_refused_and_change_nothing():
    """The fused merge loop checks sizes itself: a batch of the wrong size raises ValueError
    and leaves the statistics as they were."""
    rng = np.random.default_rng(13)
    acc = TileAccumulator(W, H)
    acc.merge_batch(*_batch_payload(_batches(rng, 2)[0]))
    before = acc.snapshot()
    rgb, m2, count = _batch_payload(_batches(rng, 4)[2])
    for bad in (
        (rgb.reshape(-1)[:-3], m2, count),  # a pixel short
        (rgb, m2.reshape(-1)[:-1], count),
        (np.concatenate([rgb.reshape(-1), rgb.reshape(-1)]), m2, count),  # twice the pixels
    ):
        with pytest.raises(ValueError):
            acc.merge_batch(*bad)
    assert acc.samples == 1 and acc.batches == 1
    for old, new in zip(before, acc.snapshot(), strict=True):
        assert old is new


def test_merge_takes_any_array_layout_and_keeps_snapshots():
    """Non-contiguous and integer batches merge as their float64 values; a snapshot() taken
    before a merge still holds the values it had (checkpoints serialise it in a thread)."""
    a, b = TileAccumulator(W, H), TileAccumulator(W, H)
    rgb = np.arange(H * W * 3 * 2).reshape(H, W, 6)[:, :, ::2]  # strided int64
    m2 = np.arange(H * W * 2, dtype=np.float32).reshape(H, 2 * W)[:, ::2]
    for acc in (a, b):
        acc.merge_batch(np.ones((H, W, 3)), np.zeros((H, W)), 1)
    kept = a.snapshot()
    copies = [x.copy() for x in kept]
    a.merge_batch(rgb, m2, 4)
    b.merge_batch(np.ascontiguousarray(rgb, np.float64), np.ascontiguousarray(m2), 4)
    for name in channels.STATS_ARRAYS:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    for x, y in zip(kept, copies, strict=True):
        np.testing.assert_array_equal(x, y)
    np.testing.assert_array_equal(a.rgb_sum, 1 + rgb)
