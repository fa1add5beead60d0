"""Tiles and batches: how a job is cut into tasks.

A job's image is cut into square tiles (the last row/column may be smaller). Each tile renders
its samples in batches whose sizes follow one fixed schedule, so batch b of every pixel always
covers the same global sample indices [start_b, start_b + S_b): the image does not depend on
which worker rendered which batch (docs/architecture.md, "Determinism").

The schedule is 1, 1, 2, 4, 8, 16, 32, 64, 64, 64, ... clipped at max_spp. Starting small gives
a full-frame preview quickly and two batches (a between-batch variance) almost at once; every
batch [start, start + S) with S a power of two is aligned to S, so for the sobol sampler each
batch is a complete scrambled (0, m, 2)-net. The cap keeps tasks short enough for fine-grained
scheduling and cancellation.

With a noise threshold, the capped batches (from PLANNED_FROM on) are planned: a tile's last
batches are cut down to the samples its own noise predicts it still needs (plan_batch), so that
it stops close to the threshold instead of up to a whole batch past it. A planned batch keeps
its place in the index schedule and renders a prefix of it, [start_b, start_b + count); the
indices it leaves out are never used. Each sample is still uniform (and for sobol, a prefix of
an aligned block of a scrambled net is well spread), so the estimate stays unbiased.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

BATCH_CAP = 64
# The albedo and normal layers are means over each pixel's first AOV_SAMPLES samples (batches
# 0-4 of the schedule): they converge far faster than the radiance, and leaving them out of
# later results makes those 42% smaller. Tasks past it carry skip_aovs (workers.proto).
AOV_SAMPLES = 16


def carries_aovs(sample_start: int) -> bool:
    """Whether the batch starting at global sample index sample_start adds to the albedo and
    normal layers (every batch of the schedule lies wholly on one side of AOV_SAMPLES)."""
    return sample_start < AOV_SAMPLES


_RAMP = (1, 1, 2, 4, 8, 16, 32)


@dataclass(frozen=True)
class Rect:
    x0: int
    y0: int
    width: int
    height: int

    @property
    def pixels(self) -> int:
        return self.width * self.height


def tile_grid(width: int, height: int, tile_size: int) -> list[Rect]:
    """Tiles in row-major order covering a width x height image exactly once."""
    if width <= 0 or height <= 0 or tile_size <= 0:
        raise ValueError("width, height and tile_size must be positive")
    tiles = []
    for y0 in range(0, height, tile_size):
        for x0 in range(0, width, tile_size):
            tiles.append(Rect(x0, y0, min(tile_size, width - x0), min(tile_size, height - y0)))
    return tiles


def batch_size(batch_index: int) -> int:
    """Unclipped size S_b of batch b of the schedule."""
    if batch_index < 0:
        raise ValueError("batch index must be non-negative")
    return _RAMP[batch_index] if batch_index < len(_RAMP) else BATCH_CAP


def batch_start(batch_index: int) -> int:
    """Global sample index of the first sample of batch b (sum of the earlier sizes)."""
    if batch_index < 0:
        raise ValueError("batch index must be non-negative")
    if batch_index <= len(_RAMP):
        return sum(_RAMP[:batch_index])
    return sum(_RAMP) + (batch_index - len(_RAMP)) * BATCH_CAP


def batch_range(batch_index: int, max_spp: int) -> tuple[int, int]:
    """(start, count) of batch b clipped to max_spp; count is 0 past the last batch."""
    start = batch_start(batch_index)
    count = max(0, min(batch_size(batch_index), max_spp - start))
    return start, count


# First batch whose size a tile with a noise threshold plans (the ramp is fixed: the preview and
# the first variance estimates come from it).
PLANNED_FROM = len(_RAMP)
# Planned batches are multiples of this many samples (and at least this many).
PLAN_GRAIN = 8
# A tile plans for PLAN_MARGIN times the samples its error predicts: the stop then lands at
# about threshold / sqrt(PLAN_MARGIN), with room for the noise of the error estimate itself.
PLAN_MARGIN = 1.1


def plan_batch(
    samples: int, error: float, threshold: float, min_spp: int, max_spp: int, before: int
) -> int:
    """Samples per pixel of a tile's next planned batch (0: none, max_spp is reached).

    `samples` and `error` are the tile's merged samples per pixel and relative error when the
    plan is made; `before` is how many samples per pixel the tile will have merged before this
    batch (the merged ones plus those of batches already planned). Monte Carlo error falls as
    1/sqrt(n), so the tile needs about samples * (error / threshold)^2 in all: the batch takes
    what is missing, rounded up to PLAN_GRAIN, at most BATCH_CAP; at least PLAN_GRAIN when the
    prediction says the tile is done before it (it is then usually cancelled unrendered).
    """
    count = BATCH_CAP
    if threshold > 0 and math.isfinite(error) and samples > 0:
        need = max(float(min_spp), samples * (error / threshold) ** 2 * PLAN_MARGIN)
        missing = need - before
        if missing < BATCH_CAP:
            count = max(PLAN_GRAIN, PLAN_GRAIN * math.ceil(missing / PLAN_GRAIN))
    return max(0, min(count, max_spp - before))


def batch_count(max_spp: int) -> int:
    """Number of non-empty batches needed to reach max_spp samples per pixel."""
    if max_spp <= 0:
        return 0
    ramp_total = sum(_RAMP)
    if max_spp > ramp_total:  # whole ramp, then ceil((max_spp - ramp) / cap) capped batches
        return len(_RAMP) + -(-(max_spp - ramp_total) // BATCH_CAP)
    b = 0
    while batch_start(b) + batch_size(b) < max_spp:
        b += 1
    return b + 1
