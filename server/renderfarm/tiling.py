"""Tiles and batches: how a job is cut into tasks.

A job's image is cut into square tiles (the last row/column may be smaller). Each tile renders
its samples in batches whose sizes follow one fixed schedule, so batch b of every pixel always
covers the same global sample indices [start_b, start_b + S_b): the image does not depend on
which worker rendered which batch (DESIGN.md section 4).

The schedule is 1, 1, 2, 4, 8, 16, 32, 64, 64, 64, ... clipped at max_spp. Starting small gives
a full-frame preview quickly and two batches (a between-batch variance) almost at once; every
batch [start, start + S) with S a power of two is aligned to S, so for the sobol sampler each
batch is a complete scrambled (0, m, 2)-net. The cap keeps tasks short enough for fine-grained
scheduling and cancellation.
"""

from __future__ import annotations

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
