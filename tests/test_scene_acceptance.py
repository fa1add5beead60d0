"""One scene-acceptance path: the server accepts a scene only if the workers' own loader does,
within the server's limits, and refuses the rest with 400 naming the glTF path of the fault.

Each hostile scene below was accepted (201) before, and then hung, exhausted or was refused by
every worker. The expected fields are the glTF spec's own structure (glTF 2.0 3.5.3: the node
hierarchy is disjoint strict trees; 3.12: a required extension the loader lacks refuses the
asset; 5.12: yfov in (0, pi)), not the loader's output.
"""

from __future__ import annotations

import json
import struct

import grpc
import pytest

from renderfarm.cli.localfarm import LocalFarm
from renderfarm.client import Client
from renderfarm.v1 import jobs_pb2, jobs_pb2_grpc

from .apihelpers import TINY, cornell_glb
from .conftest import CORNELL
from .waiting import wait_until


def split_glb(glb: bytes) -> tuple[dict, bytes]:
    json_len = struct.unpack_from("<I", glb, 12)[0]
    return json.loads(glb[20 : 20 + json_len]), glb[20 + json_len :]


def join_glb(doc: dict | str, rest: bytes) -> bytes:
    text = (doc if isinstance(doc, str) else json.dumps(doc)).encode()
    text += b" " * (-len(text) % 4)
    body = struct.pack("<II", len(text), 0x4E4F534A) + text + rest
    return b"glTF" + struct.pack("<II", 2, 12 + len(body)) + body


def cornell_variant(change) -> bytes:
    doc, rest = split_glb(cornell_glb())
    change(doc)
    return join_glb(doc, rest)


def shared_children_dag(doc: dict) -> None:
    """The 7 KB scene of the report: 40 nodes, node i lists node i+1 twice (2^40 paths)."""
    first = len(doc["nodes"])
    for i in range(40):
        doc["nodes"].append({"children": [first + i + 1] * 2} if i < 39 else {"mesh": 0})
    doc["scenes"][0]["nodes"].append(first)


def cycle(doc: dict) -> None:
    first = len(doc["nodes"])
    doc["nodes"] += [{"children": [first + 1]}, {"children": [first]}]


def unknown_required_extension(doc: dict) -> None:
    doc["extensionsUsed"] = [*doc.get("extensionsUsed", []), "EXT_made_up"]
    doc["extensionsRequired"] = ["EXT_made_up"]


def undeclared_vertices(count: int):
    def change(doc: dict) -> None:
        doc["accessors"].append({"componentType": 5126, "count": count, "type": "VEC3"})
        doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"] = len(doc["accessors"]) - 1

    return change


def index_out_of_range(doc: dict) -> None:
    """The first primitive's index accessor points at the vertex after the last one."""
    prim = doc["meshes"][0]["primitives"][0]
    vertices = doc["accessors"][prim["attributes"]["POSITION"]]["count"]
    doc["buffers"][0]["byteLength"] += 12
    doc["bufferViews"].append(
        {"buffer": 0, "byteOffset": doc["buffers"][0]["byteLength"] - 12, "byteLength": 12}
    )
    doc["accessors"].append(
        {"bufferView": len(doc["bufferViews"]) - 1, "componentType": 5125, "count": 3,
         "type": "SCALAR"}
    )  # fmt: skip
    prim["indices"] = len(doc["accessors"]) - 1
    doc["_extra_indices"] = [0, 1, vertices]  # appended to the BIN chunk by hostile()


def accessor0(**fields):
    """Accessor 0 (positions of the first mesh's first primitive) changed."""

    def change(doc: dict) -> None:
        doc["accessors"][0].update(fields)

    return change


def view0_stride(doc: dict) -> None:
    doc["bufferViews"][doc["accessors"][0]["bufferView"]]["byteStride"] = 64


def yfov(value: float):
    def change(doc: dict) -> None:
        doc["cameras"][0]["perspective"]["yfov"] = value

    return change


def hostile(name: str) -> bytes:
    if name == "index-out-of-range":
        doc, rest = split_glb(cornell_glb())
        index_out_of_range(doc)
        extra = struct.pack("<3I", *doc.pop("_extra_indices"))
        # The BIN chunk grows by the new indices; its header says how long it is.
        bin_len = struct.unpack_from("<I", rest, 0)[0]
        rest = struct.pack("<II", bin_len + 12, 0x004E4942) + rest[8 : 8 + bin_len] + extra
        doc["buffers"][0]["byteLength"] = bin_len + 12
        return join_glb(doc, rest)
    if name == "number-1e400":
        doc, rest = split_glb(cornell_glb())
        text = json.dumps(doc).replace('"yfov": ', '"yfov": 1e400, "znear_": ', 1)
        return join_glb(text, rest)
    changes = {
        "shared-children": shared_children_dag,
        "cycle": cycle,
        "required-extension": unknown_required_extension,
        "1e8-vertices-without-data": undeclared_vertices(10**8),
        "4e9-vertices-without-data": undeclared_vertices(4 * 10**9),
        "accessor-count-past-its-view": accessor0(count=10**6),
        "accessor-offset-past-its-view": accessor0(byteOffset=10**6),
        "accessor-stride-past-its-view": view0_stride,
        "accessor-missing-view": accessor0(bufferView=99),
        "accessor-bad-component-type": accessor0(componentType=1234),
        "yfov-0": yfov(0.0),
        "yfov-3.2": yfov(3.2),
    }
    return cornell_variant(changes[name])


# (scene, expected field, words of the message)
HOSTILE = [
    ("shared-children", "scene.nodes[5].children[1]", "already a child of node 5"),
    ("cycle", "scene.nodes[6].children", "cycle"),
    ("required-extension", "scene.extensionsRequired[0]", "EXT_made_up"),
    ("1e8-vertices-without-data", "scene.accessors[12]", "bufferView"),
    ("4e9-vertices-without-data", "scene.accessors[12]", "bufferView"),
    ("index-out-of-range", "scene.meshes[0].primitives[0]", "out of range"),
    ("accessor-count-past-its-view", "scene.accessors[0]", "exceeds its buffer view"),
    ("accessor-offset-past-its-view", "scene.accessors[0]", "exceeds its buffer view"),
    ("accessor-stride-past-its-view", "scene.accessors[0]", "exceeds its buffer view"),
    ("accessor-missing-view", "scene.accessors[0]", "'bufferView'"),
    ("accessor-bad-component-type", "scene", "componentType` in accessor"),
    ("yfov-0", "scene.cameras[0].perspective.yfov", "outside (0, pi)"),
    ("yfov-3.2", "scene.cameras[0].perspective.yfov", "outside (0, pi)"),
    ("number-1e400", "scene", "1e400"),
]


@pytest.fixture(scope="module")
def plain_farm(tmp_path_factory):
    """The default limits, no workers: refusals happen at submission."""
    with LocalFarm(workers=0, data_dir=tmp_path_factory.mktemp("plain")) as farm:
        yield farm


@pytest.fixture(scope="module")
def guarded_farm(tmp_path_factory):
    """One worker, and scene limits small enough to test: 12 nodes, 40 triangles over every
    mesh use (the Cornell box has 5 nodes and 32 triangles), 2 MB of scene memory, 4096
    texture pixels (one 64x64 image)."""
    env = {
        "RENDERFARM_MAX_SCENE_NODES": "12",
        "RENDERFARM_MAX_SCENE_TRIANGLES": "40",
        "RENDERFARM_MAX_SCENE_MEMORY_MB": "2",
        "RENDERFARM_MAX_TEXTURE_PIXELS": "4096",
    }
    data = tmp_path_factory.mktemp("guarded")
    with LocalFarm(workers=1, threads=1, data_dir=data, env=env) as farm:
        yield farm


def _post(client: Client, data: bytes, filename: str = "hostile.glb"):
    return client.http.post(
        "/api/v1/jobs",
        files={"scene": (filename, data, "application/octet-stream")},
        data={"settings": json.dumps(TINY)},
    )


@pytest.mark.parametrize(("name", "field", "words"), HOSTILE, ids=[c[0] for c in HOSTILE])
def test_a_scene_the_loader_refuses_is_a_400_naming_the_gltf_path(plain_farm, name, field, words):
    with Client(plain_farm.url) as client:
        before = len(client.list()["jobs"])
        r = _post(client, hostile(name), f"{name}.glb")
        assert r.status_code == 400, r.text
        body = r.json()
        assert body["field"] == field and words in body["detail"], body
        # The message names the upload, never a path on the server or a worker.
        assert body["detail"].startswith(f"{name}.glb: "), body
        assert "/tmp" not in body["detail"] and "/root" not in body["detail"], body
        assert len(client.list()["jobs"]) == before


def test_grpc_refuses_the_same_scene_with_the_same_field(plain_farm):
    with grpc.insecure_channel(plain_farm.grpc_address) as channel:
        stub = jobs_pb2_grpc.JobServiceStub(channel)
        request = jobs_pb2.SubmitJobRequest(
            scene_data=hostile("shared-children"),
            scene_filename="dag.glb",
            settings=jobs_pb2.RenderSettings(width=32, height=32, max_spp=4),
        )
        with pytest.raises(grpc.RpcError) as info:
            stub.SubmitJob(request, timeout=60)
    assert info.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    metadata = dict(info.value.trailing_metadata() or ())
    assert metadata.get("renderfarm-field") == "scene.nodes[5].children[1]", metadata


def grid_glb(quads_per_side: int) -> bytes:
    """A flat grid of 2 x n^2 triangles, built here with plain struct packing."""
    n = quads_per_side
    positions = b"".join(
        struct.pack("<3f", x / n, y / n, 0.0) for y in range(n + 1) for x in range(n + 1)
    )
    indices = b"".join(
        struct.pack("<6I", a, a + 1, a + n + 2, a, a + n + 2, a + n + 1)
        for a in (y * (n + 1) + x for y in range(n) for x in range(n))
    )
    doc = {
        "asset": {"version": "2.0"},
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": (n + 1) ** 2, "type": "VEC3",
             "min": [0, 0, 0], "max": [1, 1, 0]},
            {"bufferView": 1, "componentType": 5125, "count": 6 * n * n, "type": "SCALAR"},
        ],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": len(positions)},
            {"buffer": 0, "byteOffset": len(positions), "byteLength": len(indices)},
        ],
        "buffers": [{"byteLength": len(positions) + len(indices)}],
    }  # fmt: skip
    blob = positions + indices
    blob += b"\0" * (-len(blob) % 4)
    return join_glb(doc, struct.pack("<II", len(blob), 0x004E4942) + blob)


def test_the_server_limits_are_the_loaders_limits(guarded_farm):
    with Client(guarded_farm.url) as client:

        def extra_nodes(doc: dict) -> None:
            doc["nodes"] += [{} for _ in range(8)]  # 13 nodes: one over the limit

        r = _post(client, cornell_variant(extra_nodes), "many-nodes.glb")
        assert (r.status_code, r.json()["field"]) == (400, "scene.nodes"), r.text
        assert "over the limit of 12" in r.json()["detail"]

        def second_use(doc: dict) -> None:
            doc["nodes"].append({"mesh": 0})  # the white walls (10+ triangles) once more
            doc["scenes"][0]["nodes"].append(len(doc["nodes"]) - 1)

        r = _post(client, cornell_variant(second_use), "instanced.glb")
        assert r.status_code == 400 and "more than 40 triangles" in r.json()["detail"], r.text
        assert r.json()["field"].startswith("scene.nodes["), r.text


def png(width: int, height: int) -> bytes:
    """A grey 8-bit RGB PNG, written here from the PNG specification (zlib, CRC32)."""
    import zlib

    def chunk(kind: bytes, body: bytes) -> bytes:
        crc = zlib.crc32(kind + body) & 0xFFFFFFFF
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", crc)

    rows = b"".join(b"\0" + b"\x80" * (3 * width) for _ in range(height))
    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header)
            + chunk(b"IDAT", zlib.compress(rows)) + chunk(b"IEND", b""))  # fmt: skip


def textured(*sizes: tuple[int, int]):
    def change(doc: dict) -> None:
        import base64

        doc["images"] = [
            {"uri": "data:image/png;base64," + base64.b64encode(png(w, h)).decode()}
            for w, h in sizes
        ]
        doc["textures"] = [{"source": i} for i in range(len(sizes))]
        doc["materials"][0].setdefault("pbrMetallicRoughness", {})["baseColorTexture"] = {
            "index": 0
        }

    return change


def test_texture_pixels_are_limited_from_the_images_headers(guarded_farm):
    with Client(guarded_farm.url) as client:
        # 64 x 64 = 4096 pixels: at the limit, accepted; a second 8 x 8 image goes over it.
        assert _post(client, cornell_variant(textured((64, 64))), "t1.glb").status_code == 201
        r = _post(client, cornell_variant(textured((64, 64), (8, 8))), "t2.glb")
        assert (r.status_code, r.json()["field"]) == (400, "scene.textures[1]"), r.text
        assert "4160 pixels" in r.json()["detail"] and "limit of 4096" in r.json()["detail"]


def test_an_accepted_scene_renders(guarded_farm):
    with Client(guarded_farm.url) as client:
        job = client.submit(CORNELL, settings=TINY, name="fine")
        done = client.wait(job["id"], timeout_s=120)
        assert done["state"] == "completed", done


@pytest.fixture(scope="module")
def memory_farm(tmp_path_factory):
    env = {"RENDERFARM_MAX_SCENE_MEMORY_MB": "2"}
    with LocalFarm(workers=0, data_dir=tmp_path_factory.mktemp("memory"), env=env) as farm:
        yield farm


def test_a_scene_over_the_memory_estimate_is_refused(memory_farm):
    with Client(memory_farm.url) as client:
        # 2 x 30^2 = 1,800 triangles: about 0.2 MB, accepted. 2 x 150^2 = 45,000 triangles
        # need at least 45,000 x (12 index + 12 face normal + 5 material and flags) bytes of
        # arrays alone, 1.3 MB, and Embree's BVH as much again: over 2 MB.
        assert _post(client, grid_glb(30), "small-grid.glb").status_code == 201
        r = _post(client, grid_glb(150), "grid.glb")
        assert (r.status_code, r.json()["field"]) == (400, "scene.meshes"), r.text
        assert "over the limit of 2.0 MB" in r.json()["detail"], r.text


def test_a_task_over_the_workers_time_budget_fails_the_job(tmp_path):
    """A worker with a 1 s task budget: the render stops and the job fails with the budget's
    message instead of spinning."""
    with LocalFarm(workers=0, data_dir=tmp_path) as farm:
        farm.add_workers(1, threads=1, extra_args=["--task-timeout-s", "1"])
        with Client(farm.url) as client:
            # Uniform batches (no noise threshold) of up to 64 spp over one 512x512 tile: 16M
            # paths a batch, many seconds on one thread.
            settings = {"width": 512, "height": 512, "tile_size": 512, "max_spp": 256,
                        "noise_threshold": 0}  # fmt: skip
            job = client.submit(CORNELL, settings=settings)
            done = client.wait(job["id"], timeout_s=180)
    assert done["state"] == "failed", done
    assert "time budget of 1 s" in done["error"], done
    assert "/" not in done["error"].split("time budget")[0], done  # no local paths


def test_a_worker_refuses_a_scene_over_its_own_memory_and_names_no_local_path(tmp_path):
    """The server (default limits) accepts a 45,000-triangle grid; a worker allowed 1 MB of
    scene memory refuses it before allocating it, for good, and the job's error names the
    scene by its hash, not by the worker's cache path."""
    with LocalFarm(workers=0, data_dir=tmp_path) as farm:
        farm.add_workers(1, threads=1, extra_args=["--max-scene-memory-mb", "1"])
        with Client(farm.url) as client:
            path = tmp_path / "grid.glb"
            path.write_bytes(grid_glb(150))
            job = client.submit(path, settings=TINY)
            done = client.wait(job["id"], timeout_s=120)
    assert done["state"] == "failed", done
    error = done["error"]
    assert f"scene {job['scene_sha256'][:12]}: meshes: " in error, error
    assert "over the limit of 1.0 MB" in error, error
    assert "/" not in error, error


def test_cancel_reaches_a_running_render(tmp_path):
    """Cancel a job while its only worker is rendering a long batch: the worker stops within
    a second (its heartbeats then report no busy thread)."""
    with LocalFarm(workers=1, threads=1, data_dir=tmp_path) as farm, Client(farm.url) as client:
        settings = {"width": 512, "height": 512, "tile_size": 512, "max_spp": 4096,
                    "noise_threshold": 0}  # fmt: skip
        job = client.submit(CORNELL, settings=settings)
        wait_until(
            lambda: any(w["busy_threads"] for w in client.workers()),
            timeout_s=60,
            what="the worker to report a busy thread",
        )
        client.cancel(job["id"])
        wait_until(
            lambda: all(not w["busy_threads"] for w in client.workers()),
            timeout_s=10,
            what="the worker to stop rendering the cancelled job",
        )
