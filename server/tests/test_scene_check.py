"""The scene checker's confinement: a loader that spins is stopped by its CPU limit, one that
allocates without bound by its address-space limit, and the loader's own verdicts pass
through with the glTF path as the field. The loaders here are small stand-in programs."""

from __future__ import annotations

import asyncio
import json
import sys
import time
from pathlib import Path

import pytest

from renderfarm.domain.scenes.pack import pack_gltf
from renderfarm.errors import SceneError
from renderfarm.infra.scene_check import SceneChecker, SceneLimits
from renderfarm.infra.worker_binary import find_worker_binary

CORNELL = Path(__file__).resolve().parents[2] / "examples" / "cornell-box.gltf"

LIMITS = SceneLimits(
    max_nodes=100, max_depth=16, max_triangles=1000, max_texture_pixels=0,
    max_memory_mb=64, cpu_seconds=1.0,
)  # fmt: skip


def stand_in(tmp_path, body: str) -> str:
    """An executable Python script standing in for renderfarm-worker."""
    path = tmp_path / "fake-worker"
    path.write_text(f"#!{sys.executable}\n{body}\n")
    path.chmod(0o755)
    return str(path)


def check(checker: SceneChecker, data: bytes = b"glTF0000", name: str = "x.glb") -> dict:
    return asyncio.run(checker.check(data, name, f"{time.monotonic_ns():064x}"))


def test_a_spinning_loader_is_stopped_by_the_cpu_limit(tmp_path):
    checker = SceneChecker(stand_in(tmp_path, "while True: pass"), LIMITS, tmp_path)
    started = time.monotonic()
    with pytest.raises(SceneError, match="more than the server's limit of 1 s of CPU time"):
        check(checker)
    # The limit, not the wall-clock backstop (2 x CPU + 30 s), ended it.
    assert time.monotonic() - started < 30


def test_a_loader_allocating_without_bound_is_stopped_by_the_memory_limit(tmp_path):
    # 1 GiB of base address space + 1.5 x 64 MB: a 4 GB allocation is refused.
    body = "import sys\ntry:\n    x = bytearray(4 << 30)\nexcept MemoryError:\n    sys.exit(3)"
    checker = SceneChecker(stand_in(tmp_path, body), LIMITS, tmp_path)
    with pytest.raises(SceneError, match="within the server's limits of 64 MB"):
        check(checker)


def test_the_loaders_refusal_names_the_gltf_path_and_acceptance_is_remembered(tmp_path):
    calls = tmp_path / "calls"
    verdict = {
        "ok": False,
        "error": "x.glb: nodes[2].children[0]: bad",
        "path": "nodes[2].children[0]",
    }
    body = (
        "import json, sys\n"
        f"open({str(calls)!r}, 'a').write('x')\n"
        "ok = 'good' in sys.argv[sys.argv.index('--name') + 1]\n"
        f"print(json.dumps({{'ok': True}} if ok else {verdict!r}))\n"
        "sys.exit(0 if ok else 1)"
    )
    checker = SceneChecker(stand_in(tmp_path, body), LIMITS, tmp_path)
    with pytest.raises(SceneError) as info:
        check(checker, name="x.glb")
    assert (info.value.field, info.value.message) == (
        "scene.nodes[2].children[0]",
        verdict["error"],
    )
    sha = "ab" * 32
    assert asyncio.run(checker.check(b"glTF", "good.glb", sha)) == {"ok": True}
    assert asyncio.run(checker.check(b"glTF", "good.glb", sha)) == {"ok": True}
    assert calls.read_text() == "xx"  # the second check of the same content ran nothing


def test_the_real_loader_accepts_the_cornell_box(tmp_path):
    checker = SceneChecker(find_worker_binary(), LIMITS, tmp_path)
    info = check(checker, pack_gltf(CORNELL), "cornell.glb")
    # The same counts read from the .gltf's JSON here: nodes, triangles (index counts / 3) and
    # the triangles of emissive materials.
    doc = json.loads(CORNELL.read_text())
    emissive = {i for i, m in enumerate(doc["materials"]) if any(m.get("emissiveFactor", [0]))}
    triangles = lit = 0
    for node in doc["nodes"]:
        for prim in doc["meshes"][node["mesh"]]["primitives"] if "mesh" in node else []:
            count = doc["accessors"][prim["indices"]]["count"] // 3
            triangles += count
            lit += count if prim.get("material") in emissive else 0
    assert (info["nodes"], info["triangles"], info["emissive_triangles"]) == (
        len(doc["nodes"]), triangles, lit), info  # fmt: skip
    assert not list(tmp_path.glob("inspect-*")), "the temporary copy is removed"


def test_a_missing_inspector_is_refused_at_start(tmp_path):
    with pytest.raises(RuntimeError, match="not an executable file"):
        SceneChecker(str(tmp_path / "nope"), LIMITS, tmp_path)
