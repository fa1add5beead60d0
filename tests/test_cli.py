"""The CLI as a user runs it: `renderfarm render` with and without a running server."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np

from renderfarm.infra.images import read_exr

from .conftest import CORNELL

CLI = [sys.executable, "-m", "renderfarm"]


def test_render_starts_a_local_farm_writes_exr_and_png_and_exits(tmp_path):
    out = tmp_path / "out" / "cornell.exr"
    env = {k: v for k, v in os.environ.items() if k != "RENDERFARM_URL"}
    done = subprocess.run(
        CLI + ["render", str(CORNELL), "-o", str(out), "--workers", "2", "--threads", "1"]
        + ["--width", "32", "--height", "32", "--spp", "4", "--data-dir", str(tmp_path / "d")],
        capture_output=True, text=True, timeout=300, env=env,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert f"EXR: {out}" in done.stdout and f"PNG: {out.with_suffix('.png')}" in done.stdout
    channels = read_exr(str(out))
    assert channels["R"].shape == (32, 32) and (channels["spp"] == 4).all()
    assert np.isfinite(channels["R"]).all()
    assert out.with_suffix(".png").read_bytes()[:4] == b"\x89PNG"


def test_render_against_a_server_reports_bad_settings_by_name(farm, tmp_path):
    done = subprocess.run(
        CLI + ["render", str(CORNELL), "-o", str(tmp_path / "x.exr"), "--url", farm.url]
        + ["--sampler", "magic"],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert done.returncode == 1
    assert "settings.sampler" in done.stderr and "magic" not in done.stdout


def test_render_refuses_a_missing_scene_and_a_non_exr_output(tmp_path):
    missing = subprocess.run(
        CLI + ["render", str(tmp_path / "nope.glb"), "-o", str(tmp_path / "x.exr")],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert missing.returncode == 2 and "scene file not found" in missing.stderr
    png = subprocess.run(
        CLI + ["render", str(CORNELL), "-o", str(tmp_path / "x.png")],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert png.returncode == 2 and ".exr" in png.stderr


def test_worker_render_refuses_a_bad_output_before_rendering(worker_binary, tmp_path):
    # 2^31 spp would take days: the refusal must come before the render starts.
    base = [worker_binary, "render", str(CORNELL), "--spp", "2147483648", "--threads", "1"]
    for out, says in (
        (tmp_path / "x.png", ".exr"),
        (tmp_path / "missing" / "x.exr", "does not exist"),
    ):
        done = subprocess.run(base + ["-o", str(out)], capture_output=True, text=True, timeout=60)
        assert done.returncode == 2, done.stderr
        assert says in done.stderr and "rendering" not in done.stderr
        assert not out.exists()


def test_worker_render_bvh_layouts_give_the_same_image(worker_binary, tmp_path):
    base = [worker_binary, "render", str(CORNELL), "--spp", "8", "--threads", "1"]
    base += ["--width", "48", "--height", "36"]
    images = {}
    for bvh in ("fast", "compact"):
        out = tmp_path / f"{bvh}.exr"
        done = subprocess.run(
            base + ["-o", str(out), "--bvh", bvh], capture_output=True, text=True, timeout=120
        )
        assert done.returncode == 0, done.stderr
        assert " in memory)" in done.stderr  # the scene line reports its memory
        images[bvh] = read_exr(str(out))
    for name, fast in images["fast"].items():
        np.testing.assert_array_equal(fast, images["compact"][name], err_msg=name)
    bad = subprocess.run(
        base + ["-o", str(tmp_path / "x.exr"), "--bvh", "small"],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert bad.returncode == 2 and "fast or compact" in bad.stderr


def test_worker_bench_runs_the_chosen_scenes_and_names_bad_ones(worker_binary, tmp_path):
    out = tmp_path / "bench.json"
    done = subprocess.run(
        [worker_binary, "bench", "--scenes", "cornell", "--cornell", str(CORNELL)]
        + ["--json", str(out), "--threads", "1", "--spp", "2", "--width", "16", "--height", "16"],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    scenes = json.loads(out.read_text())["scenes"]
    assert [s["scene"] for s in scenes] == ["cornell"]
    assert scenes[0]["packet_query_width"] in (8, 16)
    for args, says in (
        (["--scenes", "cornell,teapot", "--cornell", str(CORNELL)], "not 'teapot'"),
        (["--scenes", "cornell"], "needs --cornell"),
        (["--threads", "1,,2", "--cornell", str(CORNELL)], "--threads"),
    ):
        bad = subprocess.run(
            [worker_binary, "bench", *args], capture_output=True, text=True, timeout=60
        )
        assert bad.returncode == 2 and says in bad.stderr, bad.stderr
