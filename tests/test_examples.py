"""The example scenes and `make demo SCENE=...`.

examples/make_studio.py (a still life: tiled floor with colour, normal and metallic-roughness
textures, gold, tinted glass, alpha-masked leaves, clearcoat, an area and a spot light) must be
deterministic, load in the worker with no warning, and render; its leaves must be cut out by
their texture's alpha. scripts/demo.sh must resolve SCENE (a short name or a path) and refuse a
bad one with one line and exit status 2 before it starts anything.
"""

from __future__ import annotations

import importlib.util
import json
import shutil
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from renderfarm.infra.images import read_exr

ROOT = Path(__file__).resolve().parents[1]
GENERATOR = ROOT / "examples" / "make_studio.py"
DEMO = ROOT / "scripts" / "demo.sh"


def load_generator():
    spec = importlib.util.spec_from_file_location("make_studio", GENERATOR)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def read_glb(path: Path) -> tuple[dict, bytes]:
    """The JSON and BIN chunks of a GLB file (glTF 2.0, 4.4)."""
    data = path.read_bytes()
    magic, version, total = struct.unpack_from("<4sII", data)
    assert (magic, version, total) == (b"glTF", 2, len(data))
    json_len, json_type = struct.unpack_from("<I4s", data, 12)
    assert json_type == b"JSON"
    doc = json.loads(data[20 : 20 + json_len])
    bin_len, bin_type = struct.unpack_from("<I4s", data, 20 + json_len)
    assert bin_type == b"BIN\0"
    start = 28 + json_len
    return doc, data[start : start + bin_len]


def write_glb(path: Path, doc: dict, binary: bytes) -> None:
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    total = 12 + 8 + len(text) + 8 + len(binary)
    path.write_bytes(
        struct.pack("<4sII", b"glTF", 2, total)
        + struct.pack("<I4s", len(text), b"JSON")
        + text
        + struct.pack("<I4s", len(binary), b"BIN\0")
        + binary
    )


def accessor(doc: dict, binary: bytes, index: int) -> np.ndarray:
    a = doc["accessors"][index]
    view = doc["bufferViews"][a["bufferView"]]
    dtype = {5126: "<f4", 5123: "<u2", 5125: "<u4"}[a["componentType"]]
    width = {"SCALAR": 1, "VEC2": 2, "VEC3": 3}[a["type"]]
    assert "byteStride" not in view
    start = view.get("byteOffset", 0) + a.get("byteOffset", 0)
    values = np.frombuffer(binary, dtype, a["count"] * width, start)
    return values.reshape(a["count"], width) if width > 1 else values


def image(doc: dict, binary: bytes, index: int, where: Path) -> np.ndarray:
    """An embedded image decoded by OpenImageIO (not by the generator's code): uint8 H x W x C."""
    import OpenImageIO as oiio

    view = doc["bufferViews"][doc["images"][index]["bufferView"]]
    path = where / f"image{index}.png"
    path.write_bytes(binary[view["byteOffset"] : view["byteOffset"] + view["byteLength"]])
    pixels = oiio.ImageBuf(str(path)).get_pixels(oiio.UINT8)
    assert pixels is not None and pixels.size, f"OpenImageIO could not read image {index}"
    return pixels


@pytest.fixture(scope="module")
def studio(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("studio") / "studio.glb"
    subprocess.run([sys.executable, str(GENERATOR), "-o", str(out)], check=True, timeout=300)
    return out


# ---------------------------------------------------------------------------- the generator


def test_the_generator_writes_the_same_bytes_twice(studio, tmp_path):
    again = tmp_path / "again.glb"
    subprocess.run([sys.executable, str(GENERATOR), "-o", str(again)], check=True, timeout=300)
    assert again.read_bytes() == studio.read_bytes()


def test_the_scene_holds_what_it_is_meant_to_show(studio, tmp_path):
    doc, binary = read_glb(studio)
    materials = {m["name"]: m for m in doc["materials"]}
    # Tiles: base colour, normal and metallic-roughness textures.
    tiles = materials["glazed tiles"]
    pbr = tiles["pbrMetallicRoughness"]
    assert {"baseColorTexture", "metallicRoughnessTexture"} <= pbr.keys()
    assert "normalTexture" in tiles
    # The metallic-roughness map: rough grout lines (G, roughness) between glossy tiles, no
    # metal (B). Read by OpenImageIO, so this checks the PNG encoding as well.
    mr = image(doc, binary, doc["textures"][pbr["metallicRoughnessTexture"]["index"]]["source"],
               tmp_path)  # fmt: skip
    assert mr.shape == (512, 512, 3)
    roughness = mr[:, :, 1] / 255.0
    assert (mr[:, :, 2] == 0).all()
    assert 0.005 < (roughness > 0.7).mean() < 0.1  # the thin lines
    assert (roughness < 0.3).mean() > 0.85
    normal = image(doc, binary, doc["textures"][tiles["normalTexture"]["index"]]["source"],
                   tmp_path) / 127.5 - 1.0  # fmt: skip
    lengths = np.linalg.norm(normal, axis=-1)
    assert np.allclose(lengths, 1.0, atol=0.02) and (normal[:, :, 2] > 0).all()
    assert (normal[:, :, 2] < 0.95).mean() > 0.01  # the tiles' bevels slope
    # Gold: a metal.
    gold = materials["gold"]["pbrMetallicRoughness"]
    assert gold["metallicFactor"] == 1.0 and gold["baseColorFactor"][:3] == [1.0, 0.766, 0.336]
    # Glass: transmission, ior and a volume that absorbs (not thin-walled).
    glass = materials["tinted glass"]["extensions"]
    assert glass["KHR_materials_transmission"]["transmissionFactor"] == 1.0
    assert glass["KHR_materials_ior"]["ior"] == 1.5
    volume = glass["KHR_materials_volume"]
    assert volume["thicknessFactor"] > 0 and volume["attenuationDistance"] > 0
    assert max(volume["attenuationColor"]) < 1.0
    # Leaves: alpha-masked, two-sided, an RGBA texture whose alpha is 0 or 1.
    leaf = materials["leaf"]
    assert (leaf["alphaMode"], leaf["alphaCutoff"], leaf["doubleSided"]) == ("MASK", 0.5, True)
    rgba = image(doc, binary,
                 doc["textures"][leaf["pbrMetallicRoughness"]["baseColorTexture"]["index"]]["source"],
                 tmp_path)  # fmt: skip
    assert rgba.shape[2] == 4 and set(np.unique(rgba[:, :, 3])) == {0, 255}
    assert 0.3 < (rgba[:, :, 3] == 255).mean() < 0.8
    # Clearcoat, an emitter, a spot light, a camera.
    assert materials["red lacquer"]["extensions"]["KHR_materials_clearcoat"]["clearcoatFactor"] > 0
    assert materials["soft box"]["extensions"]["KHR_materials_emissive_strength"]
    lights = doc["extensions"]["KHR_lights_punctual"]["lights"]
    assert [light["type"] for light in lights] == ["spot"]
    assert doc["cameras"][0]["type"] == "perspective"


# ---------------------------------------------------------------------------- the worker


def inspect(worker_binary: str, scene: Path) -> dict:
    run = subprocess.run([worker_binary, "inspect", "--json", str(scene)], capture_output=True,
                         text=True, timeout=120)  # fmt: skip
    assert run.returncode == 0, run.stderr
    return json.loads(run.stdout)


def test_the_worker_loads_it_with_no_warning(worker_binary, studio):
    report = inspect(worker_binary, studio)
    assert report["ok"] and report["warnings"] == [], report
    # Every extension the scene uses is one the renderer implements (an unknown one would be a
    # warning above); these are the ones the still life is about.
    assert set(report["extensions_used"]) == {
        "KHR_lights_punctual", "KHR_materials_clearcoat", "KHR_materials_emissive_strength",
        "KHR_materials_ior", "KHR_materials_transmission", "KHR_materials_volume",
    }  # fmt: skip
    # Four textures: the tiles' three 512 x 512 maps and the 128 x 256 leaf.
    assert report["textures"] == 4
    assert report["texture_pixels"] == 3 * 512 * 512 + 128 * 256
    # The soft box's two triangles and the spot light.
    assert report["emissive_triangles"] == 3
    assert report["camera"] and report["materials"] == 10
    assert 10_000 < report["triangles"] < 200_000


# -------------------------------------------------------------- the leaves' cut-out, by rays


def camera_rays(doc: dict, width: int, height: int, offsets) -> tuple[np.ndarray, np.ndarray]:
    """Origins and directions of rays through points of every pixel: the pinhole camera as
    glTF defines it (looking down the node's -Z, +Y up, yfov vertical, the image's aspect), raster
    y down; offsets are (dx, dy) inside the pixel. Directions: (height, width, len(offsets), 3)."""
    node = next(n for n in doc["nodes"] if "camera" in n)
    x, y, z, w = node["rotation"]
    rot = np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])  # fmt: skip
    half_h = np.tan(doc["cameras"][node["camera"]]["perspective"]["yfov"] / 2)
    half_w = half_h * width / height
    dirs = np.empty((height, width, len(offsets), 3))
    px, py = np.meshgrid(np.arange(width), np.arange(height))
    for k, (dx, dy) in enumerate(offsets):
        sx = (2 * (px + dx) / width - 1) * half_w
        sy = (1 - 2 * (py + dy) / height) * half_h
        local = np.stack([sx, sy, -np.ones_like(sx)], axis=-1)
        dirs[:, :, k] = local @ rot.T
    dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    return np.array(node["translation"]), dirs


def hits(origin: np.ndarray, dirs: np.ndarray, tris: np.ndarray):
    """Every ray against every triangle (Moeller-Trumbore): t (inf where missed), u, v."""
    p0, e1, e2 = tris[:, 0], tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]
    pvec = np.cross(dirs[:, None, :], e2[None])
    det = np.einsum("tk,rtk->rt", e1, pvec)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / det
        s = origin - p0
        u = np.einsum("tk,rtk->rt", s, pvec) * inv
        q = np.cross(s, e1)
        v = (dirs @ q.T) * inv
        t = (q * e2).sum(-1)[None] * inv
    ok = (np.abs(det) > 1e-12) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-6)
    return np.where(ok, t, np.inf), u, v


def nearest_other(origin, dirs, doc, binary, skip) -> tuple[np.ndarray, np.ndarray]:
    """Distance to, and name of, the nearest hit of each ray on the meshes not in skip."""
    best = np.full(len(dirs), np.inf)
    name = np.full(len(dirs), "", dtype=object)
    for node in doc["nodes"]:
        if "mesh" not in node or node["name"] in skip:
            continue
        prim = doc["meshes"][node["mesh"]]["primitives"][0]
        pos = accessor(doc, binary, prim["attributes"]["POSITION"]).astype(float)
        tris = pos[accessor(doc, binary, prim["indices"]).reshape(-1, 3)]
        lo, hi = pos.min(0), pos.max(0)
        with np.errstate(divide="ignore", invalid="ignore"):  # the slab test first
            t0, t1 = (lo - origin) / dirs, (hi - origin) / dirs
        near = np.nanmax(np.minimum(t0, t1), axis=1)
        far = np.nanmin(np.maximum(t0, t1), axis=1)
        candidates = np.flatnonzero((near <= far) & (far > 0))
        for chunk in np.array_split(candidates, max(1, len(candidates) // 64)):
            if len(chunk) == 0:
                continue
            t = hits(origin, dirs[chunk], tris)[0].min(axis=1)
            closer = t < best[chunk]
            best[chunk[closer]] = t[closer]
            name[chunk[closer]] = node["name"]
    return best, name


def classify_leaf_pixels(doc, binary, where: Path, width: int, height: int):
    """Pixels whose every sample point sees, on a leaf card first, (a) texels of alpha 0 and
    then a bright non-leaf surface (the wall, the pot, the floor): "through"; (b) texels of
    alpha 1: "solid". Returns two boolean images."""
    offsets = [(0.5, 0.5), (0.1, 0.1), (0.9, 0.1), (0.1, 0.9), (0.9, 0.9)]
    origin, dirs = camera_rays(doc, width, height, offsets)
    flat = dirs.reshape(-1, 3)
    leaf_node = next(n for n in doc["nodes"] if n.get("name") == "leaves")
    prim = doc["meshes"][leaf_node["mesh"]]["primitives"][0]
    assert doc["materials"][prim["material"]]["alphaMode"] == "MASK"
    pos = accessor(doc, binary, prim["attributes"]["POSITION"]).astype(float)
    uv = accessor(doc, binary, prim["attributes"]["TEXCOORD_0"]).astype(float)
    index = accessor(doc, binary, prim["indices"]).reshape(-1, 3)
    texture = doc["materials"][prim["material"]]["pbrMetallicRoughness"]["baseColorTexture"]
    alpha = image(doc, binary, doc["textures"][texture["index"]]["source"], where)[:, :, 3]
    th, tw = alpha.shape
    parts = [hits(origin, flat[i : i + 1024], pos[index]) for i in range(0, len(flat), 1024)]
    t, u, v = (np.concatenate([part[k] for part in parts]) for k in range(3))
    # Each ray's leaf hits in order; the alpha class of each (0: clear, 1: solid, 2: an edge,
    # where the 2 x 2 texels bilinear filtering reads are not all alike).
    order = np.argsort(t, axis=1)
    t_sorted = np.take_along_axis(t, order, axis=1)
    other_t, other_name = nearest_other(origin, flat, doc, binary, skip={"leaves"})

    def texel_class(ray: int, hit: int) -> int:
        tri = index[order[ray, hit]]
        b1, b2 = u[ray, order[ray, hit]], v[ray, order[ray, hit]]
        s, r = (1 - b1 - b2) * uv[tri[0]] + b1 * uv[tri[1]] + b2 * uv[tri[2]]
        x, y = s * tw - 0.5, r * th - 0.5
        x0, y0 = int(np.floor(x)), int(np.floor(y))
        block = alpha[np.clip([y0, y0 + 1], 0, th - 1)][:, np.clip([x0, x0 + 1], 0, tw - 1)]
        return 0 if (block == 0).all() else 1 if (block == 255).all() else 2

    through = np.zeros(len(flat), bool)
    solid = np.zeros(len(flat), bool)
    for ray in range(len(flat)):
        if not t_sorted[ray, 0] < other_t[ray]:
            continue  # no leaf in front
        classes = [
            texel_class(ray, h) for h in range(t.shape[1]) if t_sorted[ray, h] < other_t[ray]
        ]
        if classes[0] == 1:
            solid[ray] = True
        elif all(c == 0 for c in classes) and other_name[ray] in ("wall", "pot", "floor"):
            through[ray] = True
    k = len(offsets)
    return (through.reshape(height, width, k).all(-1), solid.reshape(height, width, k).all(-1))


def render(worker_binary: str, scene: Path, out: Path, width: int, height: int, spp: int):
    args = [worker_binary, "render", str(scene), "-o", str(out), "--spp", str(spp), "--width",
            str(width), "--height", str(height), "--threads", "2", "--seed", "3"]  # fmt: skip
    subprocess.run(args, check=True, capture_output=True, timeout=600)
    ch = read_exr(str(out))
    return np.stack([ch["R"], ch["G"], ch["B"]], axis=-1)


def test_a_small_render_is_finite_and_the_leaves_are_cut_out(worker_binary, studio, tmp_path):
    width, height, spp = 128, 96, 16
    doc, binary = read_glb(studio)
    masked = render(worker_binary, studio, tmp_path / "masked.exr", width, height, spp)
    assert np.isfinite(masked).all() and (masked >= 0).all()
    luminance = masked @ np.array([0.2126, 0.7152, 0.0722])
    # Nothing is black: the wall (the top rows) and the floor (the bottom rows) are lit by the
    # soft box everywhere; what is dark (the soil in the pot, the vase's reflection of the dark
    # room behind the camera) is a small part of the frame.
    assert luminance[:8].min() > 0.03 and luminance[-8:].min() > 0.03
    assert (luminance < 0.01).mean() < 0.03, (luminance < 0.01).mean()
    assert 0.05 < luminance.mean() < 1.0, luminance.mean()

    through, solid = classify_leaf_pixels(doc, binary, tmp_path, width, height)
    # The same scene with the leaves' alphaMode OPAQUE: the whole card shows, its cut-away
    # texels in the leaf's green (make_studio.py gives them that colour).
    for material in doc["materials"]:
        if material["name"] == "leaf":
            material["alphaMode"] = "OPAQUE"
    opaque_scene = tmp_path / "opaque.glb"
    write_glb(opaque_scene, doc, binary)
    opaque = render(worker_binary, opaque_scene, tmp_path / "opaque.exr", width, height, spp)

    assert through.sum() >= 10 and solid.sum() >= 10, (through.sum(), solid.sum())

    def green(img):  # the leaf's green: linear G about 4 x R (sRGB 0.24, 0.47, 0.16)
        return img[:, :, 1] > 1.5 * img[:, :, 0]

    # Through the cut-away part: the opaque card shows green, the masked one what is behind it
    # (warm grey plaster, terracotta or cream tiles: G below R).
    assert green(opaque)[through].mean() > 0.9, green(opaque)[through].mean()
    assert (masked[:, :, 1] < 1.1 * masked[:, :, 0])[through].mean() > 0.9
    # On the leaf itself both show it.
    assert green(masked)[solid].mean() > 0.9 and green(opaque)[solid].mean() > 0.9


# ---------------------------------------------------------------------------- make demo


def resolve(scene: str, cwd: Path = ROOT) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", str(DEMO), "--resolve", scene], capture_output=True,
                          text=True, cwd=cwd, timeout=30)  # fmt: skip


def fields(line: str) -> dict[str, str]:
    return dict(item.split("=", 1) for item in line.split())


def test_demo_resolves_the_examples_by_name():
    default = resolve("")
    assert default.returncode == 0, default.stderr
    # The default is the Cornell box, with the settings the README states.
    assert fields(default.stdout) == {
        "scene": "examples/cornell-box.gltf", "generator": "-",
        "output": "out/cornell-box.exr", "width": "512", "height": "512",
        "noise_threshold": "0.08", "max_spp": "1024",
    }  # fmt: skip
    studio = fields(resolve("studio").stdout)
    assert studio["scene"] == "examples/studio.glb"
    assert studio["generator"] == "examples/make_studio.py"
    assert studio["output"] == "out/studio.exr"
    assert (studio["width"], studio["height"]) == ("512", "384")
    hinged = fields(resolve("hinged-box").stdout)
    assert hinged["generator"] == "examples/make_hinged_box.py"
    for example in (default, resolve("studio"), resolve("hinged-box")):
        f = fields(example.stdout)
        assert (ROOT / f["scene"]).exists() or (ROOT / f["generator"]).exists(), f
    # An example's file by its path gets the example's settings.
    assert fields(resolve("examples/../examples/cornell-box.gltf").stdout)["max_spp"] == "1024"


def test_demo_takes_a_path_relative_to_the_caller(tmp_path):
    (tmp_path / "My Shot.glb").write_bytes(b"glTF")
    got = resolve("My Shot.glb", cwd=tmp_path)
    assert got.returncode == 0, got.stderr
    # Read as one line: the path has a blank in it.
    assert got.stdout.startswith(f"scene={tmp_path / 'My Shot.glb'} generator=- ")
    assert "output=out/My Shot.exr" in got.stdout


@pytest.mark.parametrize(
    ("scene", "message"),
    [
        ("nosuch", "demo: SCENE=nosuch: no such example (examples: cornell-box, studio, "
                   "hinged-box; or a path to a .glb/.gltf)"),
        ("missing/shot.glb", "demo: SCENE=missing/shot.glb: no such file"),
        ("notes/shot.txt", "demo: SCENE=notes/shot.txt: not a .glb or .gltf file (examples: "
                           "cornell-box, studio, hinged-box)"),
    ],
)  # fmt: skip
def test_a_bad_scene_is_one_line_and_status_2_before_anything_starts(tmp_path, scene, message):
    # A copy of the script in an empty tree: were it to go on, it would make .farm and out
    # there (and fail on the missing .venv); it must stop before.
    (tmp_path / "scripts").mkdir()
    shutil.copy(DEMO, tmp_path / "scripts" / "demo.sh")
    run = subprocess.run(["bash", str(tmp_path / "scripts" / "demo.sh"), scene],
                         capture_output=True, text=True, cwd=tmp_path, timeout=30)  # fmt: skip
    assert (run.returncode, run.stdout, run.stderr) == (2, "", message + "\n")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scripts"]


def test_make_demo_checks_the_scene_before_building():
    run = subprocess.run(["make", "--no-print-directory", "demo", "SCENE=nosuch"], cwd=ROOT,
                         capture_output=True, text=True, timeout=30)  # fmt: skip
    assert run.returncode == 2
    assert run.stderr.splitlines()[0].startswith("demo: SCENE=nosuch: no such example")
    assert "install" not in run.stdout and "cmake" not in run.stdout
