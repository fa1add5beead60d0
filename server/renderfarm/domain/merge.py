"""Progressive merge of batch results and the per-pixel error estimate.

The statistics are explained in docs/architecture.md, "Statistics".

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

Relative error of a pixel: s / max(mean luminance - s, DARK_FLOOR), s = sqrt(variance of the
mean). Dividing by the estimated mean itself would understate the error exactly where the
estimate is worst: a dark pixel whose few bright samples have inflated its mean also gets a
large denominator, and a tile whose error lives in a few such pixels stops early (measured in a
sunlit scene's shadowed strip: stop estimates of 0.06-0.1 against true errors of 0.09-0.3). The
mean less one standard error is a lower confidence bound on the brightness; for a converged
pixel (s / mean = e small) it changes the error only by a factor 1 / (1 - e).
Relative error of a tile: root mean square of its pixels' relative errors.

The per-pixel loops of merge_batch() and tile_error() are fused in C (_kernels.c, built with
the package; merge_batch() computes the merged tile's error in its own pass): one pass over a
tile's arrays instead of a dozen numpy passes, which matters on a server merging thousands of
results a second (bench/server_merge.py). The arithmetic is the
same; relative_error() states it in numpy, and the tests hold the C loops to it and to the
statistics of all samples computed at once.

One module although over 500 lines: the accumulator is one class, and its arrays, their
merge, their means and its checkpoint blobs change together (a row of the channel table reaches
each of them); per-pixel adaptive sampling's decisions are apart, in pixel_stops.py.

The arrays, their types and their order come from the channel table (channels.py), as a
job's layout has them (the rows always on and those its settings turn on): the radiance and its
luminance statistics are merged by the fused kernel, every other row that accumulates (a sum, a
count, a first sample) batch by batch in batch order, within its window: albedo and normal sums
cover each pixel's first AOV_SAMPLES samples only, depth and position its first sample
(tiling.py), so batches merged after that point do not add to them, whatever they carry.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from .. import _kernels
from . import channels, cryptomatte, pixel_stops
from .channels import Accumulate
from .pixel_stops import NEVER
from .tiling import AOV_SAMPLES

DARK_FLOOR = 0.01  # pixels darker than this (linear luminance) are judged on absolute error


def all_finite(values) -> bool:
    """Whether every value is finite: one pass in C for float32/float64 (what results carry)."""
    a = np.ascontiguousarray(values)
    if a.dtype in (np.float32, np.float64):
        return _kernels.all_finite(a)
    return bool(np.isfinite(a).all())


def _batch_array(values) -> np.ndarray:
    """A batch's values as a contiguous float32 or float64 array, as the merge kernel reads."""
    a = np.ascontiguousarray(values)
    return a if a.dtype in (np.float32, np.float64) else a.astype(np.float64)


class Snapshot(tuple):
    """The arrays of a TileAccumulator.snapshot() in RAM, with their names (as spill.SpillRef,
    the snapshot of an evicted tile, has them)."""

    def __new__(cls, names: tuple, arrays):
        self = super().__new__(cls, arrays)
        self.names = names
        return self


class TileAccumulator:
    """Merged statistics of one tile. No I/O; merge order is the caller's job."""

    # The per-pixel arrays are the channel table's (channels.ARRAYS), one attribute each (None
    # for the rows the job's layout leaves out).
    __slots__ = (
        *channels.ARRAYS,
        "layout",
        "height",
        "width",
        "samples",
        "batches",
        "nonfinite",
        "iid",
        "spill",
        "spp_sum",
    )

    # Bytes a pixel of the per-pixel arrays of a job that turns nothing on (76: float64 RGB
    # sum, mean luminance and two M2; float32 coverage count, albedo and normal sums); a job's
    # own are its layout's (nbytes).
    BYTES_PER_PIXEL = channels.bytes_per_pixel()

    def __init__(
        self,
        width: int,
        height: int,
        iid: bool = False,
        arrays: bool = True,
        layout: channels.Layout = channels.DEFAULT,
    ):
        """arrays=False leaves the per-pixel arrays None (a tile cache fills them on demand).
        layout: the job's rows (channels.job_layout)."""
        # iid: the samples are independent (the `independent` sampler); see variance_of_mean.
        self.iid = iid
        self.layout = layout
        for name in channels.ARRAYS:  # the table's arrays the layout leaves out stay None
            setattr(self, name, None)
        self.width = width
        self.height = height
        # Where the arrays are kept while they are out of RAM (spill.TileCache); None when
        # the accumulator lives in RAM only.
        self.spill = None
        if arrays:
            self.zero_arrays()
        else:
            self.drop_arrays()
        self.samples = 0
        self.batches = 0
        self.nonfinite = 0
        # Samples merged over the tile's pixels (per-pixel adaptive sampling: each pixel's own
        # count; else samples x pixels), kept while the arrays are out of RAM.
        self.spp_sum = 0.0

    @property
    def pixel_adaptive(self) -> bool:
        """Whether the job samples adaptively per pixel (its layout keeps stop_batch)."""
        return "stop_batch" in self.layout.array_names()

    def zero_arrays(self) -> None:
        """Fresh zero arrays: the statistics of no samples. (The coverage is a count, exact in
        float32 up to 2^24 samples, above the max_spp limit; albedo and normal are sums over
        at most AOV_SAMPLES samples, which float32 holds to its rounding.)"""
        for a in self.layout.stored():
            setattr(self, a.name, np.zeros(a.shape(self.width, self.height), a.dtype))
        if self.stop_batch is not None:  # no pixel has stopped
            self.stop_batch = np.full((self.height, self.width), NEVER, np.int32)

    def drop_arrays(self) -> None:
        """Let go of the per-pixel arrays (evicted; spill.TileCache restores them)."""
        for name in self.layout.array_names():
            setattr(self, name, None)

    @property
    def arrays(self) -> tuple[str, ...]:
        """The names of the per-pixel arrays the job's layout keeps, in table order."""
        return self.layout.array_names()

    @property
    def stats_arrays(self) -> tuple[str, ...]:
        """Those of rows over every sample (checkpointed with each checkpoint)."""
        return self.layout.array_names(False)

    @property
    def aov_arrays(self) -> tuple[str, ...]:
        """Those of windowed rows (checkpointed apart, while they change)."""
        return self.layout.array_names(True)

    @property
    def resident(self) -> bool:
        """Whether the per-pixel arrays are in RAM."""
        return self.rgb_sum is not None

    @property
    def nbytes(self) -> int:
        """Bytes of the per-pixel arrays."""
        return self.layout.bytes_per_pixel() * self.width * self.height

    def merge_batch(
        self,
        rgb_sum: np.ndarray,
        luminance_m2: np.ndarray,
        sample_count: int,
        albedo_sum: np.ndarray | None = None,
        normal_sum: np.ndarray | None = None,
        nonfinite: int = 0,
        coverage_sum: np.ndarray | None = None,
        extra: dict[str, np.ndarray] | None = None,
    ) -> float:
        """Merge one batch of `sample_count` samples per pixel (Chan et al. 1979). A batch
        without coverage_sum adds no coverage (its samples count as misses in the alpha);
        `extra` holds the sums of the layout's other rows by their wire name (BatchResult.extra).
        Returns the merged tile's tile_error(), computed in the same pass."""
        if sample_count <= 0:
            raise ValueError("a batch has at least one sample")
        # Per-pixel adaptive sampling: the pixels this batch rendered (the others' values are
        # not read); None: every pixel.
        active = None
        if self.stop_batch is not None:
            active = self.stop_batch >= self.batches
            if active.all():
                active = None
        before = self._idle_state() if active is not None else None
        n_a = float(self.samples)
        # Copy on write: every merge writes new arrays instead of updating in place, so a
        # checkpoint can hold on to the arrays of a snapshot() and serialise them in another
        # thread while merging goes on.
        out = tuple(
            np.empty_like(a) for a in (self.rgb_sum, self.lum_mean, self.m2_within, self.m2_between)
        )
        terms, k = self._error_terms(self.samples + sample_count, self.batches + 1)
        # One fused pass (_kernels.c): the luminance of the batch's mean, delta to the running
        # mean, m2_between += delta^2 n_a n_b / n (none for a first batch), the running mean,
        # m2_within and the RGB sum, and the merged statistics' squared relative errors; float32
        # or float64 input, float64 arithmetic.
        total = _kernels.merge(
            self.height * self.width,
            n_a,
            float(sample_count),
            self.rgb_sum,
            self.lum_mean,
            self.m2_within,
            self.m2_between,
            _batch_array(rgb_sum),
            _batch_array(luminance_m2),
            *out,
            terms,
            k,
            DARK_FLOOR,
        )
        self.rgb_sum, self.lum_mean, self.m2_within, self.m2_between = out
        # The other rows: a new array each (copy on write, as above), for a row with a window
        # only while the batch is in it (in-order merges: self.samples is the batch's start).
        batch = {"albedo_sum": albedo_sum, "normal_sum": normal_sum, "coverage_sum": coverage_sum}
        if extra:
            batch.update(extra)
        for wire, name, window in _summed(self.layout):
            values = batch.get(wire)
            if values is None or (window and self.samples >= window):
                continue
            stored = getattr(self, name)
            values = np.asarray(values).reshape(stored.shape)
            setattr(self, name, np.add(stored, values, dtype=stored.dtype))
        # Ranked rows (Cryptomatte): counts of equal labels added, the largest kept.
        for wire, name in _ranked(self.layout):
            values = batch.get(wire)
            if values is not None:
                setattr(self, name, cryptomatte.merge_ranked(getattr(self, name), values))
        if self.pixel_spp is not None:
            grown = sample_count if active is None else np.where(active, sample_count, 0)
            self.pixel_spp = np.add(self.pixel_spp, grown, dtype=np.float32)
        if before is not None:
            self._keep_idle(before, ~active, sample_count)
        self.samples += sample_count
        self.batches += 1
        self.nonfinite += nonfinite
        self.spp_sum += sample_count * (
            self.height * self.width if active is None else int(np.count_nonzero(active))
        )
        if before is not None:  # the kernel's error counted the idle pixels' batch of zeros
            return self.tile_error()
        return math.sqrt(total / (self.height * self.width)) if terms else math.inf

    # Per-pixel adaptive sampling (pixel_stops.py): what an idle pixel keeps of a merge.
    def _idle_state(self) -> dict:
        """The arrays an idle pixel keeps, before a merge replaces them (copy on write: the old
        arrays are never written): those pixel_stops.carry_idle carries over."""
        names = ["rgb_sum", "lum_mean", "m2_within", "m2_between"]
        names += [name for _, name, window in _summed(self.layout)
                  if not (window and self.samples >= window)]  # fmt: skip
        names += [name for _, name in _ranked(self.layout)]
        return {n: getattr(self, n) for n in names}

    def _keep_idle(self, before: dict, idle: np.ndarray, sample_count: int) -> None:
        n_a, n = self.samples, self.samples + sample_count
        kind_a, k_a = self._error_terms(n_a, self.batches)
        kind, k = self._error_terms(n, self.batches + 1)
        m2_scale = k_a / k if kind == kind_a and k > 0 else 1.0
        ranked = {name for _, name in _ranked(self.layout)}
        pixel_stops.carry_idle(self, before, idle, n_a, n, m2_scale, ranked)

    def pixel_samples(self) -> np.ndarray | float:
        """Samples merged per pixel: each pixel's own (per-pixel adaptive sampling) or the
        tile's count."""
        return self.pixel_spp.astype(np.float64) if self.pixel_spp is not None else self.samples

    def active_pixels(self, batch: int) -> np.ndarray | None:
        """The pixels batch `batch` renders (per-pixel adaptive sampling), None: every one."""
        if self.stop_batch is None:
            return None
        return self.stop_batch >= batch

    def mean_rgb(self) -> np.ndarray:
        if self.samples == 0:
            return np.zeros_like(self.rgb_sum)
        return self.rgb_sum / self.samples

    @property
    def aov_samples(self) -> int:
        """Samples behind albedo_sum and normal_sum."""
        return min(self.samples, AOV_SAMPLES)

    def mean_alpha(self) -> np.ndarray:
        """The alpha: the share of samples whose camera ray hit geometry (0 before any)."""
        return self.coverage_sum.astype(np.float64) / max(1, self.samples)

    def mean_albedo(self) -> np.ndarray:
        return self.albedo_sum / max(1, self.aov_samples)

    def mean_normal(self) -> np.ndarray:
        return self.normal_sum / max(1, self.aov_samples)

    def mean_of(self, row: channels.Channel) -> np.ndarray:
        """The per-pixel mean of a summed row over the samples in its window, float64 (a
        first-sample row: its value); zeros before any sample."""
        n = min(self.samples, row.window) if row.window else self.samples
        return getattr(self, row.store[0].name) / float(max(1, n))

    # _error_terms()' kinds, as _kernels.merge() takes them: which M2 arrays sum to the
    # variance of the mean (times k).
    _TERMS_NONE, _TERMS_BOTH, _TERMS_BETWEEN, _TERMS_WITHIN = 0, 1, 2, 3

    def _error_terms(self, n: int, batches: int) -> tuple[int, float]:
        """(kind, k) of the variance of the mean with n samples in `batches` batches."""
        if self.iid and n >= 2:
            # Independent samples: the pooled M2 over every sample is exact and has N - 1
            # degrees of freedom instead of B - 1, so its estimate is far less noisy.
            return self._TERMS_BOTH, 1.0 / ((n - 1) * n)
        if batches >= 2:
            return self._TERMS_BETWEEN, 1.0 / ((batches - 1) * n)
        if n >= 2:
            return self._TERMS_WITHIN, 1.0 / ((n - 1) * n)
        return self._TERMS_NONE, 0.0

    def _variance_terms(self) -> tuple[tuple[np.ndarray, ...], float] | None:
        """(M2 arrays, k) with variance of the mean = sum(M2 arrays) * k per pixel; None while
        unknown."""
        terms, k = self._error_terms(self.samples, self.batches)
        if terms == self._TERMS_BOTH:
            return (self.m2_within, self.m2_between), k
        if terms == self._TERMS_BETWEEN:
            return (self.m2_between,), k
        if terms == self._TERMS_WITHIN:
            return (self.m2_within,), k
        return None

    def variance_of_mean(self) -> np.ndarray:
        """Per-pixel estimated variance of the mean luminance (inf when unknown)."""
        terms = self._variance_terms()
        if terms is None:
            return np.full((self.height, self.width), np.inf)
        m2, k = terms
        return sum(m2[1:], m2[0]) * k

    def relative_error(self) -> np.ndarray:
        """Per-pixel standard error over a lower bound of the brightness (module docstring);
        inf before any estimate exists (the bound is then the floor)."""
        s = np.sqrt(self.variance_of_mean())
        return s / np.maximum(self.lum_mean - s, DARK_FLOOR)

    def tile_error(self) -> float:
        """Root mean square of the pixels' relative_error() (inf before any estimate exists),
        in one fused pass (_kernels.c)."""
        terms = self._variance_terms()
        if terms is None:
            return float("inf")
        m2, k = terms
        pixels = self.height * self.width
        extra = m2[1] if len(m2) > 1 else None
        total = _kernels.squared_relative_error(pixels, self.lum_mean, m2[0], extra, k, DARK_FLOOR)
        return math.sqrt(total / pixels)

    # Checkpoints: the accumulator as blobs with a header naming their arrays
    # (channels.blob_header), and back. The arrays of rows over every sample change with every
    # merge; those of windowed rows (albedo, normal, depth, position) only during their window,
    # so they are stored apart and written only while they change.
    # Blobs of servers from before the header, recognised by their length (read, never written).
    _LEGACY_ARRAYS = ("rgb_sum", "lum_mean", "m2_within", "m2_between")  # before coverage
    _LEGACY_AOV_ARRAYS = ("albedo_sum", "normal_sum")

    def snapshot(self, names: tuple | None = None) -> tuple:
        """An immutable view of the statistics (cheap: arrays are replaced, never mutated), or
        of the arrays named. Of an evicted accumulator: a reference to its copy out of RAM
        (spill.SpillRef), read by snapshot_arrays()."""
        names = self.stats_arrays if names is None else names
        if not self.resident:
            return self.spill.reference(names)
        return Snapshot(names, (getattr(self, a) for a in names))

    def aov_snapshot(self) -> tuple:
        """The same for the albedo and normal sums."""
        return self.snapshot(self.aov_arrays)

    @staticmethod
    def snapshot_arrays(snapshot) -> tuple:
        """The arrays of a snapshot() or aov_snapshot(); safe to call from another thread."""
        return snapshot if isinstance(snapshot, tuple) else snapshot.read()

    @staticmethod
    def snapshot_bytes(snapshot) -> bytearray:
        """Serialise a snapshot() or aov_snapshot() as a checkpoint blob with one copy: the
        header naming its arrays, then each array little-endian in its own dtype; safe to call
        from another thread."""
        snapshot_names = snapshot.names
        snapshot = TileAccumulator.snapshot_arrays(snapshot)
        # Components as the arrays have them (a per-group row's: its groups' times the table's).
        arrays = tuple(
            channels.Array(n, channels.ARRAYS[n].dtype, a.shape[2] if a.ndim == 3 else 1)
            for n, a in zip(snapshot_names, snapshot, strict=True)
        )
        pixels = snapshot[0].shape[0] * snapshot[0].shape[1] if snapshot else 0
        header = channels.blob_header(arrays, pixels)
        out = bytearray(len(header) + sum(a.nbytes for a in snapshot))
        out[: len(header)] = header
        offset = len(header)
        for a in snapshot:
            dtype = a.dtype.newbyteorder("<")
            view = np.frombuffer(out, dtype=dtype, count=a.size, offset=offset)
            np.copyto(view, a.reshape(-1))
            offset += a.nbytes
        return out

    def to_bytes(self) -> bytearray:
        return self.snapshot_bytes(self.snapshot())

    def aovs_to_bytes(self) -> bytearray:
        return self.snapshot_bytes(self.aov_snapshot())

    def _load_blob(self, data: bytes, what: str) -> None:
        """Fill the arrays a blob with a header names (the others keep their values)."""
        _, arrays, pixels, offset = channels.read_header(data, what)
        if pixels != self.width * self.height:
            raise ValueError(
                f"checkpoint {what} holds {pixels} pixels, the tile has {self.width * self.height}"
            )
        stored = {x.name: x for x in self.layout.stored()}
        for a in arrays:
            known = stored.get(a.name, channels.ARRAYS.get(a.name))
            if known != a:
                raise ValueError(
                    f"checkpoint {what}: array {a.name} ({a.dtype} x {a.components}) is not "
                    "one of this server's channel table"
                )
            if a.name not in self.arrays:
                raise ValueError(
                    f"checkpoint {what}: array {a.name} belongs to no row the job's settings "
                    f"turn on ({', '.join(self.layout.names)})"
                )
        expected = offset + sum(a.bytes_per_pixel * pixels for a in arrays)
        if len(data) != expected:
            raise ValueError(f"checkpoint {what} has {len(data)} bytes, expected {expected}")
        for a in arrays:
            target = getattr(self, a.name)
            chunk = np.frombuffer(data, dtype=a.dtype, count=target.size, offset=offset)
            target[...] = chunk.reshape(target.shape)
            offset += target.size * chunk.itemsize

    def _load(self, names: tuple, data: bytes, what: str, dtype: str | None = None) -> None:
        """Fill the arrays named from data, each in its own dtype (or all in `dtype`, as
        checkpoints from before the AOV split stored them)."""
        kinds = [np.dtype(dtype) if dtype else getattr(self, n).dtype.newbyteorder("<")
                 for n in names]  # fmt: skip
        sizes = [getattr(self, n).size for n in names]
        expected = sum(k.itemsize * size for k, size in zip(kinds, sizes, strict=True))
        if len(data) != expected:
            raise ValueError(f"checkpoint {what} has {len(data)} bytes, expected {expected}")
        offset = 0
        for kind, name in zip(kinds, names, strict=True):
            target = getattr(self, name)
            chunk = np.frombuffer(data, dtype=kind, count=target.size, offset=offset)
            target[...] = chunk.reshape(target.shape)
            offset += target.size * kind.itemsize

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
        aovs: bytes | None = None,
        layout: channels.Layout = channels.DEFAULT,
    ) -> TileAccumulator:
        """Restore to_bytes() (with aovs_to_bytes(), or zero windowed arrays when None): the
        arrays each blob's header names. Blobs of servers from before the header load by their
        length: those written before the AOVs were split off hold both in `data`, and those
        written before the coverage existed restore as fully covered (alpha 1)."""
        acc = cls(width, height, iid, layout=layout)
        pixels = width * height
        if channels.has_header(data):
            acc._load_blob(data, "accumulators")
        elif aovs is None and len(data) == 8 * pixels * 12:  # float64 statistics and AOVs
            acc._load(cls._LEGACY_ARRAYS + cls._LEGACY_AOV_ARRAYS, data, "accumulators", "<f8")
            acc.coverage_sum[...] = samples
        elif len(data) == 8 * pixels * 6:  # the statistics without the coverage
            acc._load(cls._LEGACY_ARRAYS, data, "accumulators")
            acc.coverage_sum[...] = samples
        else:
            acc._load(("rgb_sum", "lum_mean", "m2_within", "m2_between", "coverage_sum"), data,
                      "accumulators")  # fmt: skip
        if aovs is not None:
            if channels.has_header(aovs):
                acc._load_blob(aovs, "aovs")
            else:
                acc._load(cls._LEGACY_AOV_ARRAYS, aovs, "aovs")
        acc.samples, acc.batches, acc.nonfinite = samples, batches, nonfinite
        acc.spp_sum = (
            float(acc.pixel_spp.sum(dtype=np.float64)) if acc.pixel_spp is not None
            else float(samples * pixels)
        )  # fmt: skip
        return acc

    @classmethod
    def from_snapshot(
        cls,
        width: int,
        height: int,
        names: tuple,
        snapshot,
        samples: int,
        batches: int,
        iid: bool = False,
        layout: channels.Layout = channels.DEFAULT,
    ) -> TileAccumulator:
        """A read-only accumulator over the arrays of a snapshot(names) (no copy of arrays in
        RAM; the others None), for images written in another thread."""
        acc = cls(width, height, iid, arrays=False, layout=layout)
        for name, a in zip(names, cls.snapshot_arrays(snapshot), strict=True):
            setattr(acc, name, a)
        acc.samples, acc.batches = samples, batches
        return acc


@functools.cache
def _ranked(layout: channels.Layout) -> tuple[tuple[str, str], ...]:
    """The ranked rows of a layout (Cryptomatte): (wire name, array)."""
    return tuple(
        (c.wire, c.store[0].name) for c in layout.rows if c.accumulate is Accumulate.RANKED
    )


@functools.cache
def _summed(layout: channels.Layout) -> tuple[tuple[str, str, int], ...]:
    """The rows of a layout merged batch by batch (the fused kernel merges rgb and luminance):
    (wire name, array, window)."""
    return tuple(
        (c.wire, c.store[0].name, c.window)
        for c in layout.rows
        if c.accumulate in (Accumulate.SUM, Accumulate.COUNT, Accumulate.FIRST) and c.name != "rgb"
    )
