"""Images of a job, written with OpenImageIO one row of tiles at a time.

EXR channels (32-bit float) and layers are the channel table's (domain/channels.py): R, G, B
(mean radiance), variance.Y (estimated variance of the mean luminance, inf where unknown), spp
(samples merged per pixel), error (sqrt(variance.Y) / max(Y - sqrt(variance.Y), DARK_FLOOR)),
albedo.R/G/B and normal.X/Y/Z (mean first-hit albedo and world-space shading normal), A (the
share of the pixel's samples whose camera ray hit geometry), then the outputs the job's
settings.aovs turns on (depth.Z, position.X/Y/Z) and, with settings.denoise, denoised.R/G/B
(Open Image Denoise of R, G, B with the albedo and normal as guides, denoise_frame): the
channels of the job's layout (channels.job_layout). _exr_band computes the first 13 in one C
pass (_kernels.exr_tile) in that order, which server/tests/test_channel_table.py holds to the
table, and the outputs' means row by row (TileAccumulator.mean_of).
PNG: one layer, clamped to [0, 1], 8 bits; rgb, albedo, normal and denoised sRGB-encoded, the
variance (as a standard error), spp, error and depth layers grey, normalised to their maximum
(recorded in the PNG's tEXt chunk renderfarm:scale_max, beside renderfarm:scale_min 0; a depth's
background, 1e10, is white), position as v / (2 max |v|) + 0.5 per component. A PNG may be
downscaled (max_size): each output pixel is the mean of a square of f x f pixels (f the smallest
integer that brings both sides within max_size) in linear values, encoded after.

A full frame is never held: ImageWriter takes the tiles one row at a time (a band of tile_size
scanlines, or fewer at the bottom), computes its channels and hands them to OpenImageIO's
scanline writer, which compresses and writes them to the file as they come (an EXR in chunks of
EXR_CHUNK_BYTES, written by a thread of their own while the next chunk is computed, so that
OpenEXR's compression and the channels' arithmetic use both cores). An 8192x8192 EXR thus needs
about 170 MB beside the tiles instead of several GB. The values are the ones a full
frame would have (the same float64 arithmetic per pixel, rounded once).

The denoised layer is the exception: Open Image Denoise needs its inputs for the whole frame,
so a DenoiseFrame gathers the colour, albedo and normal (float32) band by band and denoises them
at once, and the writer then takes its rows from that frame. What it costs
(jobspec.denoise_memory_bytes) is checked against the job memory limit at submission.

One module although over 500 lines: the layers' arithmetic, the band writer and the denoise
frame share the band and slicing conventions above, and tests hold them to the whole-frame
values together (server/tests/test_images.py).
"""

from __future__ import annotations

import math
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from .. import _kernels
from ..domain import channels, cryptomatte
from ..domain.channels import Accumulate, Display
from ..domain.merge import DARK_FLOOR, TileAccumulator
from ..domain.tiling import Rect
from ..errors import Cancelled

# The channels of every EXR, computed by the fused kernel (those of a job without outputs).
EXR_CHANNELS = channels.exr_channels()
_SPP_CHANNEL = EXR_CHANNELS.index("spp")
LAYERS = tuple(channels.layers())
# The EXR of a job with settings.denoise: its channels, then the denoised RGB.
DENOISED_CHANNELS = channels.exr_channels(denoise=True)[len(EXR_CHANNELS) :]
# zip (deflate level 1): what every EXR reader reads; none: faster, 2.5 times larger.
EXR_COMPRESSIONS = ("zip", "none")
# Layers normalised to the image's maximum in a PNG (grey), and every layer scaled by a
# maximum over the image (layer_maximum).
_DISPLAY = {n: layer.display for n, layer in channels.layers().items()}


def _display(layer: str) -> Display:
    """How a layer is shown (a light group's layer: as its row's template)."""
    if layer.startswith(channels.LIGHT_GROUP_LAYER + "."):
        layer = channels.LIGHT_GROUP_LAYER
    return _DISPLAY[layer]


GREY_LAYERS = tuple(n for n, d in _DISPLAY.items() if d in (Display.GREY, Display.DEPTH))
SCALED_LAYERS = GREY_LAYERS + tuple(
    n for n, d in _DISPLAY.items() if d in (Display.RANGE, Display.FLOW)
)
# The rows of a layout beyond those of every job, summed or first-sample, written after the
# fused kernel's channels (their means, row by row).
_OWN_ROWS = frozenset(channels.DEFAULT.names)


def output_rows(layout: channels.Layout) -> tuple[channels.Channel, ...]:
    """The rows of a job's layout whose EXR channels follow the fused kernel's (the outputs
    of settings.aovs), in table order."""
    return tuple(c for c in layout.rows if c.name not in _OWN_ROWS and c.store and c.layers)


# A band of tiles and what each one holds: None for a tile with no merged samples.
Band = list[tuple[Rect, TileAccumulator | None]]


def arrays_needed(
    fmt: str, layer: str, layout: channels.Layout = channels.DEFAULT
) -> tuple[str, ...]:
    """The accumulator arrays an image of a job with this layout reads (a spilled tile reads
    only these)."""
    if fmt == "exr":
        return layout.array_names()
    names = channels.layer_arrays(layer)
    if "pixel_spp" in layout.array_names() and "pixel_spp" not in names:
        names += ("pixel_spp",)  # each pixel's count (the spp layer, Cryptomatte coverage)
    return names


@dataclass(frozen=True)
class TileView:
    """A tile as an image needs it, taken on the event loop and read in a writer thread: a
    snapshot of the arrays it needs (in RAM, or a reference to their copy in a spill file)."""

    rect: Rect
    samples: int
    batches: int
    iid: bool
    names: tuple
    snapshot: object
    layout: channels.Layout = channels.DEFAULT

    @classmethod
    def of(cls, rect: Rect, acc: TileAccumulator, names: tuple) -> TileView | None:
        if acc.samples == 0:
            return None
        return cls(rect, acc.samples, acc.batches, acc.iid, names, acc.snapshot(names), acc.layout)

    def accumulator(self) -> TileAccumulator:
        return TileAccumulator.from_snapshot(
            self.rect.width, self.rect.height, self.names, self.snapshot, self.samples,
            self.batches, self.iid, self.layout,
        )  # fmt: skip


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB transfer function of linear values clamped to [0, 1] (NaN to 0)."""
    # fmax and fmin take the number over a NaN: NaN goes to 0 and infinities to 0 or 1, as
    # nan_to_num and clip would, in two passes instead of six.
    x = np.fmin(np.fmax(linear, 0.0), 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def _next_frame_motion(vector: np.ndarray) -> np.ndarray:
    """A motion row's (..., 4) values (Blender's Vector: previous - current, current - next,
    y up) as the motion to the next frame in image coordinates, x right and y down: (-Z, W)."""
    return np.stack([-vector[..., 2], vector[..., 3]], -1)


def label_colours(labels: np.ndarray) -> np.ndarray:
    """Linear RGB (..., 3) float64 of integer labels: black for 0, else a colour of the label's
    own (its hue the fractional part of label x the golden ratio, so that neighbouring labels
    differ most; saturation 0.65, value 0.95 after sRGB encoding)."""
    hue = np.mod(labels.astype(np.float64) * 0.6180339887498949, 1.0) * 6.0
    # HSV to RGB: each channel's distance to its sector, clipped.
    k = np.mod(np.array([5.0, 3.0, 1.0]) + hue[..., None], 6.0)
    f = 0.95 - 0.95 * 0.65 * np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0)
    # Decode sRGB (IEC 61966-2-1), so that the PNG's encoding gives back f.
    linear = np.where(f <= 0.04045, f / 12.92, ((f + 0.055) / 1.055) ** 2.4)
    return np.where(labels[..., None] > 0, linear, 0.0)


def crypto_type(layer: channels.Layer) -> str:
    """The Cryptomatte type of a ranked row's layer (CryptoObject, ...): its channels' prefix."""
    return layer.exr[0].split(".")[0][:-2]


def _ranked_pairs(
    layer: channels.Layer, row: channels.Channel, acc: TileAccumulator, names: cryptomatte.Names
) -> np.ndarray:
    """A Cryptomatte layer's ranked (label, count) pairs of a tile, (h, w, 2 RANKS) uint32:
    its row's, or for CryptoAsset the nodes' regrouped by their root node."""
    pairs = getattr(acc, row.store[0].name).reshape(acc.height, acc.width, -1)
    if crypto_type(layer) == "CryptoAsset":
        return cryptomatte.regroup(pairs, names.roots)
    return pairs


def _outputs_band(
    width: int,
    height: int,
    tiles: Band,
    rows: tuple,
    names: cryptomatte.Names | None = None,
    ids: dict[str, dict[int, float]] | None = None,
) -> np.ndarray:
    """The EXR channels of the output rows (output_rows) of a band, float32 (height, width,
    their layers' channels): each summed row's mean over its window (zeros where nothing is
    merged), each ranked row's Cryptomatte layers (IDs of `names` and coverages)."""
    names = names or cryptomatte.Names.of({})
    if ids is None and any(r.accumulate is Accumulate.RANKED for r in rows):
        ids = {t: names.id_table(t) for t in cryptomatte.TYPES}
    out = np.zeros((height, width, sum(len(la.exr) for r in rows for la in r.layers)), np.float32)
    for rect, acc in tiles:
        if acc is None:
            continue
        t = out[:, rect.x0 : rect.x0 + rect.width]
        c = 0
        for row in rows:
            if row.accumulate is Accumulate.RANKED:
                for layer in row.layers:
                    pairs = _ranked_pairs(layer, row, acc, names)
                    values = cryptomatte.exr_values(
                        pairs, acc.pixel_samples(), ids[crypto_type(layer)]
                    )
                    t[..., c : c + len(layer.exr)] = values
                    c += len(layer.exr)
                continue
            mean = acc.mean_of(row).reshape(rect.height, rect.width, row.wire_components)
            t[..., c : c + row.wire_components] = mean
            c += row.wire_components
    return out


def _exr_band(width: int, height: int, tiles: Band) -> np.ndarray:
    """The fused kernel's EXR channels of a band, float32 (height, width, 13)."""
    out = np.empty((height, width, len(EXR_CHANNELS)), np.float32)
    for rect, acc in tiles:
        if acc is None:  # nothing merged: zeros, and variance and error unknown
            t = out[:, rect.x0 : rect.x0 + rect.width]
            t[...] = 0.0
            t[..., 3] = t[..., 5] = np.inf
            continue  # (alpha 0: nothing is known to cover it)
        # One pass in C (_kernels.c) of what rgb_sum / samples, variance_of_mean(),
        # relative_error(), mean_albedo() and mean_normal() compute.
        terms = acc._variance_terms()
        m2, k = terms if terms is not None else ((None,), 0.0)
        _kernels.exr_tile(
            acc.rgb_sum, acc.lum_mean, m2[0], m2[1] if len(m2) > 1 else None, acc.albedo_sum,
            acc.normal_sum, acc.coverage_sum, rect.height, rect.width, acc.samples,
            max(1, acc.aov_samples), k, DARK_FLOOR, out, width, rect.x0,
        )  # fmt: skip
        if acc.pixel_spp is not None:  # per-pixel adaptive sampling: each pixel's own count
            out[:, rect.x0 : rect.x0 + rect.width, _SPP_CHANNEL] = acc.pixel_spp
    return out


def _grey_values(layer: str, acc: TileAccumulator) -> np.ndarray:
    """The values a scaled layer is normalised by (inf: shown white, left out of the
    maximum)."""
    if layer == "variance":
        return np.sqrt(acc.variance_of_mean())
    if layer == "spp":
        if acc.pixel_spp is not None:  # per-pixel adaptive sampling
            return acc.pixel_spp.astype(np.float64)
        return np.full((acc.height, acc.width), float(acc.samples))
    if layer == "error":
        return acc.relative_error()
    values = acc.mean_of(channels.layer_channel(layer))
    if _display(layer) is Display.DEPTH:  # where the ray hit nothing: white
        return np.where(values < channels.BACKGROUND_DEPTH, values, np.inf)
    if _display(layer) is Display.FLOW:
        return np.abs(_next_frame_motion(values))
    return np.abs(values)  # RANGE: scaled by the largest magnitude


def layer_maximum(layer: str, tiles: Band) -> float:
    """The largest finite value of a scaled layer (SCALED_LAYERS) in a band (-inf when there
    is none)."""
    top = -math.inf
    for _, acc in tiles:
        if acc is None:
            if layer == "spp":  # unsampled pixels count 0 samples
                top = max(top, 0.0)
            continue
        values = _grey_values(layer, acc)
        finite = values[np.isfinite(values)]
        if finite.size:
            top = max(top, float(finite.max()))
    return top


def _display_tile(
    layer: str,
    acc: TileAccumulator | None,
    top: float,
    h: int,
    w: int,
    names: cryptomatte.Names | None = None,
):
    """A tile of the PNG layer in linear display values, float64 (h, w, 3): before sRGB
    encoding (rgb, albedo, normal) or the 0..1 grey scale."""
    if acc is None:  # nothing merged: black, a normal of 0 (grey), white where unknown
        fill = {"normal": 0.5, "spp": 0.0, "variance": 1.0, "error": 1.0}.get(layer, 0.0)
        return np.full((h, w, 3), fill)
    if layer in GREY_LAYERS:
        values = _grey_values(layer, acc)
        grey = np.where(np.isfinite(values), values / top, 1.0)
        return np.repeat(grey[..., None], 3, axis=-1)
    if _display(layer) is Display.FLOW:
        flow = _next_frame_motion(acc.mean_of(channels.layer_channel(layer))) / (2.0 * top)
        return np.concatenate([flow + 0.5, np.full(flow.shape[:-1] + (1,), 0.5)], -1)
    if _display(layer) is Display.RANGE:
        return acc.mean_of(channels.layer_channel(layer)) / (2.0 * top) + 0.5
    if _display(layer) is Display.LABEL:
        return label_colours(getattr(acc, channels.layer_channel(layer).store[0].name))
    if _display(layer) is Display.MATTE:  # each label's colour weighted by its coverage
        row = channels.layer_channel(layer)
        pairs = _ranked_pairs(channels.layers()[layer], row, acc, names or cryptomatte.Names.of({}))
        n = np.maximum(np.asarray(acc.pixel_samples(), np.float64), 1.0)
        coverage = pairs[..., 1::2] / (n[..., None] if n.ndim else n)
        return (label_colours(pairs[..., 0::2]) * coverage[..., None]).sum(-2)
    if layer == "rgb":
        return acc.rgb_sum / acc.samples
    if layer == "albedo":
        return acc.mean_albedo().astype(np.float64)
    if layer == "normal":
        return acc.mean_normal().astype(np.float64) * 0.5 + 0.5
    values = acc.mean_of(channels.layer_channel(layer))  # a radiance (lobes, light groups)
    if layer.startswith(channels.LIGHT_GROUP_LAYER + "."):  # the group's block of three
        k = acc.layout.groups.index(layer.split(".", 1)[1])
        values = values[..., 3 * k : 3 * k + 3]
    return values


def _display_band(
    layer: str,
    width: int,
    height: int,
    tiles: Band,
    top: float,
    names: cryptomatte.Names | None = None,
) -> np.ndarray:
    """A band of the PNG layer in display values (see _display_tile), (height, width, 3)."""
    out = np.empty((height, width, 3))
    for rect, acc in tiles:
        t = out[:, rect.x0 : rect.x0 + rect.width]
        if layer == "rgb" and acc is not None:
            np.divide(acc.rgb_sum, acc.samples, out=t)  # no temporary
        else:
            t[...] = _display_tile(layer, acc, top, rect.height, rect.width, names)
    return out


def _block_means(values: np.ndarray, f: int, divisor: float = 1.0) -> np.ndarray:
    """Means of the f x f blocks of (h, w, c) values over divisor (partial blocks at the right
    and bottom edges), in one pass (_kernels.c)."""
    h, w, c = values.shape
    out = np.empty((-(-h // f), -(-w // f), c))
    _kernels.block_means(np.ascontiguousarray(values, np.float64), h, w, c, f, divisor, out)
    return out


def _display_blocks(
    layer: str,
    width: int,
    height: int,
    tiles: Band,
    top: float,
    f: int,
    names: cryptomatte.Names | None = None,
) -> np.ndarray:
    """A band of the PNG layer downscaled by f, tile by tile: f divides every tile's offset and
    the band's height (but at the bottom), so no block spans two tiles."""
    out = np.empty((-(-height // f), -(-width // f), 3))
    for rect, acc in tiles:
        xs = slice(rect.x0 // f, -(-(rect.x0 + rect.width) // f))
        if layer == "rgb" and acc is not None:  # the mean of the block's sums, over n
            out[:, xs] = _block_means(acc.rgb_sum, f, acc.samples)
        else:
            tile = _display_tile(layer, acc, top, rect.height, rect.width, names)
            out[:, xs] = _block_means(tile, f)
    return out


def downscale_factor(width: int, height: int, max_size: int) -> int:
    """The smallest integer f with ceil(width / f) and ceil(height / f) <= max_size (1 when
    max_size is 0: full resolution)."""
    if max_size <= 0:
        return 1
    return max(1, math.ceil(max(width, height) / max_size))


class _Downscaler:
    """Box filter by an integer factor over rows arriving in bands of any height."""

    def __init__(self, width: int, factor: int):
        self.factor = factor
        self.width = width
        self.whole = width - width % factor  # columns in complete blocks
        counts = [factor] * (self.whole // factor) + (
            [width - self.whole] if width % factor else []
        )
        self.counts = np.array(counts, dtype=np.float64)[:, None]
        self.pending: np.ndarray | None = None

    def _blocks(self, rows: np.ndarray, height: int) -> np.ndarray:
        """Means of `height`-row groups of rows (k * height rows) over blocks of columns."""
        # Sums of strided slices: one pass over the band, several times faster than numpy's
        # reductions over the axes of a reshaped view.
        f = self.factor
        summed = rows[0::height].copy()  # (k, width, c): row i of every group at once
        for i in range(1, height):
            summed += rows[i::height]
        out = summed[:, 0 : self.whole : f].copy()
        for i in range(1, f):
            out += summed[:, i : self.whole : f]
        if self.whole < self.width:
            out = np.concatenate([out, summed[:, self.whole :].sum(axis=1, keepdims=True)], 1)
        return out / (self.counts * height)

    def aligned(self, band_height: int, tiles: Band, final: bool) -> bool:
        """Whether the band can be reduced tile by tile (_display_blocks): no rows carried
        over, and the factor divides its height (but for the last band) and its tiles'
        offsets, as it does a power-of-two tile size for power-of-two factors."""
        f = self.factor
        return (
            self.pending is None
            and (band_height % f == 0 or final)
            and all(rect.x0 % f == 0 for rect, _ in tiles)
        )

    def add(self, rows: np.ndarray, final: bool = False) -> np.ndarray:
        """The output rows complete with these input rows (all that is left when final)."""
        if self.pending is not None:
            rows = np.concatenate([self.pending, rows])
            self.pending = None
        f = self.factor
        whole = rows.shape[0] - rows.shape[0] % f
        out = [self._blocks(rows[:whole], f)] if whole else []
        rest = rows[whole:]
        if rest.shape[0]:
            if final:
                out.append(self._blocks(rest, rest.shape[0]))
            else:
                self.pending = rest.copy()  # not a view: the band it is in can go
        if not out:
            return np.zeros((0, len(self.counts), rows.shape[2]))
        return np.concatenate(out) if len(out) > 1 else out[0]


class DenoiseFrame:
    """The colour, albedo and normal of a whole frame (float32 (height, width, 3) each),
    filled band by band (add_band), then denoised (denoise)."""

    def __init__(self, width: int, height: int):
        self.width, self.height = width, height
        self.color = np.zeros((height, width, 3), np.float32)
        self.albedo = np.zeros((height, width, 3), np.float32)
        self.normal = np.zeros((height, width, 3), np.float32)
        self.y = 0

    def add_band(self, band_height: int, tiles: Band) -> None:
        ys = slice(self.y, self.y + band_height)
        for rect, acc in tiles:  # an unsampled tile stays zero (black, no guides)
            if acc is None:
                continue
            xs = slice(rect.x0, rect.x0 + rect.width)
            self.color[ys, xs] = acc.rgb_sum / acc.samples
            if acc.albedo_sum is not None:
                self.albedo[ys, xs] = acc.mean_albedo()
                self.normal[ys, xs] = acc.mean_normal()
        self.y += band_height

    def denoise(self) -> np.ndarray:
        """The denoised RGB, float32 (height, width, 3). The frame lets go of its inputs: they
        are freed once denoised."""
        inputs = self.color, self.albedo, self.normal
        self.color = self.albedo = self.normal = None
        return denoise_frame(*inputs)


def denoise_frame(color: np.ndarray, albedo: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Open Image Denoise's "RT" filter (HDR colour, albedo and normal guides, high quality)
    on whole float32 (h, w, 3) frames. Its scratch memory is held under
    jobspec.DENOISE_SCRATCH_MB (maxMemoryMB: beyond it, OIDN denoises in overlapping tiles)."""
    import pyoidn  # heavy import (loads the OIDN library), only where a frame is denoised

    from ..domain.jobspec import DENOISE_SCRATCH_MB

    # Non-finite values would spread through the network: a broken pixel is black for the
    # denoiser (the unbiased layers keep what they are). A copy only when there is one.
    if not np.isfinite(color).all():
        color = np.nan_to_num(color, nan=0.0, posinf=0.0, neginf=0.0)
    color = np.ascontiguousarray(color, np.float32)
    output = np.empty_like(color)
    with _DENOISE_LOCK, pyoidn.Device() as device:
        device.commit()
        with pyoidn.Filter(device, pyoidn.OIDN_FILTER_TYPE_RT) as flt:
            for name, image in (
                (pyoidn.OIDN_IMAGE_COLOR, color),
                (pyoidn.OIDN_IMAGE_ALBEDO, np.ascontiguousarray(albedo, np.float32)),
                (pyoidn.OIDN_IMAGE_NORMAL, np.ascontiguousarray(normal, np.float32)),
                (pyoidn.OIDN_IMAGE_OUTPUT, output),
            ):
                flt.set_image(name, image, pyoidn.OIDN_FORMAT_FLOAT3)
            flt.set_bool("hdr", True)
            flt.set_int("maxMemoryMB", DENOISE_SCRATCH_MB)
            flt.set_quality(pyoidn.OIDN_QUALITY_HIGH)
            flt.commit()
            flt.execute()
        error = device.get_error()
    if error is not None:
        raise RuntimeError(f"Open Image Denoise failed: {error}")
    return output


# One frame denoised at a time: OIDN uses every core already, and two at once would double
# the memory the submission check allowed for (the service also writes one such image at a
# time).
_DENOISE_LOCK = threading.Lock()


SLICE_ROWS = 64  # rows an ImageWriter computes from the tiles at a time
# An EXR's rows go to OpenImageIO in chunks of about this many bytes, written (compressed by
# OpenEXR's thread pool, 16 scanlines a zip block) in a thread of their own while the next
# chunk's channels are computed: two chunks are held at most. Small chunks starve the pool:
# 64-row calls took 1.7 times as long as 256-row ones on an 8192-pixel-wide EXR.
EXR_CHUNK_BYTES = 64 << 20


def _rows_of(tiles: Band, y0: int, y1: int) -> Band:
    """Rows y0..y1 of a band's tiles: accumulators over views of their arrays (no copies)."""
    part: Band = []
    for rect, acc in tiles:
        rows = Rect(rect.x0, rect.y0 + y0, rect.width, y1 - y0)
        if acc is not None:
            present = tuple(n for n in acc.arrays if getattr(acc, n) is not None)
            arrays = tuple(getattr(acc, n)[y0:y1] for n in present)
            acc = TileAccumulator.from_snapshot(
                rect.width, y1 - y0, present, arrays, acc.samples, acc.batches, acc.iid,
                acc.layout,
            )  # fmt: skip
        part.append((rows, acc))
    return part


class ImageWriter:
    """Writes a job's EXR or a PNG layer to `path` from bands of tiles given top to bottom.

    For a grey PNG layer, `top` is the layer's maximum over the whole image (layer_maximum of
    every band): the layer is normalised to it. An EXR's DateTime is `date_time` (Unix
    seconds, UTC; the epoch when None), never the time of writing."""

    def __init__(
        self,
        path: str,
        fmt: str,
        width: int,
        height: int,
        layer: str = "rgb",
        max_size: int = 0,
        top: float = 1.0,
        cancelled: threading.Event | None = None,
        compression: str = "zip",
        date_time: float | None = None,
        denoised: np.ndarray | None = None,
        attributes: dict[str, str | int | float | tuple[float, ...]] | None = None,
        layout: channels.Layout = channels.DEFAULT,
        crypto: cryptomatte.Names | None = None,
    ):
        """layout: the job's (channels.job_layout): the EXR's channels are its own. crypto: the
        scene's Cryptomatte names (a layout with Cryptomatte rows: its IDs and manifests)."""
        import OpenImageIO as oiio  # heavy import, only where images are written

        self.fmt, self.layer, self.width, self.height = fmt, layer, width, height
        self.outputs = output_rows(layout)
        self.crypto = crypto or cryptomatte.Names.of({})
        # Each type's IDs by label, hashed once for the whole image.
        self.crypto_ids = {t: self.crypto.id_table(t) for t in cryptomatte.TYPES}
        self.top = top if math.isfinite(top) and top > 0 else 1.0
        self.cancelled = cancelled
        if fmt == "exr":
            channels = (
                EXR_CHANNELS
                + tuple(e for row in self.outputs for layer in row.layers for e in layer.exr)
                + (DENOISED_CHANNELS if denoised is not None else ())
            )
            spec = oiio.ImageSpec(width, height, len(channels), oiio.FLOAT)
            spec.channelnames = channels
            spec.alpha_channel = channels.index("A")
            # The job's record (renderfarm:settings, ...): string, int or float attributes,
            # and 16 floats as a matrix (Imath M44f: worldToCamera, worldToNDC).
            for name, value in (attributes or {}).items():
                if isinstance(value, tuple) and len(value) == 16:
                    spec.attribute(name, oiio.TypeMatrix44, value)
                else:
                    spec.attribute(name, value)
            # Cryptomatte's attributes (cryptomatte/{key}/name, hash, conversion, manifest).
            for row in self.outputs:
                for layer in row.layers if row.accumulate is Accumulate.RANKED else ():
                    for name, value in self.crypto.header(crypto_type(layer)).items():
                        spec.attribute(name, value)
            # zip at zlib level 1 (deflate's fastest): 15-30% less CPU than OpenEXR's default
            # level 4 for files under 1% larger, and still the zip every EXR reader reads.
            spec.attribute("compression", "zip:1" if compression == "zip" else compression)
            # OpenImageIO stamps an EXR with the time of writing unless told a time: the
            # caller's (the job's) keeps an image's bytes a function of the job alone.
            stamp = time.gmtime(0 if date_time is None else date_time)
            spec.attribute("DateTime", time.strftime("%Y:%m:%d %H:%M:%S", stamp))
        else:
            f = downscale_factor(width, height, max_size)
            self.scale = _Downscaler(width, f) if f > 1 else None
            spec = oiio.ImageSpec(math.ceil(width / f), math.ceil(height / f), 3, oiio.UINT8)
            spec.channelnames = ("R", "G", "B")
            # zlib's fastest level and the "up" filter: 3-4 times faster to encode than the
            # defaults (level 6, adaptive filters) for a file 5-20% larger.
            spec.attribute("png:compressionLevel", 1)
            spec.attribute("png:filter", 32)
            if layer in GREY_LAYERS:
                # The scale of the grey (tEXt chunks): black is 0 and white self.top, so a
                # viewer can label its colour bar with values (the dashboard does).
                spec.attribute("renderfarm:layer", layer)
                spec.attribute("renderfarm:scale_min", "0")
                spec.attribute("renderfarm:scale_max", repr(self.top))
        self.spec = spec
        self.rows_written = 0  # output scanlines so far
        # The whole denoised frame (DenoiseFrame.denoise): the EXR's denoised.R/G/B, or the
        # PNG's denoised layer; its rows are taken as the bands' rows come.
        self.denoised = denoised
        if layer == "denoised" and fmt == "png" and denoised is None:
            raise ValueError("the denoised layer needs the denoised frame")
        self.rows_in = 0  # input scanlines so far
        if fmt == "exr":
            # Chunks of whole zip blocks (16 rows), given to OpenImageIO in self._emitter.
            row_bytes = width * len(spec.channelnames) * 4
            self.chunk_rows = max(16, EXR_CHUNK_BYTES // max(1, row_bytes) // 16 * 16)
            self._chunk: np.ndarray | None = None
            self._chunk_fill = 0
            self._emitter = ThreadPoolExecutor(1, thread_name_prefix="exr-writer")
            self._emitting: Future | None = None
        # One thread at a time: abandon() may come from another thread while a band is
        # being written (the request was cancelled), and waits for it.
        self._lock = threading.Lock()
        self.out = oiio.ImageOutput.create(path)
        if self.out is None or not self.out.open(path, spec):
            raise RuntimeError(f"cannot write {fmt} image: {oiio.geterror()}")

    def write_band(self, band_height: int, tiles: Band, final: bool = False) -> None:
        """The next band_height rows of the image (final: the last band)."""
        with self._lock:
            if self.cancelled is not None and self.cancelled.is_set():
                raise Cancelled("the server is stopping")
            # At most SLICE_ROWS rows at a time: the channels of a band of 512-pixel tiles
            # would be 200 MB on an 8192-pixel-wide EXR.
            for y0 in range(0, band_height, SLICE_ROWS):
                y1 = min(band_height, y0 + SLICE_ROWS)
                part = tiles if y1 - y0 == band_height else _rows_of(tiles, y0, y1)
                self._write_rows(y1 - y0, part, final and y1 == band_height)

    def _write_rows(self, band_height: int, tiles: Band, final: bool) -> None:
        y_in = self.rows_in
        self.rows_in += band_height
        if self.fmt == "exr":
            pixels = _exr_band(self.width, band_height, tiles)
            parts = [pixels]
            if self.outputs:
                parts.append(
                    _outputs_band(
                        self.width, band_height, tiles, self.outputs, self.crypto, self.crypto_ids
                    )
                )
            if self.denoised is not None:
                parts.append(self.denoised[y_in : y_in + band_height])
            if len(parts) > 1:
                pixels = np.concatenate(parts, 2)
        elif self.layer == "denoised":
            linear = self.denoised[y_in : y_in + band_height].astype(np.float64)
            if self.scale is not None:
                linear = self.scale.add(linear, final)
        elif self.scale is not None and self.scale.aligned(band_height, tiles, final):
            linear = _display_blocks(
                self.layer, self.width, band_height, tiles, self.top, self.scale.factor,
                self.crypto,
            )  # fmt: skip
        else:
            linear = _display_band(
                self.layer, self.width, band_height, tiles, self.top, self.crypto
            )
            if self.scale is not None:
                linear = self.scale.add(linear, final)
        if self.fmt == "png":
            if self.layer in GREY_LAYERS:
                pixels = np.round(np.clip(linear, 0, 1) * 255).astype(np.uint8)
            else:
                pixels = np.round(srgb_encode(linear) * 255.0).astype(np.uint8)
        if not pixels.shape[0]:
            return
        if self.fmt == "exr":
            self._buffer_rows(pixels, final)
        else:
            self._emit(pixels)

    def _emit(self, pixels: np.ndarray) -> None:
        y = self.rows_written
        if not self.out.write_scanlines(y, y + pixels.shape[0], 0, np.ascontiguousarray(pixels)):
            raise RuntimeError(f"cannot write {self.fmt} image: {self.out.geterror()}")
        self.rows_written += pixels.shape[0]

    def _buffer_rows(self, pixels: np.ndarray, final: bool) -> None:
        """Adds an EXR's rows to the chunk being filled; a full chunk (or the last) goes to the
        emitter thread once the previous one is written (its error, if any, raised here)."""
        taken = 0
        while taken < pixels.shape[0]:
            if self._chunk is None:
                self._chunk = np.empty((self.chunk_rows, *pixels.shape[1:]), np.float32)
                self._chunk_fill = 0
            n = min(pixels.shape[0] - taken, self.chunk_rows - self._chunk_fill)
            self._chunk[self._chunk_fill : self._chunk_fill + n] = pixels[taken : taken + n]
            self._chunk_fill += n
            taken += n
            if self._chunk_fill == self.chunk_rows:
                self._hand_over()
        if final and self._chunk is not None:
            self._hand_over()

    def _hand_over(self) -> None:
        chunk, self._chunk = self._chunk[: self._chunk_fill], None
        self._wait_emitted()
        self._emitting = self._emitter.submit(self._emit, chunk)

    def _wait_emitted(self) -> None:
        if self._emitting is not None:
            emitting, self._emitting = self._emitting, None
            emitting.result()

    def _stop_emitter(self) -> None:
        if self.fmt == "exr":
            try:
                self._wait_emitted()
            finally:
                self._emitter.shutdown(wait=True)

    def close(self) -> None:
        with self._lock:
            try:
                if self.fmt == "exr" and self._chunk is not None:
                    self._hand_over()  # the last rows, when no band was marked final
                self._stop_emitter()
            except BaseException:
                self.out.close()
                raise
            ok = self.out.close()
            if not ok or self.rows_written != self.spec.height:
                raise RuntimeError(
                    f"cannot write {self.fmt} image: {self.out.geterror() or 'missing rows'}"
                )

    def abandon(self) -> None:
        """Close after an error (the file is the caller's to remove)."""
        with self._lock:
            try:
                self._stop_emitter()
            except Exception:  # noqa: BLE001 (the error that made the caller abandon counts)
                pass
            self.out.close()


def read_exr(path: str) -> dict[str, np.ndarray]:
    """Channels of an EXR file by name (used by tests and the CLI)."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(path)
    if inp is None:
        raise RuntimeError(f"cannot read {path}: {oiio.geterror()}")
    try:
        spec = inp.spec()
        pixels = inp.read_image(oiio.FLOAT)
    finally:
        inp.close()
    return {name: pixels[..., i] for i, name in enumerate(spec.channelnames)}
