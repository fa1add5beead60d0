"""Images written a row of tiles at a time hold the values of the whole frame, computed here
per pixel from the accumulators at once; downscaled previews are box filters of them."""

from __future__ import annotations

import numpy as np
import OpenImageIO as oiio
import pytest

from renderfarm.domain.merge import TileAccumulator
from renderfarm.domain.tiling import tile_grid
from renderfarm.infra import images
from renderfarm.infra.images import EXR_CHANNELS, ImageWriter, TileView, arrays_needed, read_exr
from renderfarm.infra.spill import TileCache

W, H, TILE = 70, 45, 16  # edge tiles narrower and shorter than the others


@pytest.fixture(autouse=True, params=[64, 5], ids=["whole-bands", "5-row-slices"])
def slice_rows(request, monkeypatch):
    """Bands written whole, and in slices of 5 rows (as 512-pixel tiles are, in 64)."""
    monkeypatch.setattr(images, "SLICE_ROWS", request.param)
    return request.param


@pytest.fixture(autouse=True, params=[64 << 20, 1], ids=["one-chunk", "16-row-chunks"])
def exr_chunk_bytes(request, monkeypatch):
    """EXR rows handed to OpenImageIO all at once, and in chunks of 16 rows (the smallest: the
    last chunk then ends inside a band and a band spans chunks)."""
    monkeypatch.setattr(images, "EXR_CHUNK_BYTES", request.param)
    return request.param


def accumulators(seed: int = 0) -> list[tuple]:
    """(rect, accumulator) of every tile, a few of them never merged, some very dark, and
    fireflies above 1 (clamped in PNGs)."""
    rng = np.random.default_rng(seed)
    tiles = []
    for i, rect in enumerate(tile_grid(W, H, TILE)):
        acc = TileAccumulator(rect.width, rect.height, iid=i % 4 == 1)
        if i % 5 != 3:
            for n in (1, 1, 2, 4)[: 1 + i % 4]:
                shape = (rect.height, rect.width)
                rgb = rng.lognormal(-1.5, 1.5, (*shape, 3)) * n * (0.01 if i % 7 == 0 else 1)
                acc.merge_batch(
                    rgb, rng.random(shape) * n, n,
                    rng.random((*shape, 3), dtype=np.float32) * n,
                    rng.standard_normal((*shape, 3)).astype(np.float32) * n, 0,
                    rng.integers(0, n + 1, shape).astype(np.float32),  # hits of n samples
                )  # fmt: skip
        tiles.append((rect, acc))
    return tiles


def whole_frame(tiles) -> dict[str, np.ndarray]:
    """Every layer of the frame at once, float64, as the server computed it before images
    were written in bands."""
    frame = {
        "rgb": np.zeros((H, W, 3)),
        "variance": np.full((H, W), np.inf),
        "spp": np.zeros((H, W)),
        "error": np.full((H, W), np.inf),
        "albedo": np.zeros((H, W, 3)),
        "normal": np.zeros((H, W, 3)),
        "alpha": np.zeros((H, W)),
    }
    for rect, acc in tiles:
        if acc.samples == 0:
            continue
        at = (slice(rect.y0, rect.y0 + rect.height), slice(rect.x0, rect.x0 + rect.width))
        n = acc.samples
        frame["rgb"][at] = acc.rgb_sum / n
        frame["variance"][at] = acc.variance_of_mean()
        frame["spp"][at] = n
        frame["error"][at] = acc.relative_error()
        frame["albedo"][at] = acc.albedo_sum / min(n, 16)
        frame["normal"][at] = acc.normal_sum / min(n, 16)
        frame["alpha"][at] = acc.coverage_sum.astype(np.float64) / n
    return frame


def srgb(x: np.ndarray) -> np.ndarray:
    x = np.clip(np.nan_to_num(x, nan=0.0, posinf=1.0), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)


def display(frame, layer: str) -> tuple[np.ndarray, bool]:
    """(linear display values (H, W, 3), whether they are sRGB-encoded) of a PNG layer."""
    if layer in ("rgb", "albedo"):
        return frame[layer], True
    if layer == "normal":
        return frame["normal"] * 0.5 + 0.5, True
    values = np.sqrt(frame["variance"]) if layer == "variance" else frame[layer]
    finite = values[np.isfinite(values)]
    top = finite.max() if finite.size and finite.max() > 0 else 1.0
    grey = np.where(np.isfinite(values), values / top, 1.0)
    return np.repeat(grey[..., None], 3, axis=-1), False


def encode(linear: np.ndarray, is_srgb: bool) -> np.ndarray:
    scaled = srgb(linear) if is_srgb else np.clip(linear, 0, 1)
    return np.round(scaled * 255).astype(np.uint8)


def write(path, fmt, tiles, layer="rgb", max_size=0, as_views=False):
    """The image through ImageWriter, band by band (a row of tiles each), as the server does."""
    cols = -(-W // TILE)
    bands = [tiles[i : i + cols] for i in range(0, len(tiles), cols)]
    if as_views:  # as the server hands them over: snapshots, read in the writer's thread
        names = arrays_needed(fmt, layer)
        bands = [[(r, v and v.accumulator()) for r, v in
                  [(r, TileView.of(r, a, names)) for r, a in band]] for band in bands]  # fmt: skip
    else:
        bands = [[(r, a if a.samples else None) for r, a in band] for band in bands]
    top = -np.inf
    if layer in ("variance", "spp", "error"):
        from renderfarm.infra.images import layer_maximum

        top = max(layer_maximum(layer, band) for band in bands)
    writer = ImageWriter(str(path), fmt, W, H, layer, max_size, top)
    for i, band in enumerate(bands):
        writer.write_band(band[0][0].height, band, i == len(bands) - 1)
    writer.close()


def read_png(path) -> np.ndarray:
    inp = oiio.ImageInput.open(str(path))
    try:
        return inp.read_image(oiio.UINT8)
    finally:
        inp.close()


def test_exr_has_every_layer_of_the_whole_frame(tmp_path):
    tiles = accumulators()
    write(tmp_path / "a.exr", "exr", tiles)
    got = read_exr(str(tmp_path / "a.exr"))
    assert sorted(got) == sorted(EXR_CHANNELS)
    frame = whole_frame(tiles)
    expected = {
        "R": frame["rgb"][..., 0], "G": frame["rgb"][..., 1], "B": frame["rgb"][..., 2],
        "variance.Y": frame["variance"], "spp": frame["spp"], "error": frame["error"],
        **{f"albedo.{c}": frame["albedo"][..., i] for i, c in enumerate("RGB")},
        **{f"normal.{c}": frame["normal"][..., i] for i, c in enumerate("XYZ")},
        "A": frame["alpha"],
    }  # fmt: skip
    for name, values in expected.items():
        want = values.astype(np.float32)  # rounded once, from the float64 value
        assert got[name].tobytes() == want.tobytes(), name
    assert np.isinf(got["variance.Y"]).any() and (got["spp"] == 0).any()  # unmerged tiles
    assert 0 < got["A"].mean() < 1 and got["A"].max() <= 1
    spec = oiio.ImageInput.open(str(tmp_path / "a.exr"))
    try:  # readers that composite know which channel is the alpha
        assert spec.spec().channelnames[spec.spec().alpha_channel] == "A"
    finally:
        spec.close()


@pytest.mark.parametrize("layer", ["rgb", "variance", "spp", "error", "albedo", "normal"])
def test_png_layers_are_those_of_the_whole_frame(tmp_path, layer):
    tiles = accumulators(1)
    write(tmp_path / "a.png", "png", tiles, layer)
    want = encode(*display(whole_frame(tiles), layer))
    got = read_png(tmp_path / "a.png")
    assert got.shape == (H, W, 3)
    assert np.array_equal(got, want)


def box_filter(linear: np.ndarray, f: int) -> np.ndarray:
    """The mean of each f x f block (partial blocks at the right and bottom edges)."""
    out_h, out_w = -(-H // f), -(-W // f)
    out = np.zeros((out_h, out_w, 3))
    for y in range(out_h):
        for x in range(out_w):
            out[y, x] = linear[y * f : (y + 1) * f, x * f : (x + 1) * f].mean(axis=(0, 1))
    return out


# Factors that divide the tile size (band heights) and others, which carry rows over.
@pytest.mark.parametrize(
    ("max_size", "factor"), [(35, 2), (18, 4), (9, 8), (24, 3), (10, 7), (70, 1)]
)
@pytest.mark.parametrize("layer", ["rgb", "error", "normal", "albedo", "spp"])
def test_downscaled_previews_average_blocks_of_linear_values(tmp_path, layer, max_size, factor):
    tiles = accumulators(2)
    write(tmp_path / "a.png", "png", tiles, layer, max_size=max_size)
    got = read_png(tmp_path / "a.png")
    assert got.shape == (-(-H // factor), -(-W // factor), 3)
    assert max(got.shape[:2]) <= max_size
    linear, is_srgb = display(whole_frame(tiles), layer)
    want = encode(box_filter(linear, factor), is_srgb)
    # Sums in another order may round a value at a step of 1/255 the other way.
    difference = np.abs(got.astype(int) - want)
    assert difference.max() <= 1 and (difference == 0).mean() > 0.99


@pytest.mark.parametrize(
    ("fmt", "layer"),
    [("exr", "rgb"), ("png", "rgb"), ("png", "error"), ("png", "normal"), ("png", "spp")],
)
def test_images_of_spilled_tiles_are_the_same_files(tmp_path, fmt, layer):
    """Tiles read from a spill file give the image they give from RAM, bit for bit."""
    tiles = accumulators(3)
    write(tmp_path / f"ram.{fmt}", fmt, tiles, layer, as_views=True)
    cache = TileCache(tmp_path / "scratch", budget_bytes=1)
    for _, acc in tiles:
        cache.register("j", acc, TILE)
    assert sum(not acc.resident for _, acc in tiles) >= len(tiles) - 1
    write(tmp_path / f"spilled.{fmt}", fmt, tiles, layer, as_views=True)
    if fmt == "exr":  # its header has the time it was written (capDate): compare channels
        ram, spilled = (read_exr(str(tmp_path / f"{n}.exr")) for n in ("ram", "spilled"))
        assert all(ram[c].tobytes() == spilled[c].tobytes() for c in EXR_CHANNELS)
    else:
        assert (tmp_path / "ram.png").read_bytes() == (tmp_path / "spilled.png").read_bytes()


def test_exr_is_stamped_with_the_given_time_not_the_time_of_writing(tmp_path):
    """OpenImageIO writes the clock's time into an EXR's DateTime unless given one; the job's
    time makes the file a function of the job alone (the same bytes fetched a second later)."""
    tiles = accumulators()
    cols = -(-W // TILE)
    for name, stamp, expected in (("a", 0.0, "1970:01:01 00:00:00"),
                                  ("b", 1_800_000_000.0, "2027:01:15 08:00:00")):  # fmt: skip
        writer = ImageWriter(str(tmp_path / f"{name}.exr"), "exr", W, H, date_time=stamp)
        bands = [tiles[i : i + cols] for i in range(0, len(tiles), cols)]
        for i, band in enumerate(bands):
            band = [(r, a if a.samples else None) for r, a in band]
            writer.write_band(band[0][0].height, band, i == len(bands) - 1)
        writer.close()
        inp = oiio.ImageInput.open(str(tmp_path / f"{name}.exr"))
        try:
            assert inp.spec().getattribute("DateTime") == expected
        finally:
            inp.close()


def test_exr_abandoned_midway_stops_its_writer_thread(tmp_path):
    """A request cancelled after some bands: abandon() waits for the chunk being written and
    stops the emitter thread; close() refuses an image that is missing rows."""
    import threading

    tiles = [(r, a if a.samples else None) for r, a in accumulators()]
    cols = -(-W // TILE)
    before = {t.name for t in threading.enumerate()}
    writer = ImageWriter(str(tmp_path / "a.exr"), "exr", W, H)
    writer.write_band(TILE, tiles[:cols])
    writer.abandon()
    assert not {t.name for t in threading.enumerate()} - before
    writer = ImageWriter(str(tmp_path / "b.exr"), "exr", W, H)
    writer.write_band(TILE, tiles[:cols])
    with pytest.raises(RuntimeError, match="missing rows"):
        writer.close()
