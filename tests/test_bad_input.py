"""Each kind of invalid request gets its documented status and a message naming the field;
a bundle escaping with ../ is refused and nothing is written outside the store; a good bundle
renders."""

from __future__ import annotations

import io
import json
import os
import zipfile
from pathlib import Path

import pytest

from renderfarm.cli.localfarm import LocalFarm
from renderfarm.client import Client

from .apihelpers import TINY, cornell_glb, escaping_zip
from .conftest import CORNELL

UPLOAD_LIMIT = 300_000


@pytest.fixture(scope="module")
def small_farm(tmp_path_factory):
    """A farm without workers whose limits are small: uploads 300 kB, 1024x1024, 4096 spp."""
    env = {
        "RENDERFARM_MAX_UPLOAD_BYTES": str(UPLOAD_LIMIT),
        "RENDERFARM_MAX_WIDTH": "1024",
        "RENDERFARM_MAX_HEIGHT": "1024",
        "RENDERFARM_MAX_SPP": "4096",
    }
    with LocalFarm(workers=0, data_dir=tmp_path_factory.mktemp("small"), env=env) as farm:
        yield farm


def _submit(client: Client, data: bytes, filename: str, settings: dict | None = None):
    return client.http.post(
        "/api/v1/jobs",
        files={"scene": (filename, data, "application/octet-stream")},
        data={"settings": json.dumps(settings or {})},
    )


CASES = [
    ("unknown setting", {"colour": "red"}, 400, "settings.colour", "unknown setting"),
    ("wrong type", {"width": "wide"}, 400, "settings.width", "must be an integer"),
    ("width over the limit", {"width": 2048}, 400, "settings.width", "1..1024"),
    ("height over the limit", {"height": 5000}, 400, "settings.height", "1..1024"),
    ("spp over the limit", {"max_spp": 5000}, 400, "settings.max_spp", "1..4096"),
    ("spp alias over the limit", {"spp": 5000}, 400, "settings.spp", "1..4096"),
    ("negative seed", {"seed": -1}, 400, "settings.seed", "0..2^63-1"),
    ("huge integer", {"width": 10**400}, 400, "settings.width", "must be"),
    ("not a number", {"noise_threshold": "NaN"}, 400, "settings.noise_threshold", "finite"),
    ("bad sampler", {"sampler": "magic"}, 400, "settings.sampler", "must be one of"),
]  # fmt: skip


@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_bad_settings_are_named(small_farm, case):
    _, settings, status, field, words = case
    with Client(small_farm.url) as client:
        r = _submit(client, cornell_glb(), "c.glb", settings)
    assert r.status_code == status, r.text
    body = r.json()
    assert body["field"] == field and words in body["detail"], body


def test_an_upload_over_the_limit_is_413(small_farm):
    with Client(small_farm.url) as client:
        r = _submit(client, cornell_glb() + bytes(UPLOAD_LIMIT), "big.glb")
    assert r.status_code == 413 and r.json()["field"] == "scene"
    assert str(UPLOAD_LIMIT) in r.json()["detail"]


@pytest.mark.parametrize(
    "data, filename, words",
    [
        (b"\x89PNG\r\n\x1a\n" + bytes(64), "x.png", "not a glTF 2.0 file"),
        (b"<html>hello</html>", "x.gltf", "not a glTF 2.0 file"),
        (b'{"asset": {"version": "1.0"}}', "x.gltf", "version"),
        (b"", "x.glb", "empty"),
        (b"PK\x03\x04" + bytes(64), "x.zip", "zip"),
    ],
    ids=["png", "html", "gltf-1.0", "empty", "broken-zip"],
)
def test_non_gltf_content_is_refused_before_any_worker_sees_it(small_farm, data, filename, words):
    with Client(small_farm.url) as client:
        r = _submit(client, data, filename)
        assert r.status_code == 400, r.text
        assert r.json()["field"].startswith("scene") and words in r.json()["detail"], r.json()
        assert client.list()["jobs"] == [] or all(
            j["name"] != filename for j in client.list()["jobs"]
        )


def test_other_malformed_requests(small_farm):
    with Client(small_farm.url) as client:
        http = client.http
        cases = [
            (http.post("/api/v1/jobs", content=b"{", headers={"content-type": "application/json"}),
             400, "body"),
            (http.post("/api/v1/jobs", json=[1, 2]), 400, "body"),
            (http.post("/api/v1/jobs", json={"scene_sha256": "x" * 64, "bogus": 1}), 400,
             "bogus"),
            (http.post("/api/v1/jobs", content=b"x", headers={"content-type": "text/plain"}), 400,
             "content-type"),
            (http.post("/api/v1/jobs", json={"scene_sha256": "nothex"}), 400, "scene_sha256"),
            (http.post("/api/v1/jobs", json={"scene_sha256": "a" * 64, "name": "a\x00b"}), 400,
             "name"),
            (http.post("/api/v1/jobs", files={"scene": ("c.glb", cornell_glb())},
                       data={"settings": "[1]"}), 400, "settings"),
            (http.get("/api/v1/jobs", params={"state": "sleeping"}), 400, "state"),
            (http.get("/api/v1/jobs", params={"page_size": "many"}), 400, "page_size"),
            (http.get("/api/v1/jobs/abc/image.tiff"), 400, "fmt"),
            (http.get("/api/v1/scenes/zz"), 400, "sha256"),
            (http.get("/api/v1/jobs/0123456789ab"), 404, ""),
        ]  # fmt: skip
        for r, status, field in cases:
            assert (r.status_code, r.json()["field"]) == (status, field), (r.request.url, r.text)
            assert r.json()["detail"]


def test_a_zip_escaping_with_dotdot_is_refused_and_writes_nothing(small_farm, tmp_path):
    before = {p for p in Path(small_farm.data_dir).parent.rglob("escaped-by-test.txt")}
    with Client(small_farm.url) as client:
        r = _submit(client, escaping_zip(), "evil.zip")
    assert r.status_code == 400
    assert r.json()["field"] == "scene" and "climbs out of the bundle" in r.json()["detail"]
    # Bundles are read in memory: no file appears next to the store, in it, or in the cwd.
    after = {p for p in Path(small_farm.data_dir).parent.rglob("escaped-by-test.txt")}
    assert after == before == set()
    assert not Path(os.getcwd(), "..", "escaped-by-test.txt").exists()
    assert not Path("/tmp/escaped-by-test.txt").exists()


def test_a_zip_bundle_of_a_gltf_and_its_files_renders(farm, tmp_path):
    bundle = tmp_path / "cornell.zip"
    with zipfile.ZipFile(bundle, "w") as z:
        z.write(CORNELL, "cornell/cornell-box.gltf")
        z.write(CORNELL.with_suffix(".bin"), "cornell/cornell-box.bin")
    with Client(farm.url) as client:
        job = client.submit(bundle, settings=TINY, name="bundle")
        assert client.scene(job["scene_sha256"])["format"] == "glb"
        assert job["scene_sha256"] == client.submit(CORNELL, settings=TINY)["scene_sha256"]
        done = client.wait(job["id"], poll_s=0.2, timeout_s=300)
        assert done["state"] == "completed", done["error"]
        assert client.image(job["id"], "png")[:4] == b"\x89PNG"


def test_tar_gz_bundles_are_accepted_too(farm):
    import tarfile

    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as t:
        t.add(CORNELL, "cornell-box.gltf")
        t.add(CORNELL.with_suffix(".bin"), "cornell-box.bin")
    with Client(farm.url) as client:
        r = _submit(client, buf.getvalue(), "cornell.tar.gz", {**TINY, "max_spp": 1})
        assert r.status_code == 201, r.text
        client.wait(r.json()["id"], poll_s=0.2, timeout_s=300)


def _nested(depth: int) -> str:
    return "[" * depth + "]" * depth


@pytest.mark.parametrize("depth", [1000, 100_000])
def test_deeply_nested_json_is_a_400_naming_the_body(small_farm, depth):
    deep = _nested(depth)
    glb = ("c.glb", cornell_glb(), "model/gltf-binary")
    as_json = {"content-type": "application/json"}
    with Client(small_farm.url) as client:
        http = client.http
        cases = [
            (http.post("/api/v1/jobs", content=deep, headers=as_json), "body"),
            (http.post("/api/v1/jobs", content=f'{{"settings": {{"width": {deep}}}}}',
                       headers=as_json), "body"),
            (http.post("/api/v1/jobs", files={"scene": glb}, data={"settings": deep}),
             "settings"),
            (http.post("/api/v1/jobs", files={"scene": glb},
                       data={"settings": f'{{"width": {deep}}}'}), "settings"),
            (http.post("/api/v1/session", content=deep, headers=as_json), "body"),
            (http.post("/api/v1/session", content=f'{{"token": {deep}}}', headers=as_json),
             "body"),
        ]  # fmt: skip
        for r, field in cases:
            assert r.status_code == 400, (r.request.url, r.text[:300])
            assert r.json()["field"] == field and "nested too deeply" in r.json()["detail"]
        assert client.list()["jobs"] == [] or all(
            j["progress"]["tiles_total"] for j in client.list()["jobs"]
        )


def test_every_error_body_has_detail_and_field(small_farm):
    """FastAPI's and Starlette's own answers keep the shape: unknown paths, wrong methods,
    bodies they cannot parse or that miss a field."""
    as_json = {"content-type": "application/json"}
    with Client(small_farm.url) as client:
        http = client.http
        cases = [
            (http.get("/no/such/page"), 404, ""),
            (http.get("/api/v1/nothing-here"), 404, ""),
            (http.get("/assets/no-such-file.js"), 404, ""),
            (http.put("/api/v1/jobs"), 405, ""),
            (http.delete("/healthz"), 405, ""),
            (http.post("/api/v1/session", content=b"{", headers=as_json), 400, "body"),
            (http.post("/api/v1/session", content=b"", headers=as_json), 400, "body"),
            (http.post("/api/v1/session", json={}), 400, "token"),
            (http.post("/api/v1/session", json={"token": 5}), 400, "token"),
            (http.post("/api/v1/session", json=[1]), 400, "body"),
            (http.post("/api/v1/jobs", content=b'{"a": }', headers=as_json), 400, "body"),
        ]  # fmt: skip
        for r, status, field in cases:
            assert r.headers["content-type"] == "application/json", (r.request.url, r.text)
            body = r.json()
            assert (r.status_code, body["field"]) == (status, field), (r.request.url, body)
            assert set(body) == {"detail", "field"} and body["detail"], (r.request.url, body)
        assert "POST" in http.put("/api/v1/jobs").headers["allow"]  # headers are kept
