"""Everything per pixel derives from the channel table (domain/channels.py, #40): each test here
fails when one of the places that used to be written by hand disagrees with it."""

from __future__ import annotations

import json
import re
import struct
from pathlib import Path

import numpy as np
import pytest

from renderfarm.cli.commands import EXR_LAYER_CHANNELS
from renderfarm.cli.parser import build_parser
from renderfarm.domain import channels, cryptomatte, jobspec
from renderfarm.domain.channels import Accumulate
from renderfarm.domain.merge import TileAccumulator
from renderfarm.domain.tiling import Rect
from renderfarm.infra import images
from renderfarm.infra.images import ImageWriter, read_exr
from renderfarm.infra.spill import TileCache

ROOT = Path(__file__).resolve().parents[2]
W, H = 7, 5


EVERY = channels.layout_for(channels.AOV_NAMES)  # a job with every output of `aovs`


def _outputs(rng, layout: channels.Layout, start: int) -> dict[str, np.ndarray]:
    """Random sums of the layout's output rows a batch starting at `start` carries."""
    return {
        c.wire: (
            _ranked(rng, c.wire_components // 2)
            if c.accumulate is Accumulate.RANKED
            else rng.integers(0, 2**24, (H, W, c.wire_components), dtype=np.uint32)
            if c.wire_type == "<u4"
            else (rng.random((H, W, c.wire_components)) * 10 - 3).astype(np.float32)
        )
        for c in layout.wire_rows_for(start)
        if c.name not in channels.DEFAULT.names
    }


def _ranked(rng, ranks: int) -> np.ndarray:
    """Ranked (label, count) pairs as a worker sends them: distinct labels 1..5 (1..3 of
    them a pixel), random counts, by count descending (then label), empty slots (0, 0)."""
    out = np.zeros((H, W, 2 * ranks), np.uint32)
    for j in range(H):
        for i in range(W):
            labels = rng.choice(np.arange(1, 6), rng.integers(1, 4), replace=False)
            pairs = sorted(((int(rng.integers(1, 9)), int(k)) for k in labels),
                           key=lambda p: (-p[0], p[1]))  # fmt: skip
            for r, (count, label) in enumerate(pairs):
                out[j, i, 2 * r : 2 * r + 2] = (label, count)
    return out


def merged(
    seed: int = 0, batches=(1, 1, 2, 4, 8, 16), layout: channels.Layout = channels.DEFAULT
) -> TileAccumulator:
    """A tile of W x H of a job with this layout merged from batches of random values, past
    the 16-sample window."""
    rng = np.random.default_rng(seed)
    acc = TileAccumulator(W, H, layout=layout)
    for n in batches:
        acc.merge_batch(
            (rng.random((H, W, 3)) * n).astype(np.float32),
            (rng.random((H, W)) * n).astype(np.float32), n,
            (rng.random((H, W, 3)) * n).astype(np.float32),
            rng.standard_normal((H, W, 3)).astype(np.float32), 0,
            rng.integers(0, n + 1, (H, W)).astype(np.float32),
            _outputs(rng, layout, acc.samples),
        )  # fmt: skip
    return acc


def test_the_accumulator_keeps_the_tables_arrays_and_the_memory_estimate_counts_them():
    acc = TileAccumulator(W, H)
    for a in channels.stored():
        array = getattr(acc, a.name)
        assert array.dtype == np.dtype(a.dtype), a.name
        assert array.shape == a.shape(W, H), a.name
    total = sum(getattr(acc, a.name).nbytes for a in channels.stored())
    assert total == acc.nbytes == TileAccumulator.BYTES_PER_PIXEL * W * H
    assert jobspec.ACCUMULATOR_BYTES_PER_PIXEL == TileAccumulator.BYTES_PER_PIXEL
    assert jobspec.job_memory_bytes(64, 64, 64) == (
        TileAccumulator.BYTES_PER_PIXEL * 64 * 64 + jobspec.TILE_OVERHEAD_BYTES
    )
    # What docs/usage.md tells a user ("76 bytes a pixel" and the estimate's formula).
    usage = (ROOT / "docs" / "usage.md").read_text()
    said = re.search(r"tile accumulators take (\d+) bytes a pixel", usage)
    assert said and int(said.group(1)) == TileAccumulator.BYTES_PER_PIXEL
    assert f"`{TileAccumulator.BYTES_PER_PIXEL} x width x height" in usage


def test_merging_sums_each_row_within_its_window():
    """A batch adds to a windowed row only while the pixel's samples are below the window;
    independent answer: numpy sums of the batches' values in float32, in batch order."""
    rng = np.random.default_rng(3)
    acc = TileAccumulator(W, H)
    want = {a.name: np.zeros(a.shape(W, H), np.float32) for a in channels.stored()
            if a.dtype == "<f4"}  # fmt: skip
    start = 0
    for n in (1, 1, 2, 4, 8, 16, 32):
        batch = {
            "albedo_sum": (rng.random((H, W, 3)) * n).astype(np.float32),
            "normal_sum": rng.standard_normal((H, W, 3)).astype(np.float32),
            "coverage_sum": rng.integers(0, n + 1, (H, W)).astype(np.float32),
        }
        rgb, m2 = np.ones((H, W, 3), np.float32) * n, np.zeros((H, W), np.float32)
        acc.merge_batch(rgb, m2, n, batch["albedo_sum"], batch["normal_sum"], 0,
                        batch["coverage_sum"])  # fmt: skip
        for c in channels.CHANNELS:
            if c.accumulate in (Accumulate.SUM, Accumulate.COUNT) and c.wire in batch:
                if not c.window or start < c.window:
                    want[c.store[0].name] += batch[c.wire]
        start += n
    for name, values in want.items():
        assert np.array_equal(getattr(acc, name), values), name
    # The window is 16 samples: albedo stopped after the batch of 8 (samples 8..15).
    assert channels.BY_NAME["albedo"].window == 16


def test_checkpoint_blobs_name_their_arrays_and_round_trip_bit_for_bit():
    acc = merged()
    for blob, names in ((acc.to_bytes(), channels.STATS_ARRAYS),
                        (acc.aovs_to_bytes(), channels.WINDOWED_ARRAYS)):  # fmt: skip
        assert channels.has_header(blob)
        version, arrays, pixels, offset = channels.read_header(blob, "test")
        assert version == channels.TABLE_VERSION and pixels == W * H
        assert tuple(a.name for a in arrays) == names
        assert all(a == channels.ARRAYS[a.name] for a in arrays)
        # The payload: each array little-endian in the table's dtype, in the listed order.
        payload = b"".join(np.ascontiguousarray(getattr(acc, n), channels.ARRAYS[n].dtype)
                           .tobytes() for n in names)  # fmt: skip
        assert bytes(blob[offset:]) == payload
        # The magic reads as NaN in both float widths: no blob from before the header (which
        # begins with a finite value) can look like one.
        assert np.isnan(np.frombuffer(blob[:4], "<f4")[0])
        assert np.isnan(np.frombuffer(blob[:8], "<f8")[0])
    back = TileAccumulator.from_bytes(W, H, acc.to_bytes(), acc.samples, acc.batches,
                                      aovs=acc.aovs_to_bytes())  # fmt: skip
    for a in channels.stored():
        assert getattr(back, a.name).tobytes() == getattr(acc, a.name).tobytes(), a.name


def _blob(arrays: list[channels.Array], pixels: int, version: int = channels.TABLE_VERSION):
    header = bytearray(channels.MAGIC) + struct.pack("<HHI", version, len(arrays), pixels)
    for a in arrays:
        codes = {"<f4": 1, "<f8": 2, "<u4": 3}
        header += (
            struct.pack("<B", len(a.name))
            + a.name.encode()
            + struct.pack("<BH", codes[a.dtype], a.components)
        )
    return bytes(header) + bytes(sum(a.bytes_per_pixel for a in arrays) * pixels)


def test_a_checkpoint_blob_the_table_cannot_read_is_refused_naming_why():
    ok = [channels.ARRAYS[n] for n in channels.STATS_ARRAYS]
    TileAccumulator.from_bytes(W, H, _blob(ok, W * H), 1, 1)  # well formed: loads
    with pytest.raises(ValueError, match="array depth_sum .* is not one of"):
        TileAccumulator.from_bytes(W, H, _blob([*ok, channels.Array("depth_sum", "<f4")], W * H),
                                   1, 1)  # fmt: skip
    with pytest.raises(ValueError, match="array rgb_sum .* is not one of"):
        TileAccumulator.from_bytes(W, H, _blob([channels.Array("rgb_sum", "<f4", 3)], W * H), 1, 1)
    with pytest.raises(ValueError, match="holds 6 pixels, the tile has 35"):
        TileAccumulator.from_bytes(W, H, _blob(ok, 6), 1, 1)
    with pytest.raises(ValueError, match="version 2 is newer than this server's"):
        TileAccumulator.from_bytes(W, H, _blob(ok, W * H, version=2), 1, 1)
    with pytest.raises(ValueError, match="has .* bytes, expected"):
        TileAccumulator.from_bytes(W, H, _blob(ok, W * H)[:-4], 1, 1)
    with pytest.raises(ValueError, match="malformed header"):
        TileAccumulator.from_bytes(W, H, channels.MAGIC + b"\x01", 1, 1)


def test_a_spill_slot_holds_the_tables_arrays(tmp_path):
    cache = TileCache(tmp_path, budget_bytes=1)
    acc = merged()
    want = {a.name: getattr(acc, a.name).copy() for a in channels.stored()}
    cache.register("j", acc, 8)
    assert acc.spill.home.slot_bytes == TileAccumulator.BYTES_PER_PIXEL * 8 * 8
    cache.register("j", merged(1), 8)  # evicts the first
    assert not acc.resident
    cache.use(acc)
    for name, values in want.items():
        assert getattr(acc, name).tobytes() == values.tobytes(), name


def _expected_channel(name: str, acc: TileAccumulator) -> np.ndarray:
    """Each EXR channel from the accumulator's arrays in numpy, per the table's row."""
    n = acc.samples
    window = min(n, channels.AOV_SAMPLES)
    rows = {
        "R": acc.rgb_sum[..., 0] / n, "G": acc.rgb_sum[..., 1] / n, "B": acc.rgb_sum[..., 2] / n,
        "variance.Y": acc.variance_of_mean(), "spp": np.full((H, W), float(n)),
        "error": acc.relative_error(), "A": acc.coverage_sum.astype(np.float64) / n,
    }  # fmt: skip
    for i, axis in enumerate("RGB"):
        rows[f"albedo.{axis}"] = acc.albedo_sum[..., i] / np.float32(window)
    for i, axis in enumerate("XYZ"):
        rows[f"normal.{axis}"] = acc.normal_sum[..., i] / np.float32(window)
    # First-sample rows: the first batch's values, as they were merged.
    if acc.depth is not None:
        rows["depth.Z"] = acc.depth
    if acc.position is not None:
        for i, axis in enumerate("XYZ"):
            rows[f"position.{axis}"] = acc.position[..., i]
    if acc.motion is not None:
        for i, axis in enumerate("XYZW"):
            rows[f"motion.{axis}"] = acc.motion[..., i]
    # Labels: the integers, exact in float32 below 2^24.
    if acc.instance_id is not None:
        rows["instance.id"] = acc.instance_id
    if acc.material_id is not None:
        rows["material.id"] = acc.material_id
    # The lobes: means over every sample, like the radiance.
    for lobe, *_ in channels.LOBES:
        values = getattr(acc, f"{lobe}_sum", None)
        if values is not None:
            for i, axis in enumerate("RGB"):
                rows[f"{lobe}.{axis}"] = values[..., i] / n
    # The light groups: a block of three a group, in the layout's order.
    for k, group in enumerate(acc.layout.groups):
        for i, axis in enumerate("RGB"):
            rows[f"light_group_{group}.{axis}"] = acc.light_groups_sum[..., 3 * k + i] / n
    if name.startswith("Crypto"):
        return _expected_crypto(name, acc)
    return rows[name].astype(np.float32)


# The document of the Cryptomatte names in these tests: nodes 0..4 (labels 1..5), node 1 the
# parent of nodes 2 and 3 (one asset), node 4 unnamed; materials 0..4, material 3 unnamed.
CRYPTO_DOC = {
    "nodes": [{"name": "a"}, {"name": "b", "children": [2, 3]}, {"name": "c"}, {"name": "d"},
              {}],
    "materials": [{"name": "m0"}, {"name": "m1"}, {"name": "m2"}, {}, {"name": "m4"}],
}  # fmt: skip


def _murmur_id(name: str) -> float:
    """The Cryptomatte specification's uint32_to_float32 of MurmurHash3_32 (mmh3), written out
    as its sample code does: the exponent clamped to 1..254."""
    import mmh3

    h = mmh3.hash(name, 0, signed=False)
    exponent = min(max((h >> 23) & 255, 1), 254)
    bits = (h & (1 << 31)) | (exponent << 23) | (h & ((1 << 23) - 1))
    return struct.unpack("<f", struct.pack("<I", bits))[0]


def _expected_crypto(name: str, acc: TileAccumulator) -> np.ndarray:
    """A Cryptomatte channel per pixel in plain Python: the row's pairs (CryptoAsset: summed by
    root node), ranked by coverage, each label's name hashed."""
    kind, level, channel = name[:-4], int(name[-4:-2]), name[-1]
    rank = 2 * level + (channel in "BA")
    nodes, materials = CRYPTO_DOC["nodes"], CRYPTO_DOC["materials"]
    node_names = [n.get("name", f"nodes[{i}]") for i, n in enumerate(nodes)]
    root = {1: 1, 2: 1, 3: 1}  # node -> root node (nodes 2 and 3 are node 1's children)
    pairs = acc.crypto_material if kind == "CryptoMaterial" else acc.crypto_object
    out = np.zeros((H, W), np.float32)
    for j in range(H):
        for i in range(W):
            counts: dict[int, int] = {}  # by index (of the root node, for CryptoAsset)
            for r in range(channels.CRYPTO_RANKS):
                label, count = (int(v) for v in pairs[j, i, 2 * r : 2 * r + 2])
                if label:
                    index = root.get(label - 1, label - 1) if kind == "CryptoAsset" else label - 1
                    counts[index] = counts.get(index, 0) + count
            # Ranked by count, ties by index (the farm's order).
            ranked = sorted(counts.items(), key=lambda kv: (-kv[1], kv[0]))
            if rank < len(ranked):
                index, count = ranked[rank]
                key = (
                    materials[index].get("name", f"materials[{index}]")
                    if kind == "CryptoMaterial" else node_names[index]
                )  # fmt: skip
                out[j, i] = _murmur_id(key) if channel in "RB" else count / acc.samples
    return out


def test_the_exr_has_the_tables_channels_in_its_order_with_their_values(tmp_path):
    acc = merged()
    band = [(Rect(0, 0, W, H), acc)]
    path = tmp_path / "a.exr"
    writer = ImageWriter(str(path), "exr", W, H)
    writer.write_band(H, band, True)
    writer.close()
    import OpenImageIO as oiio

    # (OpenEXR stores channels by name, and OpenImageIO reads R, G, B, A first: the names are
    # compared as a set, and each one's values below tie the writer's order to the table's.)
    names = oiio.ImageInput.open(str(path)).spec().channelnames
    assert sorted(names) == sorted(channels.exr_channels())
    values = read_exr(str(path))
    for name in channels.exr_channels():
        np.testing.assert_array_equal(values[name], _expected_channel(name, acc), err_msg=name)
    # With settings.denoise, the denoised layer's channels follow.
    path = tmp_path / "d.exr"
    writer = ImageWriter(str(path), "exr", W, H, denoised=np.zeros((H, W, 3), np.float32))
    writer.write_band(H, band, True)
    writer.close()
    names = oiio.ImageInput.open(str(path)).spec().channelnames
    assert sorted(names) == sorted(channels.exr_channels(denoise=True))
    # A job with every output: the layout's channels, each with its values.
    acc = merged(layout=EVERY)
    path = tmp_path / "o.exr"
    crypto = cryptomatte.Names.of(CRYPTO_DOC)
    writer = ImageWriter(str(path), "exr", W, H, layout=EVERY, crypto=crypto)
    writer.write_band(H, [(Rect(0, 0, W, H), acc)], True)
    writer.close()
    names = oiio.ImageInput.open(str(path)).spec().channelnames
    assert sorted(names) == sorted(EVERY.exr_channels())
    assert {"depth.Z", "position.X", "position.Y", "position.Z"} <= set(names)
    values = read_exr(str(path))
    for name in EVERY.exr_channels():
        np.testing.assert_array_equal(values[name], _expected_channel(name, acc), err_msg=name)


@pytest.mark.parametrize("layer", [n for n in channels.layers() if n != "denoised"])
def test_every_layer_has_a_png(tmp_path, layer):
    acc = merged(layout=EVERY)
    band = [(Rect(0, 0, W, H), acc)]
    top = images.layer_maximum(layer, band) if layer in images.SCALED_LAYERS else 1.0
    path = tmp_path / f"{layer}.png"
    names = images.arrays_needed("png", layer, EVERY)
    assert set(names) <= set(EVERY.array_names())
    writer = ImageWriter(str(path), "png", W, H, layer, top=top, layout=EVERY)
    writer.write_band(H, band, True)
    writer.close()
    assert path.stat().st_size > 0


def test_the_layers_of_images_the_cli_and_the_rest_api_are_the_tables():
    layers = channels.layers()
    assert images.LAYERS == tuple(layers)
    assert EXR_LAYER_CHANNELS == {name: layer.exr for name, layer in layers.items()}
    assert set(images.GREY_LAYERS) == {"variance", "spp", "error", "depth"}
    get = next(a for a in build_parser()._subparsers._group_actions[0].choices["get"]._actions
               if "--layer" in a.option_strings)  # fmt: skip
    assert all(name in get.help for name in layers)
    # The REST API's `layer` (web/openapi.json, whence the dashboard's LayerName type: its
    # switch must name every layer and no other, or `make test-web` fails to type check).
    document = json.loads((ROOT / "web" / "openapi.json").read_text())
    for path in ("/api/v1/jobs/{job_id}/image.{fmt}",
                 "/api/v1/jobs/{job_id}/frames/{frame}/image.{fmt}"):  # fmt: skip
        params = document["paths"][path]["get"]["parameters"]
        layer = next(p for p in params if p["name"] == "layer")
        assert layer["schema"]["enum"] == list(layers), f"stale {path}: run `make openapi`"
    viewer = (ROOT / "web" / "src" / "pages" / "viewer.ts").read_text()
    assert "Record<LayerName," in viewer


def test_usage_md_has_the_generated_layers_table():
    """docs/usage.md's outputs table is layers_markdown(): regenerate it with `make channels`."""
    text = (ROOT / "docs" / "usage.md").read_text()
    found = re.search(
        r"<!-- layers table: generated.*?-->\n(.*?)<!-- end of layers table -->", text, re.S
    )
    assert found, "docs/usage.md has no generated layers table"
    assert found.group(1) == channels.layers_markdown(), "stale: run `make channels`"


def test_the_table_refuses_what_would_break_the_merge():
    # Windows end on a batch boundary of the schedule; names are unique.
    for c in channels.CHANNELS:
        assert c.window in (0, 1, 2, 4, 8, 16, 32, 64), c.name
    exr = channels.exr_channels(denoise=True)
    assert len(exr) == len(set(exr))
    assert channels.exr_channels()[:3] == ("R", "G", "B") and "A" in channels.exr_channels()


def test_the_workers_header_is_the_generated_one():
    """worker/src/render/channel_table.h is cpp_header(): regenerate it with `make channels`."""
    header = ROOT / "worker" / "src" / "render" / "channel_table.h"
    assert header.read_text() == channels.cpp_header(), "stale: run `make channels`"
    # Every row a result carries is in it, by name, with its components and window.
    types = {"<f4": "F32", "<u4": "U32"}
    for c in channels.WIRE:
        ranked = "true" if c.accumulate is Accumulate.RANKED else "false"
        per_group = "true" if c.name == "light_groups" else "false"
        row = (
            f'"{c.name}", {c.wire_components}, Type::{types[c.wire_type]}, {c.window}, {ranked}, '
            f"{per_group}}}"
        )
        assert row in header.read_text()


def _result(rows, start: int = 0, **change):
    """A TileResult of a 4 x 2 rect carrying `rows` (name -> values) as ChannelBlocks."""
    from renderfarm.v1 import workers_pb2

    msg = workers_pb2.TileResult(
        task_id="t", job_id="j", sample_start=start, sample_count=4,
        rect=workers_pb2.TileRect(x0=0, y0=0, width=4, height=2),
        table_version=change.pop("table_version", channels.TABLE_VERSION),
    )  # fmt: skip
    for name, values in rows.items():
        row = channels.BY_NAME.get(name)
        dtype = row.wire_type if row else "<f4"
        block = msg.channels.add(name=name, type={"<f4": 1, "<u4": 3}[dtype],
                                 components=row.wire_components if row else 1)  # fmt: skip
        block.data = np.asarray(values, dtype).tobytes()
    for name, fields in change.items():
        block = next(b for b in msg.channels if b.name == name)
        for key, value in fields.items():
            setattr(block, key, value)
    return msg


def _values(name: str, pixels: int = 8) -> np.ndarray:
    row = channels.BY_NAME[name]
    return np.arange(pixels * row.wire_components, dtype=row.wire_type) + len(name)


def test_results_decode_by_their_blocks_and_the_table_refuses_the_rest():
    from renderfarm.api.grpc_decode import decode_result

    every = {c.name: _values(c.name) for c in channels.wire_rows_for(0)}
    r = decode_result(_result(every))
    for c in channels.wire_rows_for(0):
        assert np.array_equal(getattr(r, c.wire), every[c.name]), c.name
    # Past the window of albedo and normal, a result carries the others only.
    later = {c.name: _values(c.name) for c in channels.wire_rows_for(16)}
    assert set(later) == {"rgb", "luminance", "coverage"}
    r = decode_result(_result(later, start=16))
    assert r.albedo_sum is None and r.normal_sum is None
    refusals = [
        (_result({**every, "bogus": np.zeros(8)}), "channel 'bogus' is not one a result carries"),
        (_result({k: v for k, v in every.items() if k != "coverage"}), "coverage: missing"),
        (_result(every, albedo={"type": 2}), "channel albedo: type 2 x 3, expected 1 x 3"),
        (_result(every, rgb={"components": 4}), "channel rgb: type 1 x 4, expected 1 x 3"),
        (_result(every, normal={"data": b"\0" * 95}), "channel normal: 95 bytes, expected 96"),
        (_result(every, table_version=2), "channel table version 2, this server's is 1"),
    ]
    for msg, reason in refusals:
        with pytest.raises(ValueError, match=re.escape(reason)):
            decode_result(msg)
    twice = _result(every)
    twice.channels.add(name="rgb", type=1, components=3, data=every["rgb"].tobytes())
    with pytest.raises(ValueError, match="channel rgb: sent twice"):
        decode_result(twice)


# ------------------------------------------------------------- a job's layout (settings.aovs)
def test_aovs_name_the_outputs_a_job_turns_on():
    from renderfarm.domain.jobspec import parse_settings
    from renderfarm.errors import SettingsError

    assert parse_settings({"aovs": ["position", "depth"]}).aovs == "depth,position"
    assert parse_settings({"aovs": " Depth, depth "}).aovs == "depth"
    assert parse_settings({}).aovs == ""
    refusals = [
        (
            ["depth", "zz"],
            "unknown output 'zz'; known: depth, position, motion, ids, cryptomatte, lobes",
        ),
        (7, "must be a list of names"),
        ([1], "must be a list of names"),
    ]
    for bad, said in refusals:
        with pytest.raises(SettingsError, match=re.escape(said)) as e:
            parse_settings({"aovs": bad})
        assert e.value.field == "settings.aovs"
    # The lobes split what a first hit scatters: the ao integrator scatters nothing.
    for split in ("lobes", "light_groups"):
        with pytest.raises(SettingsError, match=f"names {split}, .* ao integrator") as e:
            parse_settings({"aovs": [split], "integrator": "ao"})
        assert e.value.field == "settings.aovs"
    assert parse_settings({"aovs": ["lobes"], "integrator": "direct"}).aovs == "lobes"
    layout = channels.job_layout(parse_settings({"aovs": "position"}))
    assert "position" in layout.names and "depth" not in layout.names
    assert channels.job_layout(parse_settings({})) == channels.DEFAULT
    # One name may turn on several rows: `ids` the instance and the material labels.
    layout = channels.job_layout(parse_settings({"aovs": ["ids"]}))
    assert {"instance", "material"} <= set(layout.names) and "depth" not in layout.names
    assert set(layout.layers()) >= {"instance", "material"}
    assert "denoised" in channels.layout_for((), denoise=True).layers()


def test_outputs_add_their_arrays_to_the_memory_estimate_and_the_limit_counts_them():
    from renderfarm.domain.jobspec import Limits, parse_settings
    from renderfarm.errors import SettingsError

    acc = TileAccumulator(W, H, layout=EVERY)
    assert acc.depth.dtype == np.float32 and acc.depth.shape == (H, W)
    assert acc.position.dtype == np.float32 and acc.position.shape == (H, W, 3)
    assert acc.instance_id.dtype == np.uint32 and acc.material_id.shape == (H, W)
    assert acc.crypto_object.dtype == np.uint32 and acc.crypto_object.shape == (H, W, 12)
    # 76 bytes of the rows every job has, a float32 depth, three float32 position values, four
    # float32 motion values, two uint32 labels and two Cryptomatte rows of six (label, count)
    # uint32 pairs, eight lobes of three float64 sums and one light group's three (EVERY's:
    # the environment's).
    assert acc.diffuse_direct_sum.dtype == np.float64
    assert acc.nbytes == (76 + 4 + 12 + 16 + 4 + 4 + 2 * 48 + 8 * 24 + 24) * W * H
    assert TileAccumulator(W, H).depth is None
    assert jobspec.job_memory_bytes(64, 64, 64, "depth,position") == 92 * 64 * 64 + 4096
    assert jobspec.job_memory_bytes(64, 64, 64, "depth") == 80 * 64 * 64 + 4096
    assert jobspec.job_memory_bytes(64, 64, 64, "ids") == 84 * 64 * 64 + 4096
    assert jobspec.job_memory_bytes(64, 64, 64, "motion") == 92 * 64 * 64 + 4096
    assert jobspec.job_memory_bytes(64, 64, 64, "cryptomatte") == 172 * 64 * 64 + 4096
    assert jobspec.job_memory_bytes(64, 64, 64, "lobes") == (76 + 192) * 64 * 64 + 4096
    # 1024 x 1024 in 256 tiles: 80.7 MB without outputs, 97.5 MB with both; the limit between.
    limits = Limits(max_job_memory_bytes=85 * 2**20)
    parse_settings({"width": 1024, "height": 1024}, limits)
    with pytest.raises(SettingsError, match="92 bytes a pixel") as e:
        parse_settings({"width": 1024, "height": 1024, "aovs": "depth,position"}, limits)
    assert e.value.field == "settings.width"


def test_first_sample_rows_keep_the_first_batchs_values_only():
    """Depth and position are the first sample's (window 1): a later batch that carried them
    would not change them."""
    rng = np.random.default_rng(5)
    acc = TileAccumulator(W, H, layout=EVERY)
    first = {"depth": rng.random((H, W)).astype(np.float32) + 1,
             "position": rng.standard_normal((H, W, 3)).astype(np.float32)}  # fmt: skip
    ones = np.ones((H, W, 3), np.float32)
    acc.merge_batch(ones, np.zeros((H, W), np.float32), 1, extra=first)
    later = {k: v + 5 for k, v in first.items()}
    acc.merge_batch(ones, np.zeros((H, W), np.float32), 1, extra=later)
    assert np.array_equal(acc.depth, first["depth"])
    assert np.array_equal(acc.position, first["position"])
    assert np.array_equal(acc.mean_of(channels.BY_NAME["depth"]), first["depth"])


def test_checkpoints_of_a_job_with_outputs_round_trip_and_refuse_another_layout():
    acc = merged(layout=EVERY)
    aovs = acc.aovs_to_bytes()
    _, arrays, _, _ = channels.read_header(aovs, "test")
    assert [a.name for a in arrays] == [
        "albedo_sum", "normal_sum", "depth", "position", "motion", "instance_id", "material_id",
    ]  # fmt: skip
    assert [a.dtype for a in arrays][-2:] == ["<u4", "<u4"]
    back = TileAccumulator.from_bytes(W, H, acc.to_bytes(), acc.samples, acc.batches,
                                      aovs=aovs, layout=EVERY)  # fmt: skip
    for name in EVERY.array_names():
        assert getattr(back, name).tobytes() == getattr(acc, name).tobytes(), name
    with pytest.raises(ValueError, match="array [a-z_]+ belongs to no row the job's settings"):
        TileAccumulator.from_bytes(W, H, acc.to_bytes(), acc.samples, acc.batches, aovs=aovs)


def test_a_spill_slot_of_a_job_with_outputs_holds_them(tmp_path):
    cache = TileCache(tmp_path, budget_bytes=1)
    acc = merged(layout=EVERY)
    want = {name: getattr(acc, name).copy() for name in EVERY.array_names()}
    cache.register("j", acc, 8)
    assert acc.spill.home.slot_bytes == (212 + 8 * 24 + 24) * 8 * 8
    cache.register("j", merged(1, layout=EVERY), 8)  # evicts the first
    assert not acc.resident
    ref = acc.snapshot(("depth", "position"))
    depth, position = TileAccumulator.snapshot_arrays(ref)
    assert depth.tobytes() == want["depth"].tobytes()
    assert position.tobytes() == want["position"].tobytes()
    cache.use(acc)
    for name, values in want.items():
        assert getattr(acc, name).tobytes() == values.tobytes(), name


def test_tasks_name_the_jobs_rows_and_results_must_carry_them():
    from renderfarm.api.grpc_api import _task_channels_for
    from renderfarm.api.grpc_decode import decode_result
    from renderfarm.domain.jobspec import JobSettings
    from renderfarm.domain.scheduler import Scheduler

    settings = JobSettings(width=4, height=2, tile_size=8, max_spp=4, aovs="depth,position")
    assert _task_channels_for(settings, 0) == (
        "rgb", "luminance", "albedo", "normal", "coverage", "depth", "position",
    )  # fmt: skip
    assert _task_channels_for(settings, 1) == ("rgb", "luminance", "albedo", "normal", "coverage")
    assert "depth" not in _task_channels_for(JobSettings(), 0)
    every = {c.name: _values(c.name) for c in EVERY.wire_rows_for(0)}
    r = decode_result(_result(every))
    assert set(r.extra) == {
        "depth", "position", "motion", "instance", "material", "crypto_object",
        "crypto_material", *(lobe for lobe, *_ in channels.LOBES), "light_groups",
    }  # fmt: skip
    assert r.extra["instance"].dtype == np.dtype("<u4")
    assert np.array_equal(r.extra["position"], every["position"])
    # The scheduler merges them, and refuses a first batch without one (or with a NaN).
    sched = Scheduler()
    sched.add_job("j", settings, "scene")
    sched.add_worker("w", 1)
    (lease,) = sched.assign("w")
    assert lease.sample_start == 0
    nan = np.full(8, np.nan, "<f4")
    refused = [
        ({"depth": r.extra["depth"]}, "channel position missing"),
        ({**r.extra, "depth": nan}, "channel depth: non-finite values"),
    ]
    for extra, outcome in refused:
        fields = {**r.__dict__, "job_id": "j", "tile_index": lease.tile_index,
                  "batch_index": lease.batch_index, "sample_count": lease.sample_count,
                  "extra": extra}  # fmt: skip
        assert sched.complete(lease.task_id, type(r)(**fields)) == f"mismatch: {outcome}"
        (lease,) = sched.assign("w")
    fields = {**r.__dict__, "job_id": "j", "tile_index": lease.tile_index,
              "batch_index": lease.batch_index, "sample_count": lease.sample_count}  # fmt: skip
    assert sched.complete(lease.task_id, type(r)(**fields)) == "merged"
    acc = sched.jobs["j"].tiles[0].acc
    assert np.array_equal(acc.depth.reshape(-1), every["depth"])
    assert np.array_equal(acc.position.reshape(-1), every["position"])


GROUPS = ("key", "fill", "environment")


def test_a_job_of_light_groups_has_a_block_and_a_layer_per_group(tmp_path):
    """The light_groups row is resolved per job: three float64 components a group in its
    arrays, its results and its checkpoints, and one EXR layer a group, in the job's order."""
    from renderfarm.api.grpc_decode import decode_result
    from renderfarm.domain.jobspec import JobSettings, job_memory_bytes

    layout = channels.layout_for("light_groups", groups=GROUPS)
    assert layout.groups == GROUPS
    (row,) = [c for c in layout.rows if c.name == "light_groups"]
    assert row.wire_components == 9 and row.store[0].components == 9
    assert [x.name for x in row.layers] == ["light_group.key", "light_group.fill",
                                            "light_group.environment"]  # fmt: skip
    assert layout.exr_channels()[-9:] == tuple(
        f"light_group_{g}.{c}" for g in GROUPS for c in "RGB"
    )
    assert job_memory_bytes(64, 64, 64, "light_groups", GROUPS) == (76 + 72) * 64 * 64 + 4096
    settings = JobSettings(aovs="light_groups", light_groups='{"key":[1],"fill":[2,4],'
                           '"environment":[]}')  # fmt: skip
    assert channels.job_layout(settings) == layout
    # Checkpoints name the array with its 9 components and read back into the job's layout.
    acc = TileAccumulator(W, H, layout=layout)
    values = np.arange(W * H * 9, dtype=np.float32).reshape(H, W, 9)
    acc.merge_batch(np.ones((H, W, 3), np.float32), np.zeros((H, W), np.float32), 1,
                    extra={"light_groups": values})  # fmt: skip
    blob = acc.to_bytes()
    _, arrays, _, _ = channels.read_header(blob, "test")
    assert channels.Array("light_groups_sum", "<f8", 9) in arrays
    back = TileAccumulator.from_bytes(W, H, blob, acc.samples, acc.batches, layout=layout)
    assert np.array_equal(back.light_groups_sum, values.astype(np.float64))
    other = channels.layout_for("light_groups", groups=("key", "environment"))
    with pytest.raises(ValueError, match="light_groups_sum .* is not one of"):
        TileAccumulator.from_bytes(W, H, blob, acc.samples, acc.batches, layout=other)
    # A PNG of one group shows its block.
    tile = TileAccumulator(W, H, layout=layout)
    tile.merge_batch(np.ones((H, W, 3), np.float32), np.zeros((H, W), np.float32), 1,
                     extra={"light_groups": values})  # fmt: skip
    from renderfarm.infra.images import _display_tile

    fill = _display_tile("light_group.fill", tile, 1.0, H, W)
    assert np.array_equal(fill, values[..., 3:6].astype(np.float64))
    # On the wire: a multiple of three components a pixel, checked against the job's groups
    # by the scheduler; anything else is refused by the decoder.
    every = {c.name: _values(c.name) for c in channels.DEFAULT.wire_rows_for(0)}
    nine = {**every, "light_groups": np.zeros(8 * 9, "<f4")}
    r = decode_result(_result(nine, light_groups={"components": 9}))
    assert r.extra["light_groups"].size == 8 * 9
    for components in (4, 0, 3 * 33):
        bad = _result(nine, light_groups={"components": components})
        with pytest.raises(ValueError, match="channel light_groups: type 1 x"):
            decode_result(bad)
