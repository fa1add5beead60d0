"""Tiling and the batch schedule: every pixel covered once, every sample index used once."""

import numpy as np
import pytest

from renderfarm.domain.tiling import (
    AOV_SAMPLES,
    BATCH_CAP,
    PLAN_GRAIN,
    batch_count,
    batch_range,
    batch_size,
    batch_start,
    carries_aovs,
    plan_batch,
    tile_grid,
)


@pytest.mark.parametrize(
    "width,height,tile", [(512, 512, 64), (100, 37, 16), (1, 1, 8), (65, 64, 64)]
)
def test_tiles_cover_the_image_exactly_once(width, height, tile):
    cover = np.zeros((height, width), dtype=int)
    for r in tile_grid(width, height, tile):
        assert 0 < r.width <= tile and 0 < r.height <= tile
        cover[r.y0 : r.y0 + r.height, r.x0 : r.x0 + r.width] += 1
    assert (cover == 1).all()


def test_tiles_are_row_major():
    rects = tile_grid(130, 70, 64)
    assert [(r.x0, r.y0) for r in rects] == [
        (0, 0),
        (64, 0),
        (128, 0),
        (0, 64),
        (64, 64),
        (128, 64),
    ]


@pytest.mark.parametrize("max_spp", [1, 2, 3, 16, 63, 64, 65, 100, 1000, 4096])
def test_batches_partition_the_sample_range(max_spp):
    used = []
    for b in range(batch_count(max_spp)):
        start, count = batch_range(b, max_spp)
        assert count > 0
        used.extend(range(start, start + count))
    assert used == list(range(max_spp))
    assert batch_range(batch_count(max_spp), max_spp)[1] == 0


def test_batch_count_matches_counting_batches_one_by_one():
    for max_spp in list(range(1, 300)) + [1 << 16, 1 << 20, 12345]:
        b = 0
        while batch_start(b) < max_spp:
            b += 1
        assert batch_count(max_spp) == b, max_spp


def test_unclipped_batches_are_powers_of_two_aligned_to_their_size():
    # Aligned power-of-two blocks are what makes each sobol batch a complete net.
    for b in range(40):
        size, start = batch_size(b), batch_start(b)
        assert size & (size - 1) == 0
        assert start % size == 0
        assert batch_start(b + 1) == start + size


def test_aov_batches_are_exactly_the_first_aov_samples():
    """Each batch lies wholly before or after AOV_SAMPLES; those before cover it exactly."""
    covered = 0
    for b in range(20):
        start, size = batch_start(b), batch_size(b)
        assert carries_aovs(start) == carries_aovs(start + size - 1)
        covered += size if carries_aovs(start) else 0
    assert covered == AOV_SAMPLES


def test_planned_batch_takes_what_the_error_says_is_missing():
    # 64 spp at twice the threshold: 1/sqrt(n) says 4 x 64 = 256 spp, 281.6 with the margin.
    assert plan_batch(64, 0.02, 0.01, 16, 4096, before=128) == BATCH_CAP  # 153.6 missing
    assert plan_batch(64, 0.02, 0.01, 16, 4096, before=256) == 32  # 25.6 -> a multiple of 8
    assert plan_batch(64, 0.02, 0.01, 16, 4096, before=272) == 16  # 9.6 missing
    assert plan_batch(64, 0.02, 0.01, 16, 4096, before=400) == PLAN_GRAIN  # done before it


def test_planned_batch_respects_min_and_max_spp_and_unknown_error():
    assert plan_batch(64, 0.001, 0.01, 500, 4096, before=128) == BATCH_CAP  # min_spp not met
    assert plan_batch(64, 0.001, 0.01, 200, 4096, before=160) == 40  # up to min_spp
    assert plan_batch(64, 0.02, 0.01, 16, 300, before=256) == 32
    assert plan_batch(64, 0.02, 0.01, 16, 270, before=256) == 14  # clipped at max_spp
    assert plan_batch(64, 0.02, 0.01, 16, 256, before=256) == 0  # no batch past max_spp
    assert plan_batch(64, float("inf"), 0.01, 16, 4096, before=128) == BATCH_CAP
    assert plan_batch(64, 0.02, 0.0, 16, 4096, before=256) == BATCH_CAP  # no threshold
