"""The Blender add-on (integrations/blender) in Blender itself: the bpy module of Blender 5.0.1,
installed by `scripts/install-deps.sh --blender` into .venv-blender (its own environment:
bpy needs numpy < 2, the server numpy >= 2). tests/blender_driver.py runs there, installs the
add-on from the zip the build makes and presses its buttons; this side runs the farm (with an
API token, so auth is on) and checks what the add-on did against the farm's own answers,
fetched with renderfarm.client."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from renderfarm.cli.localfarm import LocalFarm
from renderfarm.client import Client
from renderfarm.infra.images import read_exr

from .mattes import matte
from .tools import require_tool
from .waiting import wait_until

ROOT = Path(__file__).resolve().parents[1]
DRIVER = Path(__file__).with_name("blender_driver.py")
TOKEN = "rf_blender-addon-test-secret-5f0c2b"
WIDTH, HEIGHT = 40, 30  # the scene's resolution: not square, to see the aspect ratio kept
SETTINGS = {
    "max_spp": 4,
    "min_spp": 1,
    "tile_size": 16,
    "noise_threshold": 0.0,
    "sampler": "independent",
    "seed": 3,
    "aovs": "cryptomatte",
}


def blender_python() -> str:
    explicit = os.environ.get("RENDERFARM_BLENDER_PYTHON")
    path = Path(explicit) if explicit else ROOT / ".venv-blender" / "bin" / "python"
    require_tool(path.exists(), f"Blender's bpy module: {path} (scripts/install-deps.sh --blender)")
    return str(path)


@pytest.fixture(scope="module")
def addon_zip(tmp_path_factory) -> Path:
    """The zip `make blender-addon` writes, built by the same script."""
    out = tmp_path_factory.mktemp("addon") / "renderfarm-blender.zip"
    subprocess.run(
        [sys.executable, str(ROOT / "integrations" / "blender" / "build.py"), str(out)],
        check=True,
        capture_output=True,
        timeout=60,
    )
    return out


@pytest.fixture(scope="module")
def token_farm(tmp_path_factory, worker_binary):
    """A farm with an API token (auth on) and 2 workers."""
    data = tmp_path_factory.mktemp("blender-farm")
    with LocalFarm(
        workers=2, data_dir=data, threads=1, env={"RENDERFARM_ADMIN_TOKEN": TOKEN}
    ) as farm:
        with Client(farm.url, token=TOKEN, timeout=30) as c:
            wait_until(lambda: len(c.workers()) == 2, timeout_s=30, what="2 workers connected")
        yield farm


def run_driver(scenario: str, config: dict, tmp_path: Path) -> dict:
    config = {"user_resources": str(tmp_path / "blender-user"), **config}
    path = tmp_path / f"{scenario}.json"
    path.write_text(json.dumps(config))
    proc = subprocess.run(
        [blender_python(), str(DRIVER), scenario, str(path)],
        capture_output=True,
        text=True,
        timeout=600,
    )
    lines = [line for line in proc.stdout.splitlines() if line.startswith("RESULT ")]
    assert proc.returncode == 0 and lines, (
        f"driver {scenario} exited {proc.returncode}\n{proc.stdout[-4000:]}\n{proc.stderr[-4000:]}"
    )
    return json.loads(lines[-1][len("RESULT ") :])


def run_blender_script(script: Path, args: list[str], tmp_path: Path) -> dict:
    """Runs a script in Blender's Python (bpy) with a user directory of its own, and returns
    the JSON of its last `RESULT {...}` line (the script failing, or printing none, fails)."""
    env = {"BLENDER_USER_RESOURCES": str(tmp_path / "blender-user"), "PATH": "/usr/bin:/bin"}
    if "TMPDIR" in os.environ:
        env["TMPDIR"] = os.environ["TMPDIR"]
    proc = subprocess.run(
        [blender_python(), str(script), *args], capture_output=True, text=True, timeout=300,
        env=env,
    )  # fmt: skip
    lines = [line for line in proc.stdout.splitlines() if line.startswith("RESULT ")]
    assert proc.returncode == 0 and lines, proc.stdout[-2000:] + proc.stderr[-4000:]
    return json.loads(lines[-1][len("RESULT ") :])


def test_addon_zip_is_a_valid_extension(addon_zip):
    """Blender's own extension tool accepts the zip's manifest."""
    python = blender_python()
    tool = (
        subprocess.run(
            [
                python,
                "-c",
                "import os, bpy, bl_pkg; "
                "print(os.path.join(os.path.dirname(bl_pkg.__file__), 'cli', 'blender_ext.py'))",
            ],
            capture_output=True,
            text=True,
            timeout=120,
            check=True,
        )
        .stdout.strip()
        .splitlines()[-1]
    )
    proc = subprocess.run(
        [python, tool, "validate", str(addon_zip)], capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr


def test_submit_follow_fetch(token_farm, addon_zip, tmp_path):
    combined = tmp_path / "combined.exr"
    blend = tmp_path / "scene.blend"
    result = run_driver(
        "render",
        {
            "zip": str(addon_zip),
            "url": token_farm.url,
            "token": TOKEN,
            "width": WIDTH,
            "height": HEIGHT,
            "settings": SETTINGS,
            "job_name": "blender box",
            "timeout_s": 300,
            "combined_exr": str(combined),
            "matte_exr": str(tmp_path / "matte.exr"),
            "blend": str(blend),
        },
        tmp_path,
    )

    with Client(token_farm.url, token=TOKEN, timeout=30) as client:
        # A wrong token is reported with the farm's 401 and where to set the token.
        assert result["wrong_token"]["result"] == ["CANCELLED"]
        assert "HTTP 401" in result["wrong_token"]["error"]
        assert "API token" in result["wrong_token"]["error"]

        # The settings fields are the farm's list: every setting the user chooses (not those
        # the farm fills in from the scene, light_groups), type, default, help and the choices
        # of the enumerated ones.
        docs = [d for d in client.http.get("/api/v1/settings").json() if not d["derived"]]
        assert result["refresh"]["result"] == ["FINISHED"]
        keys = ("name", "type", "default", "help")
        assert [{k: s[k] for k in keys} for s in result["settings"]] == [
            {k: d[k] for k in keys} for d in docs
        ]
        assert [s["choices"] for s in result["settings"]] == [d["choices"] for d in docs]
        for s in result["settings"]:  # Blender holds floats in single precision
            expected = (
                pytest.approx(s["default"], rel=1e-6) if s["type"] == "float" else s["default"]
            )
            assert s["value"] == expected, s
        by_name = {s["name"]: s for s in result["settings"]}
        assert by_name["sampler"]["choices"] == ["sobol", "halton", "stratified", "independent"]
        assert by_name["width"]["choices"] == [] and by_name["environment"]["choices"] == []

        # The plain scene (Principled BSDF, emission, point light, camera) loses nothing.
        assert result["check"]["result"] == ["FINISHED"]
        assert result["issues"] == []

        # The panel: the farm, every setting, the scene check, the frame, the job's progress.
        before = result["panel_before"]
        assert "Farm URL" in before and "API token" in before
        for label in ("Max spp", "Noise threshold", "Sampler", "Width", "Scene resolution"):
            assert label in before, label
        assert any("everything" in t or "Nothing" in t for t in before), before
        assert any("current frame only (frame 1)" in t for t in before), before
        if "panel_running" in result:  # unless the job finished between two polls
            assert any(t.startswith("running, tiles") for t in result["panel_running"])
        assert any(t.startswith("completed, tiles") for t in result["panel_after"])
        assert any(t == "Image 'blender box'" for t in result["panel_after"])

        # A setting the farm refuses: its message and field reach the artist; no job.
        assert result["refused"]["result"] == ["CANCELLED"]
        assert "HTTP 400" in result["refused"]["error"]
        assert "[settings.max_spp]" in result["refused"]["error"]
        assert result["jobs_after_refusal"] == 0

        # The job on the farm: the settings set in Blender, the scene's resolution.
        assert result["submit"]["result"] == ["FINISHED"], result["submit"]
        job = client.get(result["job_id"])
        assert job["state"] == "completed", job["error"]
        assert job["name"] == "blender box"
        assert job["owner"] == "admin"
        for name, value in {**SETTINGS, "width": WIDTH, "height": HEIGHT}.items():
            assert job["settings"][name] == value, name
        assert result["first_state"] in ("queued", "running")
        assert result["states"][-1] == "completed"
        tiles = job["progress"]["tiles_total"]
        assert result["progress"]["tiles_done"] == result["progress"]["tiles_total"] == tiles
        assert result["progress"]["mean_spp"] == job["progress"]["mean_spp"] == 4

        # The fetched image: named after the job, the farm's EXR next to nothing but a temp
        # dir (the .blend was not saved yet), and its colour is the farm's, value for value.
        assert result["fetch"]["result"] == ["FINISHED"]
        image = result["image"]
        assert image["name"] == "blender box" and image["job_name"] == "blender box"
        assert image["type"] == "MULTILAYER"
        assert Path(image["path"]).name == f"blender_box-{job['id'][:8]}.exr"
        farm_exr = tmp_path / "farm.exr"
        farm_exr.write_bytes(client.image(job["id"], "exr"))
    farm = read_exr(str(farm_exr))
    fetched_file = read_exr(image["path"])
    seen = read_exr(str(combined))
    for c in "RGB":
        assert farm[c].shape == (HEIGHT, WIDTH)
        np.testing.assert_array_equal(fetched_file[c], farm[c])
        np.testing.assert_array_equal(seen[c], farm[c])
    rgb = np.stack([farm[c] for c in "RGB"], axis=-1)
    assert rgb.max() > 0.05, "the farm rendered a black image"

    # "Load passes into compositor": an Image node with the passes and a Cryptomatte node per
    # type, the colour at the empty compositor's output; the CryptoObject node picking Box gives
    # Box's coverage as the farm's EXR holds it (decoded here by numpy).
    compositor = result["compositor"]
    assert compositor["op"]["result"] == ["FINISHED"], compositor["op"]
    assert compositor["nodes"] == sorted(["CryptoAsset", "CryptoMaterial", "CryptoObject",
                                          "CompositorNodeImage", "NodeGroupOutput",
                                          "Render farm: blender box"])  # fmt: skip
    assert compositor["output_was"] == ["Combined"]
    assert "renderfarm.compositor" in result["panel_after"]  # its button, under the image
    box = matte(farm, "CryptoObject", "Box")
    assert box.max() == 1.0 and 0 < box.mean() < 0.5  # the box covers part of the image
    np.testing.assert_allclose(read_exr(str(tmp_path / "matte.exr"))["R"], box, atol=1e-6)

    # The token is in the preferences, never in the saved .blend.
    assert result["token_in_prefs"] is True
    data = blend.read_bytes()
    assert data[:7] == b"BLENDER" and len(data) > 10000
    assert TOKEN.encode() not in data
    assert b"renderfarm" in data  # the scene's add-on data is saved: the search was not vacuous


def test_unsupported_features_listed_and_submission_allowed(token_farm, addon_zip, tmp_path):
    with Client(token_farm.url, token=TOKEN, timeout=30) as client:
        docs = client.http.get("/api/v1/settings").json()
    result = run_driver(
        "scan",
        {
            "zip": str(addon_zip),
            "url": token_farm.url,
            "token": TOKEN,
            "settings": {"max_spp": 1, "min_spp": 1, "noise_threshold": 0.0},
            "settings_docs": json.dumps(docs),
            "blend": str(tmp_path / "scan.blend"),
        },
        tmp_path,
    )
    issues = [(i["owner"], i["message"]) for i in result["issues"]]

    def listed(owner: str, *words: str) -> bool:
        return any(o == owner and all(w in m for w in words) for o, m in issues)

    assert listed("Material 'Fur'", "'Hair BSDF'"), issues
    assert listed("Material 'Marbled'", "group 'Marble'", "'Noise Texture'"), issues
    assert listed("Material 'Marbled'", "Anisotropic"), issues
    assert not any("Coat" in m for _, m in issues), issues
    assert listed("Material 'Fog'", "'Fog Volume'", "volume"), issues
    assert listed("Object 'Smoke'", "Volume objects"), issues
    assert listed("Object 'Ground'", "particle system", "hair"), issues
    assert listed("Light 'Softbox'", "area lights"), issues
    kinds = {i["owner"]: i["kind"] for i in result["issues"]}
    assert kinds["Object 'Smoke'"] == "volume" and kinds["Material 'Fur'"] == "hair"
    # Not listed: a node linked to nothing, what Blender does not render, the inactive camera,
    # and the materials the export carries.
    assert not any("Unused Voronoi" in m for _, m in issues)
    assert not any("HiddenVolume" in o or "Camera" in o for o, _ in issues)
    assert not any(o in ("Material 'Grey'", "Material 'Red'", "Material 'Glow'") for o, _ in issues)

    # Submission is still allowed, and the list stays shown.
    assert result["submit"]["result"] == ["FINISHED"], result["submit"]
    assert result["job_id"]
    assert result["issues_after_submit"] == len(issues)
    # A field per setting the user chooses; none for those the farm fills in (light_groups).
    assert "aovs" in result["setting_fields"], result["setting_fields"]
    assert "light_groups" not in result["setting_fields"]
    with Client(token_farm.url, token=TOKEN, timeout=30) as client:
        job = client.get(result["job_id"])
    assert job["name"] == "untitled Scene frame 1"
    # Reopened, the .blend's job is followed again; Cancel is the farm's answer (a job that
    # finished first stays as it was).
    assert result["followed_after_open"] == [result["job_id"]]
    assert result["cancel"]["result"] == ["FINISHED"], result["cancel"]
    assert result["state_after_cancel"] in ("cancelled", "completed")
    assert job["state"] == result["state_after_cancel"]

    # The exported .glb keeps a camera only on the active camera's node (the farm renders
    # through the first one, and the exporter wrote the other first), though both cameras'
    # nodes were written.
    assert result["camera_nodes"] == ["SideCam"]
    assert {"Camera", "SideCam", "Box", "Ground", "Lamp"} <= set(result["exported_nodes"])
    assert "Box" in result["mesh_nodes"] and "Smoke" not in result["mesh_nodes"]


# The moving box of blender_driver.moving_box_scene: its x at frames 1, 2, 3 (unequal steps, so
# every frame's position differs from its neighbours' by a different amount).
BOX_X = {1: -1.2, 2: 0.0, 3: 0.9}
ANIM_WIDTH, ANIM_HEIGHT = 48, 24


def _settings_docs(farm) -> list:
    with Client(farm.url, token=TOKEN, timeout=30) as client:
        return client.http.get("/api/v1/settings").json()


def test_animation_export_carries_and_lists(token_farm, addon_zip, tmp_path):
    """The animation export, read from its .glb: one animation holding the whole timeline at
    frame / fps seconds, transforms baked whatever moves them, shape keys of a mesh without
    modifiers; and what it drops is what the scan lists (only for Animation)."""
    result = run_driver(
        "animation_scan",
        {
            "zip": str(addon_zip),
            "url": token_farm.url,
            "box_x": BOX_X,
            "settings_docs": json.dumps(_settings_docs(token_farm)),
        },
        tmp_path,
    )
    issues = [(i["owner"], i["message"]) for i in result["issues"]]

    def listed(owner: str, *words: str) -> bool:
        return any(o == owner and all(w in m for w in words) for o, m in issues)

    # Listed for Animation, and not for a Still (where the export evaluates the current frame).
    assert listed("Object 'Lumpy'", "shape keys", "modifiers"), issues
    assert listed("Object 'Waver'", "'Ripple' (wave)", "as at frame 0"), issues
    assert listed("Object 'Ticker'", "'Clock' (geometry nodes using the scene time)"), issues
    assert listed("Object 'Blinker'", "visibility"), issues
    # Data animation: what KHR_animation_pointer carries (lens, power, emission strength) is
    # not listed, what it does not is, by name.
    assert listed("Camera 'Camera'", "(dof.aperture_fstop)"), issues
    assert listed("Light 'Lamp'", "(exposure)"), issues
    assert listed("Material 'Pulse'", "(Principled BSDF: Sheen Tint)"), issues
    assert {i["kind"] for i in result["issues"]} == {"animation"}, issues
    for name in ("Mover", "Follower", "Blob", "Beveled"):  # carried: not listed
        assert not any(o == f"Object '{name}'" for o, _ in issues), (name, issues)
    assert result["still_issues"] == []

    # One animation, named after the scene, for every animated node.
    assert [a["name"] for a in result["animations"]] == ["Scene"]
    channels = {(c["node"], c["path"]): c for c in result["animations"][0]["channels"]}
    fps = 24.0
    assert result["settings"]["frames"] == "1-3" and result["settings"]["fps"] == fps
    assert "animation" not in result["settings"]
    for key in (("Mover", "translation"), ("Follower", "translation"), ("Blob", "weights")):
        times = channels[key]["times"]
        np.testing.assert_allclose(times, [f / fps for f in (1, 2, 3)], rtol=1e-6)
    # Baked translations are Blender's world positions at those frames (glTF is y up: x, z, -y).
    for name in ("Mover", "Follower"):
        values = channels[(name, "translation")]["values"]
        for frame, value in zip((1, 2, 3), values, strict=True):
            x, y, z = result["world"][str(frame)][name]
            np.testing.assert_allclose(value, [x, z, -y], atol=1e-5)
    np.testing.assert_allclose([v[0] for v in channels[("Mover", "translation")]["values"]],
                               [BOX_X[f] for f in (1, 2, 3)], atol=1e-6)  # fmt: skip
    np.testing.assert_allclose(
        [v[0] for v in channels[("Blob", "weights")]["values"]], [0.0, 0.5, 1.0], atol=1e-6
    )
    # Dropped as listed: Lumpy's mesh has no morph targets. Data animation is written as
    # KHR_animation_pointer channels: the lens as yfov, the power as intensity, the emission
    # strength; the sheen tint (written wrong by Blender's exporter) is dropped.
    assert result["morphed_nodes"] == ["Blob"]
    assert "KHR_animation_pointer" in result["extensions"]
    pointers = {c["node"] for c in result["animations"][0]["channels"] if c["path"] == "pointer"}
    assert pointers == {
        "/cameras/0/perspective/yfov",
        "/extensions/KHR_lights_punctual/lights/0/intensity",
        f"/materials/{result['pulse_material']}/extensions/KHR_materials_emissive_strength/emissiveStrength",
    }, pointers
    assert {c["path"] for c in result["animations"][0]["channels"]} <= {
        "translation", "rotation", "scale", "weights", "pointer"
    }  # fmt: skip
    assert result["frame_after_export"] == 2

    # The camera is written as at frame 0 (lens 50 mm, the first key held), not as at the
    # current frame 2 (60 mm): horizontal fov 2 atan(sensor / 2 / lens), the image 16 x 12.
    def yfov(lens: float) -> float:
        return 2 * math.atan(math.tan(math.atan(result["sensor_width"] / 2 / lens)) * 12 / 16)

    assert result["camera_yfov"] == pytest.approx(yfov(50.0), rel=1e-5)
    assert abs(result["camera_yfov"] - yfov(60.0)) > 0.05

    # A frame step: farm frames a-bxN, the last frame the last one Blender renders (1, 4, 7).
    assert result["stepped_settings"]["frames"] == "1-7x3"
    # fps_base: the exporter times frame f at f / (fps * fps_base), and the add-on sends that
    # rate, so the farm's f / fps is the time the .glb holds for frame f.
    ntsc = result["ntsc_settings"]["fps"]
    assert ntsc == pytest.approx(30 * result["ntsc_fps_base"], rel=1e-12)
    sent_times = [f / ntsc for f in (1, 2, 3)]
    np.testing.assert_allclose(result["ntsc_times"], sent_times, rtol=1e-6)
    playback_times = [f / (30 / result["ntsc_fps_base"]) for f in (1, 2, 3)]
    assert abs(result["ntsc_times"][-1] - playback_times[-1]) > 1e-4  # the check can fail
    assert any("30.03 fps" in m and "29.97 fps" in m for m in result["ntsc_issues"])


def _centroid_x(rgb: np.ndarray) -> float:
    """The brightness-weighted mean column (pixel centres at 0.5, 1.5, ...) of an image whose
    only bright thing is the box."""
    weight = rgb.sum(axis=-1)
    weight = np.where(weight > 0.1 * weight.max(), weight, 0.0)
    columns = np.arange(rgb.shape[1]) + 0.5
    return float((weight.sum(axis=0) * columns).sum() / weight.sum())


def test_animation_submit_follow_fetch(token_farm, addon_zip, tmp_path):
    frames = sorted(BOX_X)
    result = run_driver(
        "animation",
        {
            "zip": str(addon_zip),
            "url": token_farm.url,
            "token": TOKEN,
            "width": ANIM_WIDTH,
            "height": ANIM_HEIGHT,
            "box_x": BOX_X,
            "frame_count": len(frames),
            "settings": SETTINGS,
            "timeout_s": 300,
            "blend": str(tmp_path / "shot.blend"),
            "out_dir": str(tmp_path),
        },
        tmp_path,
    )
    assert result["refresh"]["result"] == ["FINISHED"]
    assert result["check"]["result"] == ["FINISHED"] and result["issues"] == []
    assert any("Renders frames 1-3: 3 frames at 24 fps (farm frames 1-3)" in t
               for t in result["panel_before"]), result["panel_before"]  # fmt: skip
    assert result["submit"]["result"] == ["FINISHED"], result["submit"]
    assert result["frame_after_submit"] == 2  # the export left the current frame as it was

    with Client(token_farm.url, token=TOKEN, timeout=30) as client:
        job = client.get(result["job_id"])
        assert job["state"] == "completed", job["error"]
        assert job["name"] == "moving box"
        # The scene's range 1..3 at 24 fps, whatever the farm's own fields said (7-9, 12).
        assert job["settings"]["frames"] == "1-3"
        assert job["settings"]["fps"] == 24.0
        assert job["settings"]["animation"] == ""
        for name, value in {**SETTINGS, "width": ANIM_WIDTH, "height": ANIM_HEIGHT}.items():
            assert job["settings"][name] == value, name
        assert job["progress"]["frames_total"] == job["progress"]["frames_done"] == 3
        assert [f["frame"] for f in client.frames(job["id"])] == frames

        progress = result["progress"]
        assert (progress["frames_done"], progress["frames_total"]) == (3, 3)
        assert (progress["frames"], progress["fps"]) == ("1-3", 24.0)
        assert progress["summary"].startswith("completed, frames 3/3, tiles ")
        if "panel_running" in result:  # unless the sequence finished between two polls
            running = [t for t in result["panel_running"] if t.startswith("running, frames ")]
            assert running and all("/3, tiles " in t for t in running), result["panel_running"]
            assert any(t.startswith("Farm: moving box running, frames ")
                       for t in result["panel_running"])  # fmt: skip
        assert any(t.startswith("completed, frames 3/3") for t in result["panel_after"])

        # Fetched: every frame's EXR into renderfarm/NAME-ID/ next to the .blend, numbered by
        # the scene's frames, opened as one image sequence.
        assert result["fetch"]["result"] == ["FINISHED"], result["fetch"]
        image = result["image"]
        assert image["name"] == "moving box"
        assert image["source"] == "SEQUENCE" and image["type"] == "MULTILAYER"
        directory = tmp_path / "renderfarm" / f"moving_box-{job['id'][:8]}"
        assert Path(image["path"]) == directory / "moving_box_0001.exr"
        assert image["files"] == [f"moving_box_{f:04d}.exr" for f in frames]
        assert any("Image sequence 'moving box': 3 of 3 frames" in t
                   for t in result["panel_fetched"])  # fmt: skip
        assert any("Frames 3, Start 1, Offset 0" in t for t in result["panel_fetched"])
        assert result["refetch"]["result"] == ["FINISHED"]
        assert result["images_after_refetch"] == ["moving box"]
        assert result["shifted_user"] == {
            "frame_start": 11, "frame_offset": 10, "frame_duration": 3, "use_auto_refresh": True
        }  # fmt: skip

        farm_frames, still_frames = {}, {}
        for f in frames:
            (tmp_path / f"farm_{f}.exr").write_bytes(client.frame_image(job["id"], f, "exr"))
            farm_frames[f] = read_exr(str(tmp_path / f"farm_{f}.exr"))
            still = client.get(result["stills"][str(f)])
            assert still["state"] == "completed" and still["settings"]["frames"] == ""
            (tmp_path / f"still_{f}.exr").write_bytes(client.image(still["id"], "exr"))
            still_frames[f] = read_exr(str(tmp_path / f"still_{f}.exr"))

    centroids, still_centroids = {}, {}
    for f in frames:
        fetched = read_exr(str(directory / f"moving_box_{f:04d}.exr"))
        read_back = read_exr(result["read_back"][str(f)])  # Blender's reading of the sequence
        shifted = read_exr(result["shifted_read_back"][str(f)])  # ... of it renumbered 11..13
        for c in "RGB":
            assert farm_frames[f][c].shape == (ANIM_HEIGHT, ANIM_WIDTH)
            np.testing.assert_array_equal(fetched[c], farm_frames[f][c])
            np.testing.assert_array_equal(read_back[c], farm_frames[f][c])
            np.testing.assert_array_equal(shifted[c], farm_frames[f][c])
        centroids[f] = _centroid_x(np.stack([farm_frames[f][c] for c in "RGB"], axis=-1))
        still_centroids[f] = _centroid_x(np.stack([still_frames[f][c] for c in "RGB"], axis=-1))

    # Timing, checked two ways. Frame f of the sequence shows the box where Blender put it at
    # frame f: (1) its image column is the one of Blender's own projection of the box's
    # centre at frame f through the camera, and (2) the one of the still exported at frame f.
    # The box moves 1.2 and 0.9 units between frames (several pixels): a frame off by one, or
    # a time mapping that drifts, would put it columns away.
    for f in frames:
        projected = result["projected"][str(f)][0] * ANIM_WIDTH
        assert centroids[f] == pytest.approx(projected, abs=1.0), (f, centroids, projected)
        assert centroids[f] == pytest.approx(still_centroids[f], abs=0.25), (f, still_centroids)
    steps = np.diff([centroids[f] for f in frames])
    assert steps.min() > 3.0, centroids


VARIANTS = [["Green", [0.0, 1.0, 0.0]], ["Blue", [0.0, 0.0, 1.0]]]


def test_material_variants_offered_and_all_rendered_one_image_each(token_farm, addon_zip, tmp_path):
    result = run_driver(
        "variants",
        {
            "zip": str(addon_zip),
            "url": token_farm.url,
            "token": TOKEN,
            "width": 16,
            "height": 16,
            "settings": {**SETTINGS, "max_spp": 1},
            "variants": VARIANTS,
            "timeout_s": 300,
        },
        tmp_path,
    )
    # The menu: the default materials, each variant the export carries (not "Unused", which no
    # mesh maps), All variants; the default first.
    assert result["refresh"]["result"] == ["FINISHED"]
    assert result["menu"] == [
        ["", "Default materials"], ["Green", "Green"], ["Blue", "Blue"], ["all", "All variants"]
    ]  # fmt: skip
    assert result["default_variant"] == "" and result["one"] == "Blue"
    assert result["chosen"] == ["all", "all"]
    assert result["with_animation"]["result"] == ["CANCELLED"]
    assert "All variants renders each variant as a still" in result["with_animation"]["error"]
    assert any("once per material variant: 2 images (Green, Blue)" in t for t in result["panel"])
    assert result["menu_off"] == [["", "Default materials"]]  # the exporter writes none then

    assert result["submit"]["result"] == ["FINISHED"], result["submit"]
    assert result["summary"].startswith("completed, variants 2/2")
    assert result["fetch"]["result"] == ["FINISHED"], result["fetch"]
    with Client(token_farm.url, token=TOKEN, timeout=30) as client:
        job = client.get(result["job_id"])
        assert job["state"] == "completed" and job["settings"]["variant"] == "all"
        frames = client.frames(job["id"])
    assert [(f["frame"], f["variant"]) for f in frames] == [(0, "Green"), (1, "Blue")]
    images = result["images"]
    assert sorted(images) == ["cards - Blue", "cards - Green"]
    for name, color in VARIANTS:
        path = Path(images[f"cards - {name}"])
        assert path.name.endswith(f"_{name}.exr"), path
        exr = read_exr(str(path))
        mean = np.stack([exr[c] for c in "RGB"], -1).reshape(-1, 3).mean(0)
        np.testing.assert_allclose(mean, color, atol=0.02, err_msg=name)


POINTER_KEYS = {1: (100.0, 50.0), 2: (400.0, 50.0), 3: (400.0, 25.0)}  # frame: (W, mm)
POINTER_WIDTH, POINTER_HEIGHT = 64, 48


def test_keyed_light_power_and_lens_render_as_keyed(token_farm, addon_zip, tmp_path):
    """A point light's power and the camera's lens, keyed, are exported as
    KHR_animation_pointer channels (the intensity in the still's units, P / 4 pi) and the farm
    renders them: the floor, lit by the light only, is 4 times as bright at 400 W as at
    100 W; at 25 mm the emissive square covers a quarter of the image area it covers at
    50 mm."""
    result = run_driver(
        "pointer",
        {
            "zip": str(addon_zip),
            "url": token_farm.url,
            "token": TOKEN,
            "keys": POINTER_KEYS,
            "width": POINTER_WIDTH,
            "height": POINTER_HEIGHT,
            "settings": SETTINGS,
            "timeout_s": 300,
        },
        tmp_path,
    )
    assert result["check"]["result"] == ["FINISHED"] and result["issues"] == [], result["issues"]
    assert "KHR_animation_pointer" in result["extensions"]
    intensity = result["pointers"]["/extensions/KHR_lights_punctual/lights/0/intensity"]
    yfov = result["pointers"]["/cameras/0/perspective/yfov"]
    for channel in (intensity, yfov):
        np.testing.assert_allclose(channel["times"], [f / 24 for f in POINTER_KEYS], rtol=1e-6)
    blender = {int(f): v for f, v in result["blender"].items()}
    # In the file's units: the light's static intensity is frame 1's, P / 4 pi (COMPAT).
    assert result["light"]["intensity"] == pytest.approx(100.0 / (4 * math.pi), rel=1e-6)
    np.testing.assert_allclose(
        intensity["values"], [blender[f]["energy"] / (4 * math.pi) for f in POINTER_KEYS], rtol=1e-6
    )
    np.testing.assert_allclose(
        yfov["values"], [blender[f]["yfov"] for f in POINTER_KEYS], rtol=1e-5
    )

    assert result["submit"]["result"] == ["FINISHED"], result["submit"]
    images = {}
    with Client(token_farm.url, token=TOKEN, timeout=30) as client:
        job = client.get(result["job_id"])
        assert job["state"] == "completed", job["error"]
        assert job["settings"]["frames"] == "1-3"
        for f in POINTER_KEYS:
            path = tmp_path / f"frame_{f}.exr"
            path.write_bytes(client.frame_image(job["id"], f, "exr"))
            images[f] = read_exr(str(path))
    # The floor is grey and the light white: green is the light on the floor. The square is
    # black, emitting pure red: red less green is the square alone, summed over the image
    # its projected area (its radiance is constant).
    floor = {f: float(images[f]["G"].mean()) for f in POINTER_KEYS}
    square = {f: float((images[f]["R"] - images[f]["G"]).sum()) for f in POINTER_KEYS}
    assert floor[2] / floor[1] == pytest.approx(4.0, rel=0.03), floor
    assert square[2] == pytest.approx(square[1], rel=0.03), square  # the same lens
    assert square[3] / square[2] == pytest.approx((25.0 / 50.0) ** 2, rel=0.08), square
