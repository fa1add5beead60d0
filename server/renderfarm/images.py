"""Images of a job: full-frame layers assembled from tile accumulators, written with OpenImageIO.

EXR channels (32-bit float):
  R, G, B                 mean radiance
  variance.Y              estimated variance of the mean luminance (inf where unknown)
  spp                     samples merged per pixel
  error                   relative error: sqrt(variance.Y) / max(Y, DARK_FLOOR)
  albedo.R/G/B            mean first-hit albedo
  normal.X/Y/Z            mean first-hit shading normal (world space)
PNG: the RGB layer, clamped to [0, 1], sRGB-encoded, 8 bits.
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass

import numpy as np

from .merge import TileAccumulator
from .tiling import Rect

EXR_CHANNELS = (
    "R", "G", "B", "variance.Y", "spp", "error",
    "albedo.R", "albedo.G", "albedo.B", "normal.X", "normal.Y", "normal.Z",
)  # fmt: skip
LAYERS = ("rgb", "variance", "spp", "error", "albedo", "normal")


@dataclass
class Frame:
    rgb: np.ndarray  # (H, W, 3)
    variance: np.ndarray  # (H, W)
    spp: np.ndarray  # (H, W)
    error: np.ndarray  # (H, W)
    albedo: np.ndarray  # (H, W, 3)
    normal: np.ndarray  # (H, W, 3)


def assemble(width: int, height: int, tiles: list[tuple[Rect, TileAccumulator]]) -> Frame:
    frame = Frame(
        rgb=np.zeros((height, width, 3)),
        variance=np.full((height, width), np.inf),
        spp=np.zeros((height, width)),
        error=np.full((height, width), np.inf),
        albedo=np.zeros((height, width, 3)),
        normal=np.zeros((height, width, 3)),
    )
    for rect, acc in tiles:
        if acc.samples == 0:
            continue
        ys = slice(rect.y0, rect.y0 + rect.height)
        xs = slice(rect.x0, rect.x0 + rect.width)
        n = acc.samples
        frame.rgb[ys, xs] = acc.rgb_sum / n
        frame.variance[ys, xs] = acc.variance_of_mean()
        frame.spp[ys, xs] = n
        frame.error[ys, xs] = acc.relative_error()
        frame.albedo[ys, xs] = acc.mean_albedo()
        frame.normal[ys, xs] = acc.mean_normal()
    return frame


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB transfer function of linear values clamped to [0, 1]."""
    x = np.clip(np.nan_to_num(linear, nan=0.0, posinf=1.0), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def to_png_bytes(rgb: np.ndarray) -> bytes:
    pixels = np.round(srgb_encode(rgb) * 255.0).astype(np.uint8)
    return _write(pixels, ".png", ("R", "G", "B"))


def layer_png_bytes(frame: Frame, layer: str) -> bytes:
    """A false-colour view of a layer for previews (error heat map, spp map, ...)."""
    if layer == "rgb":
        return to_png_bytes(frame.rgb)
    if layer in ("albedo",):
        return to_png_bytes(frame.albedo)
    if layer == "normal":
        return to_png_bytes(frame.normal * 0.5 + 0.5)
    values = {"variance": np.sqrt(frame.variance), "spp": frame.spp, "error": frame.error}[layer]
    finite = values[np.isfinite(values)]
    top = float(finite.max()) if finite.size and finite.max() > 0 else 1.0
    scaled = np.where(np.isfinite(values), values / top, 1.0)
    gray = np.repeat(scaled[..., None], 3, axis=-1)
    return _write(np.round(np.clip(gray, 0, 1) * 255).astype(np.uint8), ".png", ("R", "G", "B"))


def to_exr_bytes(frame: Frame) -> bytes:
    data = np.concatenate(
        [
            frame.rgb,
            frame.variance[..., None],
            frame.spp[..., None],
            frame.error[..., None],
            frame.albedo,
            frame.normal,
        ],
        axis=-1,
    ).astype(np.float32)
    return _write(data, ".exr", EXR_CHANNELS)


def _write(pixels: np.ndarray, suffix: str, channels: tuple[str, ...]) -> bytes:
    import OpenImageIO as oiio  # heavy import, only where images are written

    height, width, nchannels = pixels.shape
    fmt = oiio.FLOAT if pixels.dtype == np.float32 else oiio.UINT8
    spec = oiio.ImageSpec(width, height, nchannels, fmt)
    spec.channelnames = channels
    if suffix == ".exr":
        spec.attribute("compression", "zip")
    fd, path = tempfile.mkstemp(suffix=suffix)
    os.close(fd)
    try:
        out = oiio.ImageOutput.create(path)
        if out is None or not out.open(path, spec):
            raise RuntimeError(f"cannot write {suffix} image: {oiio.geterror()}")
        ok = out.write_image(np.ascontiguousarray(pixels))
        out.close()
        if not ok:
            raise RuntimeError(f"cannot write {suffix} image: {out.geterror()}")
        with open(path, "rb") as f:
            return f.read()
    finally:
        os.unlink(path)


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
