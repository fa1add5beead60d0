"""The denoised layer and the job's record in the EXR header, written band by band beside the
unbiased layers (which stay as they are)."""

from __future__ import annotations

import json

import numpy as np
import OpenImageIO as oiio
import pyoidn
import pytest

from renderfarm.domain.jobspec import (
    DENOISE_BYTES_PER_PIXEL,
    Limits,
    denoise_memory_bytes,
    job_memory_bytes,
    parse_settings,
)
from renderfarm.domain.merge import TileAccumulator
from renderfarm.domain.tiling import tile_grid
from renderfarm.errors import SettingsError
from renderfarm.infra import images
from renderfarm.infra.images import (
    DENOISED_CHANNELS,
    EXR_CHANNELS,
    DenoiseFrame,
    ImageWriter,
    read_exr,
)

W, H, TILE = 70, 45, 16


def accumulators() -> list[tuple]:
    """A smooth gradient seen through noise, one tile never merged."""
    rng = np.random.default_rng(7)
    tiles = []
    for i, rect in enumerate(tile_grid(W, H, TILE)):
        acc = TileAccumulator(rect.width, rect.height)
        if i != 3:
            shape = (rect.height, rect.width)
            ys, xs = np.mgrid[rect.y0 : rect.y0 + rect.height, rect.x0 : rect.x0 + rect.width]
            clean = np.stack([xs / W, ys / H, np.full(shape, 0.5)], -1)
            for n in (4, 4):
                rgb = clean * n * rng.exponential(1.0, (*shape, 3))
                albedo = np.broadcast_to(np.float32(0.8) * n, (*shape, 3)).astype(np.float32)
                normal = np.zeros((*shape, 3), np.float32)
                normal[..., 2] = n
                acc.merge_batch(rgb, rgb.mean(-1), n, albedo, normal)
        tiles.append((rect, acc))
    return tiles


def bands(tiles):
    cols = -(-W // TILE)
    rows = [tiles[i : i + cols] for i in range(0, len(tiles), cols)]
    return [[(r, a if a.samples else None) for r, a in band] for band in rows]


def inputs(tiles):
    """Colour, albedo and normal of the whole frame, as OIDN is to see them."""
    color, albedo, normal = (np.zeros((H, W, 3), np.float32) for _ in range(3))
    for rect, acc in tiles:
        if acc.samples:
            at = (slice(rect.y0, rect.y0 + rect.height), slice(rect.x0, rect.x0 + rect.width))
            color[at] = acc.rgb_sum / acc.samples
            albedo[at] = acc.albedo_sum / min(acc.samples, 16)
            normal[at] = acc.normal_sum / min(acc.samples, 16)
    return color, albedo, normal


def denoised_of(tiles) -> np.ndarray:
    frame = DenoiseFrame(W, H)
    for band in bands(tiles):
        frame.add_band(band[0][0].height, band)
    return frame.denoise()


def write(path, fmt, tiles, layer="rgb", max_size=0, denoised=None, attributes=None):
    writer = ImageWriter(
        str(path), fmt, W, H, layer, max_size, denoised=denoised, attributes=attributes
    )
    parts = bands(tiles)
    for i, band in enumerate(parts):
        writer.write_band(band[0][0].height, band, i == len(parts) - 1)
    writer.close()


@pytest.fixture(params=[64, 5], ids=["whole-bands", "5-row-slices"])
def slice_rows(request, monkeypatch):
    monkeypatch.setattr(images, "SLICE_ROWS", request.param)


def test_denoised_frame_is_open_image_denoise_of_the_frame():
    tiles = accumulators()
    color, albedo, normal = inputs(tiles)
    want = pyoidn.denoise(color, albedo, normal, hdr=True, quality="high")
    got = denoised_of(tiles)
    assert got.shape == (H, W, 3) and got.dtype == np.float32
    assert np.allclose(got, want, atol=1e-5)
    assert np.abs(got - color).max() > 0.05  # it did change the noisy colour


def test_exr_has_denoised_channels_beside_unchanged_layers(tmp_path, slice_rows):
    tiles = accumulators()
    denoised = denoised_of(tiles)
    write(tmp_path / "plain.exr", "exr", tiles)
    write(tmp_path / "denoised.exr", "exr", tiles, denoised=denoised)
    plain, got = read_exr(str(tmp_path / "plain.exr")), read_exr(str(tmp_path / "denoised.exr"))
    assert sorted(got) == sorted(EXR_CHANNELS + ("denoised.R", "denoised.G", "denoised.B"))
    assert all(got[c].tobytes() == plain[c].tobytes() for c in EXR_CHANNELS)
    for i, c in enumerate(DENOISED_CHANNELS):
        assert got[c].tobytes() == np.ascontiguousarray(denoised[..., i]).tobytes(), c


@pytest.mark.parametrize(("max_size", "factor"), [(0, 1), (35, 2), (24, 3)])
def test_png_denoised_layer_is_the_denoised_frame(tmp_path, slice_rows, max_size, factor):
    tiles = accumulators()
    denoised = denoised_of(tiles).astype(np.float64)
    write(tmp_path / "d.png", "png", tiles, "denoised", max_size, denoised=denoised)
    inp = oiio.ImageInput.open(str(tmp_path / "d.png"))
    got = inp.read_image(oiio.UINT8)
    inp.close()
    out_h, out_w = -(-H // factor), -(-W // factor)
    linear = np.zeros((out_h, out_w, 3))
    for y in range(out_h):
        for x in range(out_w):
            block = denoised[y * factor : (y + 1) * factor, x * factor : (x + 1) * factor]
            linear[y, x] = block.mean(axis=(0, 1))
    x = np.clip(linear, 0, 1)
    want = np.round(np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055) * 255)
    assert got.shape == (out_h, out_w, 3)
    assert np.abs(got.astype(int) - want.astype(int)).max() <= 1


def test_png_denoised_layer_needs_the_frame(tmp_path):
    with pytest.raises(ValueError, match="denoised frame"):
        ImageWriter(str(tmp_path / "d.png"), "png", W, H, "denoised")


def test_exr_header_carries_the_given_attributes(tmp_path):
    record = {"max_spp": 8, "denoise": True}
    attributes = {
        "renderfarm:settings": json.dumps(record),
        "renderfarm:scene_sha256": "ab" * 32,
        "renderfarm:mean_spp": 7.5,
    }
    write(tmp_path / "a.exr", "exr", accumulators(), attributes=attributes)
    spec = oiio.ImageInput.open(str(tmp_path / "a.exr")).spec()
    assert json.loads(spec.getattribute("renderfarm:settings")) == record
    assert spec.getattribute("renderfarm:scene_sha256") == "ab" * 32
    assert spec.getattribute("renderfarm:mean_spp") == pytest.approx(7.5)


def test_denoise_setting_is_a_bool():
    assert parse_settings({}).denoise is False
    assert parse_settings({"denoise": True}).denoise is True
    assert parse_settings({"denoise": "false"}).denoise is False
    for bad in (1, "yes", 0.0):
        with pytest.raises(SettingsError) as e:
            parse_settings({"denoise": bad})
        assert e.value.field == "settings.denoise"


def test_denoise_is_refused_past_the_job_memory_limit():
    need = job_memory_bytes(2048, 2048, 64) + denoise_memory_bytes(2048, 2048)
    assert denoise_memory_bytes(2048, 2048) >= DENOISE_BYTES_PER_PIXEL * 2048 * 2048
    limits = Limits(max_job_memory_bytes=need - 1)
    parse_settings({"width": 2048, "height": 2048}, limits)  # without denoise: fits
    with pytest.raises(SettingsError) as e:
        parse_settings({"width": 2048, "height": 2048, "denoise": True}, limits)
    assert e.value.field == "settings.denoise"
    assert "RENDERFARM_MAX_JOB_MEMORY_MB" in e.value.message
    parse_settings(
        {"width": 2048, "height": 2048, "denoise": True}, Limits(max_job_memory_bytes=need)
    )


@pytest.mark.parametrize("layer", ["spp", "rgb"])
def test_grey_png_records_its_scale(tmp_path, layer):
    """A grey layer's PNG says what white is (the dashboard labels its colour bar with it)."""
    tiles = accumulators()
    top = images.layer_maximum(layer, [t for band in bands(tiles) for t in band])
    writer = ImageWriter(str(tmp_path / "a.png"), "png", W, H, layer, top=top)
    parts = bands(tiles)
    for i, band in enumerate(parts):
        writer.write_band(band[0][0].height, band, i == len(parts) - 1)
    writer.close()
    spec = oiio.ImageInput.open(str(tmp_path / "a.png")).spec()
    if layer == "rgb":  # not a grey layer: no scale
        assert spec.getattribute("renderfarm:scale_max") is None
        return
    assert spec.getattribute("renderfarm:layer") == "spp"
    assert spec.getattribute("renderfarm:scale_min") == "0"
    assert float(spec.getattribute("renderfarm:scale_max")) == 8.0  # two batches of 4


def test_cli_denoise_flag_is_on_off_or_the_servers_default():
    from renderfarm.cli.commands import _job_settings
    from renderfarm.cli.parser import build_parser

    parse = build_parser().parse_args
    assert _job_settings(parse(["submit", "s.glb", "--denoise"])) == {"denoise": True}
    assert _job_settings(parse(["submit", "s.glb", "--no-denoise"])) == {"denoise": False}
    assert "denoise" not in _job_settings(parse(["render", "s.glb", "-o", "o.exr"]))
    args = parse(["get", "abc", "-o", "out.exr", "--layer", "error"])
    assert (args.output, args.layer) == ("out.exr", "error")


def test_denoise_frame_of_spilled_tiles_is_that_of_tiles_in_ram(tmp_path):
    """The frame gathered from tile views (as the server hands them over), some of them read
    back from a spill file, is the one gathered from the accumulators in RAM."""
    from renderfarm.infra.images import TileView, arrays_needed
    from renderfarm.infra.spill import TileCache

    tiles = accumulators()
    names = arrays_needed("png", "denoised")

    def gathered() -> DenoiseFrame:
        frame = DenoiseFrame(W, H)
        for band in bands(tiles):
            views = [(r, a and TileView.of(r, a, names)) for r, a in band]
            frame.add_band(band[0][0].height, [(r, v and v.accumulator()) for r, v in views])
        return frame

    in_ram = gathered()
    color, albedo, normal = inputs(tiles)
    assert np.allclose(in_ram.color, color) and np.allclose(in_ram.albedo, albedo)
    assert np.allclose(in_ram.normal, normal)
    cache = TileCache(tmp_path / "scratch", budget_bytes=1)
    for _, acc in tiles:
        cache.register("j", acc, TILE)
    assert sum(not acc.resident for _, acc in tiles) >= len(tiles) - 1
    spilled = gathered()
    for part in ("color", "albedo", "normal"):
        assert getattr(spilled, part).tobytes() == getattr(in_ram, part).tobytes(), part
