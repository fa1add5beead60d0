"""Progressive merge of batch results and the per-pixel error estimate (DESIGN.md section 5).

Per pixel a tile keeps, in float64:
  rgb_sum        sum of every merged sample's RGB
  lum_mean       mean luminance of the merged samples
  m2_within      sum over batches of the worker's within-batch M2 of luminance
  m2_between     sum over batches b of S_b (m_b - m)^2, m_b the batch's mean luminance and m the
                 overall mean; updated incrementally with Chan et al.'s parallel formula
                 (delta^2 n_a n_b / (n_a + n_b)), never with the naive sum of squares.
and per tile the sample count N (every pixel of a tile has the same count) and the batch count B.
m2_within + m2_between is the M2 over all samples, as if computed in one pass.

Error of a pixel's mean (variance of the mean):
  independent sampler: (m2_within + m2_between) / (N - 1) / N, the ordinary sample variance of
          i.i.d. samples (N - 1 degrees of freedom, unbiased);
  other samplers, B >= 2: s^2 = m2_between / (B - 1) per sample, variance of the mean
          s^2 / N. Batch means of stratified/QMC batches behave like independent replicates,
          so this stays honest (and conservative for sobol) where the within-pixel sample
          variance overstates the error.
          E[sum_b S_b (m_b - m)^2] = (B - 1) sigma^2 for independent batches of any sizes S_b.
  B == 1: the within-batch estimate m2_within / (N - 1) stands in (infinite while N < 2).

Relative error of a pixel: sqrt(variance of the mean) / max(mean luminance, DARK_FLOOR).
Relative error of a tile: root mean square of its pixels' relative errors.
"""

from __future__ import annotations

import numpy as np

LUMINANCE_WEIGHTS = np.array([0.2126, 0.7152, 0.0722])  # Rec. 709 / sRGB primaries
DARK_FLOOR = 0.01  # pixels darker than this (linear luminance) are judged on absolute error


def luminance(rgb: np.ndarray) -> np.ndarray:
    return rgb @ LUMINANCE_WEIGHTS


class TileAccumulator:
    """Merged statistics of one tile. Plain numpy, no I/O; merge order is the caller's job."""

    __slots__ = (
        "height",
        "width",
        "rgb_sum",
        "lum_mean",
        "m2_within",
        "m2_between",
        "albedo_sum",
        "normal_sum",
        "samples",
        "batches",
        "nonfinite",
        "iid",
    )

    def __init__(self, width: int, height: int, iid: bool = False):
        # iid: the samples are independent (the `independent` sampler); see variance_of_mean.
        self.iid = iid
        self.width = width
        self.height = height
        self.rgb_sum = np.zeros((height, width, 3))
        self.lum_mean = np.zeros((height, width))
        self.m2_within = np.zeros((height, width))
        self.m2_between = np.zeros((height, width))
        self.albedo_sum = np.zeros((height, width, 3))
        self.normal_sum = np.zeros((height, width, 3))
        self.samples = 0
        self.batches = 0
        self.nonfinite = 0

    def merge_batch(
        self,
        rgb_sum: np.ndarray,
        luminance_m2: np.ndarray,
        sample_count: int,
        albedo_sum: np.ndarray | None = None,
        normal_sum: np.ndarray | None = None,
        nonfinite: int = 0,
    ) -> None:
        """Merge one batch of `sample_count` samples per pixel (Chan et al. 1979)."""
        if sample_count <= 0:
            raise ValueError("a batch has at least one sample")
        shape = (self.height, self.width)
        rgb_sum = np.asarray(rgb_sum, dtype=np.float64).reshape(*shape, 3)
        luminance_m2 = np.asarray(luminance_m2, dtype=np.float64).reshape(shape)
        n_a = float(self.samples)
        n_b = float(sample_count)
        n = n_a + n_b
        batch_mean = luminance(rgb_sum) / n_b
        delta = batch_mean - self.lum_mean
        # Copy on write: every merge makes new arrays instead of updating in place, so a
        # checkpoint can hold on to the arrays of a snapshot() and serialise them in another
        # thread while merging goes on.
        # m2_between gains delta^2 n_a n_b / n; a single batch has no between part of its own.
        self.m2_between = self.m2_between + delta * delta * (n_a * n_b / n)
        self.lum_mean = self.lum_mean + delta * (n_b / n)
        self.m2_within = self.m2_within + luminance_m2
        self.rgb_sum = self.rgb_sum + rgb_sum
        if albedo_sum is not None:
            self.albedo_sum = self.albedo_sum + np.asarray(albedo_sum).reshape(*shape, 3)
        if normal_sum is not None:
            self.normal_sum = self.normal_sum + np.asarray(normal_sum).reshape(*shape, 3)
        self.samples += sample_count
        self.batches += 1
        self.nonfinite += nonfinite

    def mean_rgb(self) -> np.ndarray:
        if self.samples == 0:
            return np.zeros_like(self.rgb_sum)
        return self.rgb_sum / self.samples

    def variance_of_mean(self) -> np.ndarray:
        """Per-pixel estimated variance of the mean luminance (inf when unknown)."""
        n = self.samples
        if self.iid and n >= 2:
            # Independent samples: the pooled M2 over every sample is exact and has N - 1
            # degrees of freedom instead of B - 1, so its estimate is far less noisy.
            return (self.m2_within + self.m2_between) / (n - 1) / n
        if self.batches >= 2:
            return self.m2_between / (self.batches - 1) / n
        if n >= 2:
            return self.m2_within / (n - 1) / n
        return np.full((self.height, self.width), np.inf)

    def relative_error(self) -> np.ndarray:
        """Per-pixel standard error over brightness, with DARK_FLOOR for dark pixels."""
        return np.sqrt(self.variance_of_mean()) / np.maximum(self.lum_mean, DARK_FLOOR)

    def tile_error(self) -> float:
        """Root mean square of the pixels' relative errors (inf before any estimate exists)."""
        rel = self.relative_error()
        return float(np.sqrt(np.mean(rel * rel)))

    # Checkpoints: the accumulator as bytes, and back (float64 little-endian, fixed order).
    _ARRAYS = ("rgb_sum", "lum_mean", "m2_within", "m2_between", "albedo_sum", "normal_sum")

    def snapshot(self) -> tuple:
        """An immutable view of the accumulator (cheap: arrays are replaced, never mutated)."""
        return tuple(getattr(self, a) for a in self._ARRAYS)

    @staticmethod
    def snapshot_bytes(snapshot: tuple) -> bytes:
        """Serialise a snapshot(); safe to call from another thread."""
        return b"".join(np.ascontiguousarray(a, "<f8").tobytes() for a in snapshot)

    def to_bytes(self) -> bytes:
        return self.snapshot_bytes(self.snapshot())

    @classmethod
    def from_bytes(
        cls,
        width: int,
        height: int,
        data: bytes,
        samples: int,
        batches: int,
        nonfinite: int = 0,
        iid: bool = False,
    ) -> TileAccumulator:
        acc = cls(width, height, iid)
        offset = 0
        for name in cls._ARRAYS:
            target = getattr(acc, name)
            size = target.size * 8
            chunk = np.frombuffer(data, dtype="<f8", count=target.size, offset=offset)
            target[...] = chunk.reshape(target.shape)
            offset += size
        if offset != len(data):
            raise ValueError(f"checkpoint has {len(data)} bytes, expected {offset}")
        acc.samples, acc.batches, acc.nonfinite = samples, batches, nonfinite
        return acc
