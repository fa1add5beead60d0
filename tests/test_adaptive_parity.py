"""bench/adaptive_parity.py's analysis: the per-pixel display MSE from two references and the
allocation table that sets the farm's samples and errors beside Cycles', region by region."""

from __future__ import annotations

import importlib
from pathlib import Path

import numpy as np
import pytest

BENCH = Path(__file__).resolve().parents[1] / "bench"


def bench(monkeypatch):
    monkeypatch.syspath_prepend(str(BENCH))
    return importlib.import_module("adaptive_parity")


def srgb_levels(linear: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1's encoding, clipped to [0, 1], in 8-bit levels (written here, not taken
    from the code under test)."""
    v = np.clip(linear, 0.0, 1.0)
    encoded = np.where(v <= 0.0031308, 12.92 * v, 1.055 * np.power(v, 1 / 2.4) - 0.055)
    return encoded * 255.0


def test_pixel_mse_is_the_squared_display_error_when_the_references_agree(monkeypatch):
    ap = bench(monkeypatch)
    truth = np.full((2, 3, 3), 0.2)
    image = truth.copy()
    image[0, 0] = [0.25, 0.2, 0.2]  # one channel off: its squared error over three channels
    image[1, 2] = [2.0, 2.0, 2.0]  # above white: clipped, then the error is 255 - D(0.2)
    mse = ap.pixel_display_mse(image, (truth, truth))
    d = srgb_levels(np.array([0.25, 0.2, 2.0]))
    assert mse[0, 0] == pytest.approx((d[0] - d[1]) ** 2 / 3, rel=1e-9)
    assert mse[1, 2] == pytest.approx((255.0 - d[1]) ** 2, rel=1e-9)
    assert np.count_nonzero(mse) == 2


def test_pixel_mse_cancels_the_references_noise(monkeypatch):
    """Two references with independent noise of a few levels: the mean of (x - a)(x - b) is the
    image's own squared error, where (x - a)^2 would add the reference's variance."""
    ap = bench(monkeypatch)
    rng = np.random.default_rng(7)
    shape = (400, 400, 3)
    truth = np.full(shape, 0.2)
    # The references' noise drawn in display levels (3 levels), so that their mean display
    # value is the truth's; the image is 5 levels brighter in every channel.
    level = srgb_levels(truth)

    def from_levels(levels):
        v = levels / 255.0
        return np.where(v <= 0.04045, v / 12.92, np.power((v + 0.055) / 1.055, 2.4))

    refs = tuple(from_levels(level + rng.normal(0.0, 3.0, shape)) for _ in range(2))
    image = from_levels(level + 5.0)
    assert float(np.mean(ap.pixel_display_mse(image, refs))) == pytest.approx(25.0, abs=0.3)
    naive = float(np.mean((srgb_levels(image) - srgb_levels(refs[0])) ** 2))
    assert naive == pytest.approx(25.0 + 9.0, abs=0.5)


def test_allocation_groups_pixels_by_the_ratio_of_the_sample_counts(monkeypatch):
    ap = bench(monkeypatch)
    truth = np.full((4, 4, 3), 0.2)
    level = srgb_levels(np.array([0.2]))[0]
    # Left half: the farm 64 samples, Cycles 1024 (16x: "Cycles >= 4x"); right half: both 512.
    farm_spp = np.where(np.arange(4) < 2, 64.0, 512.0)[None, :].repeat(4, 0)
    cycles_spp = np.where(np.arange(4) < 2, 1024.0, 512.0)[None, :].repeat(4, 0)
    farm_image = truth.copy()
    farm_image[:, :2] = 0.3  # the farm's error sits on its left half
    cycles_image = truth.copy()
    cycles_image[:, 2:] = 0.25  # Cycles' on its right half
    rows = ap.allocation(
        {"image": farm_image, "own": (truth, truth), "spp_map": farm_spp},
        {"image": cycles_image, "own": (truth, truth), "spp_map": cycles_spp},
    )
    by_region = {row["region"]: row for row in rows}
    assert [row["region"] for row in rows] == [r[0] for r in ap.ALLOCATION_REGIONS]
    left, right = by_region["Cycles >= 4x"], by_region["within 2x"]
    assert left["pixels"] == right["pixels"] == 0.5
    assert sum(row["pixels"] for row in rows) == 1.0
    assert left["farm"]["mean_spp"] == 64.0 and left["cycles"]["mean_spp"] == 1024.0
    # The farm's samples: 8 pixels of 64 and 8 of 512.
    assert left["farm"]["samples_share"] == pytest.approx(64 / (64 + 512))
    assert right["cycles"]["samples_share"] == pytest.approx(512 / (1024 + 512))
    farm_err = (srgb_levels(np.array([0.3]))[0] - level) ** 2
    cycles_err = (srgb_levels(np.array([0.25]))[0] - level) ** 2
    assert left["farm"]["mse_per_pixel"] == pytest.approx(farm_err)
    assert left["farm"]["mse_share"] == 1.0 and right["farm"]["mse_share"] == 0.0
    assert right["cycles"]["mse_per_pixel"] == pytest.approx(cycles_err)
    assert left["cycles"]["mse_share"] == 0.0
    empty = by_region["farm 2-4x"]
    assert empty["pixels"] == 0.0 and empty["farm"]["mean_spp"] is None
