"""Per-pixel adaptive sampling (settings.adaptive pixel; docs/architecture.md, "Per-pixel
adaptive sampling"): which pixels of a tile render its next batches, decided from its merged
batches only, and what a stopped pixel keeps of the batches it sits out; and the error a noise
threshold bounds under either settings.noise_metric (for tiles too).

A tile's accumulator (merge.TileAccumulator) keeps two arrays for it (the channel table's
`adaptive` row): stop_batch, the last batch each pixel renders (NEVER while it samples), and
pixel_spp, each pixel's merged samples. Batch b renders the pixels with stop_batch >= b
(workers.proto, Task.active_pixels); stops are monotone, so a pixel's samples are always a
prefix of its sample indices, as with a tile's.

A pixel that has stopped rendered nothing in a batch. Its arrays are carried over so that
every output stays what it is for a tile of one sample count N (images, previews, the denoiser
and the EXR read sum / N): an idle pixel's sums are scaled by (N + S) / N, so that a sum over its
own n samples reads sum_n * N / n, its own mean; its mean luminance is kept, and its M2 scaled
so that the variance of its mean (M2 times the error terms' k) stays the one it stopped with.
The ranked rows (Cryptomatte counts) are kept as they are and read against the pixel's own
count (TileAccumulator.pixel_samples).
"""

from __future__ import annotations

import math

import numpy as np

# stop_batch of a pixel that has not stopped.
NEVER = np.iinfo(np.int32).max
# Pixels stop no earlier than this many samples: the windowed rows (albedo and normal, the
# first 16) are complete by then, and a pixel's own estimate has a few batches behind it.
AOV_WINDOW = 16


def carry_idle(acc, before: dict, idle: np.ndarray, n_a: int, n: int, m2_scale: float,
               ranked: set) -> None:  # fmt: skip
    """After a merge of n - n_a samples a pixel: the idle pixels' values from `before` (the
    arrays as they were), carried over as the module says."""
    if n_a < AOV_WINDOW:
        raise ValueError("a pixel stopped before the AOV window closed")
    scale = n / n_a
    for name, old in before.items():
        new = getattr(acc, name)
        if name == "lum_mean" or name in ranked:
            new[idle] = old[idle]
        elif name in ("m2_within", "m2_between"):
            new[idle] = old[idle] * m2_scale
        else:
            new[idle] = old[idle] * scale


def _srgb_slope(x: np.ndarray) -> np.ndarray:
    """The derivative of the sRGB encoding (IEC 61966-2-1) at linear x, 0 at and above 1 (the
    display clips there)."""
    x = np.maximum(x, 0.0)
    curve = (1.055 / 2.4) * np.power(np.maximum(x, 0.0031308), 1.0 / 2.4 - 1.0)
    return np.where(x >= 1.0, 0.0, np.where(x <= 0.0031308, 12.92, curve))


# adaptive pixel_mse: the sample count at which a pixel's bound is the threshold itself (the
# first at which pixels may stop, the schedule's PLANNED_FROM batches).
MSE_REFERENCE_SPP = 64


def mse_bound(threshold: float, samples: int) -> float:
    """The error below which a pixel with `samples` samples stops under adaptive pixel_mse:
    threshold x sqrt(samples / MSE_REFERENCE_SPP).

    The mean squared error of an image whose pixel i has variance s_i^2 per sample and n_i
    samples is the mean of s_i^2 / n_i; for a given number of samples it is least when
    n_i is proportional to s_i (Neyman's allocation; stopping every pixel at one error makes
    n_i proportional to s_i^2 instead, and spends most samples on the few noisiest pixels).
    One more sample lowers pixel i's error^2 = s_i^2 / n_i by about error^2 / n_i; stopping
    each pixel once that gain is below one common value, error^2 < c n_i, makes n_i
    proportional to s_i. c is threshold^2 / MSE_REFERENCE_SPP: a pixel stopping at the first
    sample count it may stop at stops at the threshold, as under adaptive pixel."""
    return threshold * math.sqrt(max(samples, MSE_REFERENCE_SPP) / MSE_REFERENCE_SPP)


def mse_samples_needed(error: float, samples: int, threshold: float) -> float:
    """The samples at which an error of `error` at `samples` samples, falling as 1 / sqrt(n),
    meets mse_bound(threshold, n): error sqrt(samples / n) = threshold sqrt(n / 64) at
    n = sqrt(64 samples) error / threshold, where that is 64 or more (the bound grows from
    there; no pixel stops before 64 samples in any case). What the batch planner and the
    job's ETA take a pixel_mse tile to need, as they take n (error / threshold)^2 under one
    threshold."""
    return math.sqrt(MSE_REFERENCE_SPP * samples) * error / threshold


# Degrees of freedom the tile's pooled estimate counts for in a pixel's (pooled_variance).
PRIOR_DOF = 8.0


def pooled_variance(acc) -> np.ndarray:
    """Each pixel's variance of the mean, raised toward what its tile says a pixel of its
    brightness has (never lowered: a pixel noisier than its tile keeps its own estimate):
    max(s^2, (nu s^2 + nu_0 k m) / (nu + nu_0)), with nu its own degrees of freedom (its
    batches less one), m the pixel's mean and k the mean over the tile's pixels of their
    variance of the mean over their brightness (the mean less one standard error, at least
    merge's DARK_FLOOR, as the relative error bounds it). A pixel's own estimate from a few
    batches misses what is rare: a dim floor lit by a caustic that 64 samples do not find looks
    converged on its own, while its tile's thousand pixels, between them, have found it.

    The tile's variance is shared out in proportion to the brightness, not its square: a
    pixel's light that comes in rare contributions of one size c, met with probability p a
    sample, has the mean p c and the variance p c^2 (less (p c)^2), its mean times c, so the
    pixels of a tile where the same caustic, highlight or bounce makes the noise differ in how
    often they meet it more than in how bright it is. Shared as the square (one relative error
    for the tile), a tile with one caustic made every bright, smooth pixel of it sample as if
    it were as noisy as the caustic's dim surroundings (the floor's 32 x 32 blocks in
    docs/parity.md, "Where the floor's remaining gap is")."""
    from .merge import DARK_FLOOR  # merge imports this module

    var = acc.variance_of_mean()
    known = np.isfinite(var)
    if not known.all() or acc.batches < 2:
        return var
    bound = np.maximum(acc.lum_mean - np.sqrt(var), DARK_FLOOR)
    prior = float(np.mean(var / bound)) * np.maximum(acc.lum_mean, 0.0)
    dof = float(acc.batches - 1)
    return np.maximum(var, (dof * var + PRIOR_DOF * prior) / (dof + PRIOR_DOF))


def relative_error(acc) -> np.ndarray:
    """merge's relative error of the pooled_variance()."""
    from .merge import DARK_FLOOR

    s = np.sqrt(pooled_variance(acc))
    return s / np.maximum(acc.lum_mean - s, DARK_FLOOR)


def display_error(acc, variance: np.ndarray | None = None) -> np.ndarray:
    """Per pixel, the standard error of its luminance as a viewer sees it, in display units
    (0..1 of the sRGB-encoded, clipped value): the standard error s of the mean times the
    encoding's slope at the mean less s (a lower bound of the brightness, as relative_error
    takes it: where the encoding is steeper, so the bound errs on the side of more samples).
    0 where even the bound is at or above white (the display clips it); inf where unknown.
    variance: of each pixel's mean (default: pooled_variance())."""
    s = np.sqrt(pooled_variance(acc) if variance is None else variance)
    with np.errstate(invalid="ignore"):
        return np.where(np.isfinite(s), s * _srgb_slope(acc.lum_mean - s), np.inf)


def pixel_error(acc, metric: str = "relative") -> np.ndarray:
    """Each pixel's error as settings.noise_metric measures it."""
    return display_error(acc) if metric == "display" else relative_error(acc)


def tile_error(acc, metric: str = "relative") -> float:
    """A tile's error: the root mean square of its pixels' (inf while any is unknown)."""
    if metric != "display":
        return acc.tile_error()
    e = display_error(acc)
    return float(np.sqrt(np.mean(np.square(e)))) if np.isfinite(e).all() else math.inf


def smoothed_error(acc, threshold: float = math.inf, metric: str = "relative") -> np.ndarray:
    """Each pixel's relative error, averaged (in its square) over its 3x3 neighbourhood within
    the tile: a pixel's own estimate has few degrees of freedom (its batches less one), its
    neighbours' nine times as many, and a pixel next to a noisy one is not let go on its own
    lucky estimate (as Cycles' adaptive sampling keeps the neighbours of active pixels active).
    A pixel that has stopped counts at most `threshold`: it was judged done, and its error,
    frozen, must not keep a neighbour sampling for good. Infinite where any estimate is
    unknown."""
    e2 = np.square(pixel_error(acc, metric))
    if acc.stop_batch is not None and math.isfinite(threshold):
        e2 = np.where(acc.stop_batch != NEVER, np.minimum(e2, threshold**2), e2)
    h, w = e2.shape
    total = np.zeros((h + 2, w + 2))
    count = np.zeros((h + 2, w + 2))
    for dy in range(3):
        for dx in range(3):
            total[dy : dy + h, dx : dx + w] += e2
            count[dy : dy + h, dx : dx + w] += 1.0
    return np.sqrt(total[1:-1, 1:-1] / count[1:-1, 1:-1])


def stop_pixels(
    acc, threshold: float, min_spp: int, batch: int, metric: str = "relative",
    mse: bool = False,
) -> float | None:  # fmt: skip
    """Decide, from the merged batches only, which pixels render batch `batch` (the one after
    the next, planned now): a pixel still sampling stops (its last batch is the next one) once
    it has min_spp samples and its smoothed_error() is below threshold (mse, adaptive
    pixel_mse: below mse_bound(threshold, its samples)). Deciding twice from the same state
    decides the same. Returns the median smoothed error of the pixels that render `batch`
    (what its size is planned from: with mse, the error that plans the samples the bound needs,
    mse_samples_needed()), None when none does."""
    bound = mse_bound(threshold, acc.samples) if mse else threshold
    error = smoothed_error(acc, bound, metric)
    if acc.samples >= min_spp:
        stop = (acc.stop_batch == NEVER) & (error < bound)
        if stop.any():
            acc.stop_batch = np.where(stop, np.int32(acc.batches), acc.stop_batch)
    rendering = acc.stop_batch >= batch
    if not rendering.any():
        return None
    median = float(np.median(error[rendering]))
    if not mse or not math.isfinite(median):
        return median
    # The batch planner asks for n (e / threshold)^2 samples: the error that makes that
    # mse_samples_needed().
    return threshold * math.sqrt(mse_samples_needed(median, acc.samples, threshold) / acc.samples)
