"""The outputs of a job on a real farm: the denoised layer beside the unbiased image (closer to
a high-spp render of the scene than the noisy RGB is), the job's record in the EXR header, and
`renderfarm get -o` downloading an image or one layer."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import grpc
import numpy as np
import OpenImageIO as oiio
import pytest

from renderfarm.app.job_images import renderer_version
from renderfarm.client import ApiError, Client
from renderfarm.domain.scenes.glb import build_glb
from renderfarm.infra.images import read_exr
from renderfarm.v1 import jobs_pb2, jobs_pb2_grpc

from .conftest import CORNELL
from .waiting import wait_until

SCENE = {"width": 64, "height": 64, "tile_size": 32, "noise_threshold": 0}
NOISY = {**SCENE, "max_spp": 8, "seed": 1, "denoise": True}
REFERENCE = {**SCENE, "max_spp": 1024, "seed": 2}


def _rgb(channels, prefix: str = "") -> np.ndarray:
    return np.stack([channels[prefix + c] for c in "RGB"], -1).astype(np.float64)


@pytest.fixture(scope="module")
def jobs(farm, tmp_path_factory):
    """A noisy job with denoise on and a reference of the same scene with 128 times the
    samples; (noisy job, reference job, noisy EXR path, reference EXR path)."""
    out = tmp_path_factory.mktemp("outputs")
    with Client(farm.url, timeout=120) as client:
        wait_until(lambda: len(client.workers()) >= 2, 30, "2 workers connected")
        noisy = client.submit(CORNELL, settings=NOISY, name="noisy")
        reference = client.submit(CORNELL, settings=REFERENCE, name="reference")
        noisy = client.wait(noisy["id"], poll_s=0.2, timeout_s=600)
        reference = client.wait(reference["id"], poll_s=0.2, timeout_s=900)
        assert noisy["state"] == reference["state"] == "completed"
        paths = out / "noisy.exr", out / "reference.exr"
        client.save_image(noisy["id"], paths[0], "exr")
        client.save_image(reference["id"], paths[1], "exr")
    return noisy, reference, *paths


def test_denoised_layer_is_closer_to_the_reference_than_the_noisy_image(jobs):
    _, _, noisy_path, reference_path = jobs
    noisy, reference = read_exr(str(noisy_path)), read_exr(str(reference_path))
    assert "denoised.R" in noisy and "denoised.R" not in reference
    truth = _rgb(reference)

    def mse(image: np.ndarray) -> float:
        """Of the values shown (clamped to 0..1, as the PNG shows them): in linear values the
        light's edge (radiance 17) weighs a hundred times all the rest of the picture."""
        return float(np.mean((np.clip(image, 0, 1) - np.clip(truth, 0, 1)) ** 2))

    def rel_mse(image: np.ndarray) -> float:
        """Relative MSE, the usual measure of denoisers: (x - ref)^2 / (ref^2 + 0.01)."""
        return float(np.mean((image - truth) ** 2 / (truth**2 + 0.01)))

    noisy_rgb, denoised_rgb = _rgb(noisy), _rgb(noisy, "denoised.")
    # The reference's own noise (its estimated variance of the mean luminance, per pixel) is
    # small beside the error measured against it: the comparison is not one of two noises.
    reference_noise = float(np.mean(np.minimum(reference["variance.Y"], 1.0)))
    print(f"MSE noisy {mse(noisy_rgb):.3g}, denoised {mse(denoised_rgb):.3g}; relMSE noisy "
          f"{rel_mse(noisy_rgb):.3g}, denoised {rel_mse(denoised_rgb):.3g}; reference noise "
          f"{reference_noise:.3g}")  # fmt: skip
    assert reference_noise < 0.1 * mse(noisy_rgb)
    assert mse(denoised_rgb) < 0.5 * mse(noisy_rgb)
    assert rel_mse(denoised_rgb) < 0.5 * rel_mse(noisy_rgb)
    # The unbiased layers are the renderer's: 8 samples everywhere, finite error.
    assert (noisy["spp"] == 8).all() and np.isfinite(noisy["error"]).all()


def test_denoised_preview_over_rest_and_grpc(farm, jobs):
    noisy, reference, *_ = jobs
    with Client(farm.url, timeout=60) as client:
        png = client.image(noisy["id"], "png", layer="denoised", max_size=32)
        assert png[:8] == b"\x89PNG\r\n\x1a\n"
        assert int.from_bytes(png[16:20], "big") == 32  # downscaled by 2
        with pytest.raises(ApiError) as e:
            client.image(reference["id"], "png", layer="denoised")
        assert e.value.status == 400 and e.value.field == "layer"
        assert "denoise" in str(e.value)
    with grpc.insecure_channel(farm.grpc_address) as channel:
        stub = jobs_pb2_grpc.JobServiceStub(channel)
        answer = stub.GetImage(jobs_pb2.GetImageRequest(job_id=noisy["id"], layer="denoised"))
        assert answer.data[:8] == b"\x89PNG\r\n\x1a\n"
        with pytest.raises(grpc.RpcError) as e:
            stub.GetImage(jobs_pb2.GetImageRequest(job_id=reference["id"], layer="denoised"))
        assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT
        got = stub.GetJob(jobs_pb2.GetJobRequest(job_id=noisy["id"]))
        assert got.job.settings.denoise is True
        # Submitted through gRPC, the setting is kept (and refused past the memory limit).
        small = jobs_pb2.RenderSettings(width=16, height=16, tile_size=16, max_spp=1, denoise=True)
        made = stub.SubmitJob(
            jobs_pb2.SubmitJobRequest(scene_sha256=noisy["scene_sha256"], settings=small)
        )
        assert made.job.settings.denoise is True
        plain = jobs_pb2.RenderSettings(width=16, height=16, tile_size=16, max_spp=1)
        made = stub.SubmitJob(
            jobs_pb2.SubmitJobRequest(scene_sha256=noisy["scene_sha256"], settings=plain)
        )
        assert made.job.settings.denoise is False


def test_exr_header_is_the_jobs_record(farm, jobs):
    noisy, reference, noisy_path, reference_path = jobs
    with Client(farm.url, timeout=60) as client:
        for path, job in ((noisy_path, noisy), (reference_path, reference)):
            record = client.get(job["id"])
            inp = oiio.ImageInput.open(str(path))
            spec = inp.spec()
            inp.close()
            assert json.loads(spec.getattribute("renderfarm:settings")) == record["settings"]
            assert spec.getattribute("renderfarm:scene_sha256") == record["scene_sha256"]
            assert spec.getattribute("renderfarm:version") == renderer_version()
            mean_spp = spec.getattribute("renderfarm:mean_spp")
            assert mean_spp == pytest.approx(record["progress"]["mean_spp"])
            assert mean_spp == job["settings"]["max_spp"]
            error = spec.getattribute("renderfarm:error")
            assert error == pytest.approx(record["progress"]["error"], rel=1e-6)
        # A function of the job: fetched again, the same bytes.
        again = path.with_name("again.exr")
        client.save_image(reference["id"], again, "exr")
        assert again.read_bytes() == reference_path.read_bytes()


def test_exr_header_carries_the_scenes_xmp_metadata(farm, jobs, tmp_path):
    """KHR_xmp_json_ld: the asset's metadata packet (title, creator, licence) goes into the
    EXR header as renderfarm:xmp_json_ld; a scene without one (the noisy job's) has none."""
    packet = {
        "@context": {"dc": "http://purl.org/dc/elements/1.1/"},
        "dc:title": "Cornell box",
        "dc:rights": "CC0",
    }
    doc = json.loads(CORNELL.read_text())
    doc.setdefault("asset", {})["extensions"] = {"KHR_xmp_json_ld": {"packet": 0}}
    doc.setdefault("extensions", {})["KHR_xmp_json_ld"] = {"packets": [packet]}
    doc["extensionsUsed"] = [*doc.get("extensionsUsed", []), "KHR_xmp_json_ld"]
    scene = tmp_path / "cornell-box.gltf"
    scene.write_text(json.dumps(doc))
    for name in doc.get("buffers", []):  # the buffers beside the scene, as the example has them
        uri = name.get("uri", "")
        if uri and not uri.startswith("data:"):
            (tmp_path / uri).write_bytes((CORNELL.parent / uri).read_bytes())
    with Client(farm.url, timeout=120) as client:
        job = client.submit(scene, settings={**SCENE, "max_spp": 1}, name="xmp")
        job = client.wait(job["id"], poll_s=0.2, timeout_s=300)
        assert job["state"] == "completed"
        path = tmp_path / "xmp.exr"
        client.save_image(job["id"], path, "exr")
    for exr, want in ((path, packet), (jobs[2], None)):
        inp = oiio.ImageInput.open(str(exr))
        text = inp.spec().getattribute("renderfarm:xmp_json_ld")
        inp.close()
        assert (None if text is None else json.loads(text)) == want


def _variants_scene(path, variants=(("Blue", (0, 0, 1)),)) -> None:
    """A quad filling the view, its unlit material red by default and each variant's colour in
    that variant (KHR_materials_variants; `variants`: (name, rgb) in order, () for a scene
    without any): unlit, the image is the material's colour exactly."""
    pos = np.array([[-2, -2, 0], [2, -2, 0], [2, 2, 0], [-2, 2, 0]], np.float32)
    idx = np.array([0, 1, 2, 0, 2, 3], np.uint16)
    blob = pos.tobytes() + idx.tobytes() + b"\0\0\0\0"
    unlit = {"KHR_materials_unlit": {}}
    colours = [(1, 0, 0)] + [rgb for _, rgb in variants]
    primitive = {"attributes": {"POSITION": 0}, "indices": 1, "material": 0}
    doc = {
        "asset": {"version": "2.0"},
        "extensionsUsed": ["KHR_materials_unlit"],
        "scene": 0,
        "scenes": [{"nodes": [0, 1]}],
        "nodes": [{"mesh": 0}, {"camera": 0, "translation": [0, 0, 3]}],
        "cameras": [{"type": "perspective", "perspective": {"yfov": 0.5, "znear": 0.1}}],
        "materials": [
            {"pbrMetallicRoughness": {"baseColorFactor": [*rgb, 1]}, "extensions": unlit}
            for rgb in colours
        ],
        "meshes": [{"primitives": [primitive]}],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3",
             "min": [-2, -2, 0], "max": [2, 2, 0]},
            {"bufferView": 1, "componentType": 5123, "count": 6, "type": "SCALAR"},
        ],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": 48},
                        {"buffer": 0, "byteOffset": 48, "byteLength": 12}],
        "buffers": [{"byteLength": len(blob)}],
    }  # fmt: skip
    if variants:
        doc["extensionsUsed"].append("KHR_materials_variants")
        doc["extensions"] = {
            "KHR_materials_variants": {"variants": [{"name": name} for name, _ in variants]}
        }
        primitive["extensions"] = {"KHR_materials_variants": {"mappings": [
            {"material": i + 1, "variants": [i]} for i in range(len(variants))]}}  # fmt: skip
    path.write_bytes(build_glb(doc, blob))


def test_a_material_variant_reaches_the_workers_and_an_unknown_one_is_a_400(farm, tmp_path):
    scene = tmp_path / "shoe.glb"
    _variants_scene(scene)
    small = {"width": 16, "height": 16, "tile_size": 16, "noise_threshold": 0, "max_spp": 2}
    means = {}
    with Client(farm.url, timeout=120) as client:
        for variant in ("", "Blue", "0"):
            job = client.submit(scene, settings={**small, "variant": variant}, name="shoe")
            job = client.wait(job["id"], poll_s=0.2, timeout_s=300)
            assert job["state"] == "completed", job["error"]
            assert job["settings"]["variant"] == variant
            path = tmp_path / f"shoe-{variant or 'default'}.exr"
            client.save_image(job["id"], path, "exr")
            means[variant] = _rgb(read_exr(str(path))).reshape(-1, 3).mean(0)
        with pytest.raises(ApiError) as e:
            client.submit(scene, settings={**small, "variant": "Purple"}, name="shoe")
        assert e.value.status == 400 and e.value.field == "settings.variant"
        assert "'Blue'" in e.value.message
    np.testing.assert_allclose(means[""], [1, 0, 0], atol=1e-6)
    np.testing.assert_allclose(means["Blue"], [0, 0, 1], atol=1e-6)
    np.testing.assert_allclose(means["0"], [0, 0, 1], atol=1e-6)  # by index


# Three variants, the last one named "all": settings.variant "all" renders every variant (the
# keyword wins over the name), and that variant alone is chosen by its index.
THREE_VARIANTS = (("Green", (0, 1, 0)), ("Dark blue", (0, 0, 0.5)), ("all", (1, 1, 1)))


def test_variant_all_renders_one_image_per_variant_named_by_it(farm, tmp_path):
    scene = tmp_path / "shoe.glb"
    _variants_scene(scene, THREE_VARIANTS)
    small = {"width": 16, "height": 16, "tile_size": 8, "noise_threshold": 0, "max_spp": 2}
    with Client(farm.url, timeout=120) as client:
        job = client.submit(scene, settings={**small, "variant": "all"}, name="shoe")
        assert job["settings"]["variant"] == "all"
        assert (job["progress"]["frames_total"], job["progress"]["tiles_total"]) == (3, 12)
        alone = client.submit(scene, settings={**small, "variant": "2"}, name="shoe-all-alone")
        job = client.wait(job["id"], poll_s=0.2, timeout_s=300)
        alone = client.wait(alone["id"], poll_s=0.2, timeout_s=300)
        assert job["state"] == alone["state"] == "completed", (job["error"], alone["error"])
        assert job["progress"]["frames_done"] == 3
        frames = client.frames(job["id"])
        assert [(f["frame"], f["variant"], f["state"]) for f in frames] == [
            (0, "Green", "done"), (1, "Dark blue", "done"), (2, "all", "done")
        ]  # fmt: skip
        assert client.frames(alone["id"])[0]["variant"] is None
        images = {}
        for index, (name, rgb) in enumerate(THREE_VARIANTS):
            path = tmp_path / f"shoe-{index}.exr"
            client.save_image(job["id"], path, "exr", frame=index)
            images[name] = read_exr(str(path))
            mean = _rgb(images[name]).reshape(-1, 3).mean(0)
            np.testing.assert_allclose(mean, rgb, atol=1e-6, err_msg=name)
            spec = oiio.ImageInput.open(str(path)).spec()
            assert spec.getattribute("renderfarm:variant") == name
            assert spec.getattribute("renderfarm:variant_index") == index
            assert spec.getattribute("renderfarm:frame") is None
        # Each image is the still of its variant: the same bits as a job of that variant alone.
        client.save_image(alone["id"], tmp_path / "alone.exr", "exr")
        assert (
            _rgb(read_exr(str(tmp_path / "alone.exr"))).tobytes() == _rgb(images["all"]).tobytes()
        )
        with pytest.raises(ApiError) as e:
            client.frame_image(job["id"], 3)
        assert e.value.status == 404 and "variants 0..2" in e.value.message
        finished = [e["data"] for e in client.events(job["id"]) if e["kind"] == "frame_finished"]
        assert sorted((d["frame"], d["variant"]) for d in finished) == [
            (0, "Green"), (1, "Dark blue"), (2, "all")
        ]  # fmt: skip


def test_variant_all_is_refused_without_variants_and_with_frames(farm, tmp_path):
    plain = tmp_path / "plain.glb"
    _variants_scene(plain, ())
    shoe = tmp_path / "shoe.glb"
    _variants_scene(shoe, THREE_VARIANTS)
    small = {"width": 16, "height": 16, "max_spp": 1, "variant": "all"}
    with Client(farm.url, timeout=120) as client:
        with pytest.raises(ApiError) as e:
            client.submit(plain, settings=small, name="plain")
        assert e.value.status == 400 and e.value.field == "settings.variant"
        assert "has none" in e.value.message
        # The same for a stored scene named by its hash.
        stored = client.submit(plain, settings={**small, "variant": ""}, name="plain")
        with pytest.raises(ApiError) as e:
            client.submit(scene_sha256=stored["scene_sha256"], settings=small)
        assert e.value.status == 400 and e.value.field == "settings.variant"
        with pytest.raises(ApiError) as e:
            client.submit(shoe, settings={**small, "frames": "1-2"}, name="shoe")
        assert e.value.status == 400 and e.value.field == "settings.variant"
        assert "settings.frames" in e.value.message
        client.wait(stored["id"], poll_s=0.2, timeout_s=300)


CLI = [sys.executable, "-m", "renderfarm"]


def test_cli_render_writes_each_variant_under_its_name(farm, tmp_path):
    scene = tmp_path / "shoe.glb"
    _variants_scene(scene, THREE_VARIANTS)
    out = tmp_path / "out" / "shoe.exr"
    done = _cli(
        farm, "render", str(scene), "-o", str(out), "--variant", "all", "--width", "16",
        "--height", "16", "--spp", "1", "--noise-threshold", "0", "--quiet",
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    names = ["shoe_Green", "shoe_Dark_blue", "shoe_all"]
    assert sorted(p.name for p in out.parent.iterdir()) == sorted(
        f"{n}.{ext}" for n in names for ext in ("exr", "png")
    )
    for name, (_, rgb) in zip(names, THREE_VARIANTS, strict=True):
        mean = _rgb(read_exr(str(out.parent / f"{name}.exr"))).reshape(-1, 3).mean(0)
        np.testing.assert_allclose(mean, rgb, atol=1e-6, err_msg=name)
    assert "3 variants of 16x16" in done.stderr and "shoe_*.exr" in done.stdout


def _cli(farm, *args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "RENDERFARM_URL": farm.url}
    env.pop("RENDERFARM_TOKEN", None)
    return subprocess.run(CLI + list(args), capture_output=True, text=True, timeout=300, env=env)


def test_cli_get_downloads_the_image_or_one_layer(farm, jobs, tmp_path):
    noisy, reference, noisy_path, _ = jobs
    whole = read_exr(str(noisy_path))
    done = _cli(farm, "get", noisy["id"], "-o", str(tmp_path / "all.exr"))
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "all.exr").read_bytes() == noisy_path.read_bytes()

    done = _cli(farm, "get", noisy["id"], "-o", str(tmp_path / "error.exr"), "--layer", "error")
    assert done.returncode == 0, done.stderr
    error = read_exr(str(tmp_path / "error.exr"))
    assert list(error) == ["error"] and error["error"].tobytes() == whole["error"].tobytes()
    spec = oiio.ImageInput.open(str(tmp_path / "error.exr")).spec()
    assert spec.getattribute("renderfarm:scene_sha256") == noisy["scene_sha256"]

    done = _cli(farm, "get", noisy["id"], "-o", str(tmp_path / "d.exr"), "--layer", "denoised")
    assert done.returncode == 0, done.stderr
    denoised = read_exr(str(tmp_path / "d.exr"))
    assert sorted(denoised) == ["denoised.B", "denoised.G", "denoised.R"]
    assert denoised["denoised.G"].tobytes() == whole["denoised.G"].tobytes()

    done = _cli(farm, "get", noisy["id"], "-o", str(tmp_path / "spp.png"), "--layer", "spp")
    assert done.returncode == 0, done.stderr
    png = (tmp_path / "spp.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and int.from_bytes(png[16:20], "big") == 64

    # Errors: one line, exit 1 from the server's side, 2 for usage; no file left behind.
    cases = [
        (["get", reference["id"], "-o", str(tmp_path / "x.png"), "--layer", "denoised"], 1,
         "[layer]"),
        (["get", reference["id"], "-o", str(tmp_path / "x.exr"), "--layer", "denoised"], 1,
         "no denoised layer"),
        (["get", "0123456789ab", "-o", str(tmp_path / "x.exr")], 1, "no job"),
        (["get", noisy["id"], "-o", str(tmp_path / "x.jpg")], 2, ".exr or .png"),
        (["get", noisy["id"], "-o", str(tmp_path / "x.exr"), "--layer", "bogus"], 2,
         "unknown layer"),
        (["get", noisy["id"], "-o", str(tmp_path / "nowhere" / "x.exr")], 2, "no such directory"),
        (["get", noisy["id"], "--layer", "rgb"], 2, "need -o"),
    ]  # fmt: skip
    for args, code, words in cases:
        done = _cli(farm, *args)
        assert done.returncode == code, (args, done.stderr)
        assert len(done.stderr.strip().splitlines()) == 1 and words in done.stderr, done.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "all.exr", "d.exr", "error.exr", "spp.png"
    ]  # fmt: skip


def test_settings_list_has_denoise_as_a_bool(client):
    docs = client.http.get("/api/v1/settings").json()
    denoise = next(d for d in docs if d["name"] == "denoise")
    assert denoise["type"] == "bool" and denoise["default"] is False
    refused = client.http.post(
        "/api/v1/jobs",
        files={"scene": ("box.gltf", b"{}")},
        data={"settings": json.dumps({"denoise": "yes"})},
    )
    assert refused.status_code == 400
    assert refused.json()["field"] == "settings.denoise"


def test_denoised_images_asked_at_once_are_written_in_turn(farm, jobs):
    """Three denoised previews and an EXR at once: each is answered (one after the other, see
    FarmService._denoise_turn), the previews the same bytes."""
    from concurrent.futures import ThreadPoolExecutor

    noisy = jobs[0]

    def fetch(fmt: str) -> bytes:
        with Client(farm.url, timeout=120) as c:
            return c.image(noisy["id"], fmt, layer="denoised" if fmt == "png" else "rgb")

    with ThreadPoolExecutor(4) as pool:
        answers = list(pool.map(fetch, ["png", "png", "exr", "png"]))
    pngs = [answers[0], answers[1], answers[3]]
    assert all(a[:8] == b"\x89PNG\r\n\x1a\n" for a in pngs)
    assert pngs[0] == pngs[1] == pngs[2]
    assert answers[2] == jobs[2].read_bytes()
