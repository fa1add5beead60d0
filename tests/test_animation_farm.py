"""Frame sequences on a real farm (docs/animation.md): every frame of an animation job equals
the same pose rendered alone by `renderfarm-worker render --time f/fps --seed frame_seed`, bit
for bit whether one worker or three rendered it, and after a worker or the server is killed in
the middle of the sequence; the CLI writes the sequence and its preview movie.

The scene is the project's example, examples/make_hinged_box.py (a lid on a hinge, a skinned
stalk, a moving camera). The frame seed is computed here from its definition in
docs/architecture.md ("Determinism"), not taken from the worker.
"""

from __future__ import annotations

import json
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import psycopg
import pytest

from renderfarm.cli.localfarm import LocalFarm
from renderfarm.client import ApiError, Client
from renderfarm.infra.images import read_exr

from .conftest import ROOT
from .waiting import wait_until

FPS = 24
MASK = (1 << 64) - 1
FAST_LEASES = {
    "RENDERFARM_LEASE_S": "2",
    "RENDERFARM_HEARTBEAT_INTERVAL_S": "0.5",
    "RENDERFARM_CHECKPOINT_INTERVAL_S": "0.5",
}


def splitmix64(x: int) -> int:
    z = (x + 0x9E3779B97F4A7C15) & MASK
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & MASK
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & MASK
    return z ^ (z >> 31)


def frame_seed(seed: int, frame: int) -> int:
    return splitmix64(seed ^ splitmix64(frame & MASK))


def test_the_frame_seed_is_splitmix64_as_published():
    # SplitMix64 (Steele, Lea and Flood 2014) seeded with 0: its first output.
    assert splitmix64(0) == 0xE220A8397B1DCDAF
    assert frame_seed(7, -1) != frame_seed(7, 1)


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("scene") / "hinged-box.glb"
    script = ROOT / "examples" / "make_hinged_box.py"
    subprocess.run([sys.executable, str(script), "-o", str(out)], check=True, timeout=60)
    return out


def settings(frames: str, spp: int) -> dict:
    return {"width": 64, "height": 48, "tile_size": 16, "max_spp": spp, "noise_threshold": 0,
            "seed": 11, "frames": frames, "fps": FPS}  # fmt: skip


def frame_numbers(frames: str) -> list[int]:
    first, last = (int(x) for x in frames.split("-"))
    return list(range(first, last + 1))


def rgb(path: Path) -> np.ndarray:
    ch = read_exr(str(path))
    return np.stack([ch["R"], ch["G"], ch["B"]], axis=-1)


def alone(worker: str, scene: Path, frame: int, spp: int, out: Path) -> np.ndarray:
    """The frame rendered by the standalone worker: its pose at frame / fps, its seed."""
    args = [worker, "render", str(scene), "-o", str(out), "--threads", "2", "--width", "64"]
    args += ["--height", "48", "--spp", str(spp), "--seed", str(frame_seed(11, frame))]
    args += ["--time", repr(frame / FPS)]
    subprocess.run(args, check=True, capture_output=True, timeout=600)
    return rgb(out)


def references(worker: str, scene: Path, frames: str, spp: int, where: Path) -> dict:
    where.mkdir(parents=True, exist_ok=True)
    return {f: alone(worker, scene, f, spp, where / f"{f}.exr") for f in frame_numbers(frames)}


def farm_exrs(client: Client, job_id: str, where: Path) -> dict[int, dict[str, np.ndarray]]:
    """Every frame's EXR, every layer (colour, variance, spp, albedo, normal, ...)."""
    where.mkdir(parents=True, exist_ok=True)
    out = {}
    for f in client.frames(job_id):
        path = where / f"{f['frame']}.exr"
        client.save_image(job_id, path, "exr", frame=f["frame"])
        out[f["frame"]] = read_exr(str(path))
    return out


def farm_frames(client: Client, job_id: str, where: Path) -> dict[int, np.ndarray]:
    return {f: np.stack([ch["R"], ch["G"], ch["B"]], axis=-1)
            for f, ch in farm_exrs(client, job_id, where).items()}  # fmt: skip


def assert_frames_equal_references(got: dict, want: dict) -> None:
    assert sorted(got) == sorted(want)
    for f in want:
        # The farm's tiles and batches sum in another order than one process: float32 rounding.
        np.testing.assert_allclose(got[f], want[f], rtol=1e-6, atol=1e-7, err_msg=f"frame {f}")


def test_one_and_three_workers_render_every_frame_alike(scene, worker_binary, tmp_path):
    frames, spp = "1-4", 32
    want = references(worker_binary, scene, frames, spp, tmp_path / "alone")
    # The poses differ: the lid opens, the camera moves (a frame is not the first one again).
    assert not np.allclose(want[1][..., :3], want[4][..., :3], atol=0.05)
    runs = []
    with LocalFarm(workers=1, data_dir=tmp_path / "farm", threads=1) as farm:
        with Client(farm.url, timeout=60) as client:
            for count in (1, 3):
                if count == 3:
                    farm.add_workers(2, threads=1)
                wait_until(lambda c=count: len(client.workers()) == c, 60, f"{count} workers")
                job = client.submit(scene, settings=settings(frames, spp), name=f"{count} w")
                job = client.wait(job["id"], poll_s=0.2, timeout_s=600)
                assert job["state"] == "completed", job["error"]
                p = job["progress"]
                assert p["frames_total"] == p["frames_done"] == 4
                assert p["samples_merged"] == 4 * 64 * 48 * spp
                listed = client.frames(job["id"])
                assert [f["frame"] for f in listed] == [1, 2, 3, 4]
                assert all(f["state"] == "done" and f["mean_spp"] == spp for f in listed)
                runs.append(farm_exrs(client, job["id"], tmp_path / f"farm{count}"))
                events = [e["kind"] for e in client.events(job["id"])]
                assert events.count("frame_finished") == 4
    one, three = runs
    for f in one:
        assert sorted(one[f]) == sorted(three[f])
        for name in one[f]:
            same = np.array_equal(one[f][name], three[f][name])
            assert same, f"frame {f}, channel {name} differs between 1 and 3 workers"
        assert (one[f]["spp"] == spp).all()
    rgb_one = {f: np.stack([ch["R"], ch["G"], ch["B"]], axis=-1) for f, ch in one.items()}
    assert_frames_equal_references(rgb_one, want)


def database_url(data: Path) -> str:
    return f"postgresql://postgres:@/postgres?host={data / 'pg'}"


def checkpointed_samples(data: Path, job_id: str) -> int:
    with psycopg.connect(database_url(data)) as conn:
        (spp,) = conn.execute(
            "SELECT coalesce(sum(samples), 0) FROM tiles WHERE job_id = %s", (job_id,)
        ).fetchone()
    return spp * 16 * 16  # every tile of a 64 x 48 frame is 16 x 16


@pytest.fixture(scope="module")
def long_sequence(scene, worker_binary, tmp_path_factory):
    """A sequence long enough to be interrupted in its middle, and its frames rendered alone."""
    frames, spp = "1-4", 768
    want = references(worker_binary, scene, frames, spp, tmp_path_factory.mktemp("alone"))
    return frames, spp, want


def submit_and_wait_for(client: Client, scene: Path, frames: str, spp: int, fraction: float):
    wait_until(lambda: len(client.workers()) == 2, 60, "two workers")
    job = client.submit(scene, settings=settings(frames, spp), name="interrupted")
    total = len(frame_numbers(frames)) * 64 * 48 * spp

    def merged():
        return client.get(job["id"])["progress"]["samples_merged"] / total

    wait_until(lambda: merged() > fraction, 600, f"{fraction:.0%} of the sequence merged")
    p = client.get(job["id"])["progress"]
    assert p["frames_done"] < p["frames_total"], "the sequence ended before it was interrupted"
    return job, total


def test_a_worker_killed_mid_sequence_changes_no_frame(scene, long_sequence, tmp_path):
    frames, spp, want = long_sequence
    with LocalFarm(workers=2, data_dir=tmp_path / "farm", threads=1, env=FAST_LEASES) as farm:
        with Client(farm.url, timeout=60) as client:
            job, total = submit_and_wait_for(client, scene, frames, spp, 0.3)
            victim = farm.worker_procs[0]
            victim.send_signal(signal.SIGKILL)
            victim.wait(timeout=10)
            job = client.wait(job["id"], poll_s=0.2, timeout_s=900)
            assert job["state"] == "completed", job["error"]
            assert job["progress"]["samples_merged"] == total
            assert_frames_equal_references(farm_frames(client, job["id"], tmp_path / "out"), want)


def test_the_server_killed_mid_sequence_resumes_every_frame(scene, long_sequence, tmp_path):
    frames, spp, want = long_sequence
    with LocalFarm(workers=2, data_dir=tmp_path / "farm", threads=1, env=FAST_LEASES) as farm:
        with Client(farm.url, timeout=60) as client:
            job, total = submit_and_wait_for(client, scene, frames, spp, 0.4)
            p = client.get(job["id"])["progress"]
            merged, done_before = p["samples_merged"], p["frames_done"]
            wait_until(
                lambda: checkpointed_samples(farm.data_dir, job["id"]) >= merged, 60,
                f"a checkpoint of the {merged} samples merged", poll_s=0.1,
            )  # fmt: skip
            assert client.get(job["id"])["progress"]["frames_done"] < 4, (
                "the sequence ended before the server was killed"
            )
        farm.server.send_signal(signal.SIGKILL)
        farm.server.wait(timeout=10)
        farm.start_server()
        with Client(farm.url, timeout=60) as client:
            resumed = client.get(job["id"])
            assert resumed["state"] == "running"
            assert resumed["progress"]["samples_merged"] >= merged
            assert resumed["progress"]["frames_done"] >= done_before
            job = client.wait(job["id"], poll_s=0.2, timeout_s=900)
            assert job["state"] == "completed", job["error"]
            assert job["progress"]["samples_merged"] == total
            assert job["progress"]["frames_done"] == 4
            assert_frames_equal_references(farm_frames(client, job["id"], tmp_path / "out"), want)


def ffprobe(path: Path) -> dict:
    tool = shutil.which("ffprobe")
    assert tool is not None, "ffprobe (Debian's ffmpeg package) is needed"
    out = subprocess.run(
        [tool, "-v", "error", "-select_streams", "v:0", "-count_frames", "-show_entries",
         "stream=codec_name,width,height,avg_frame_rate,nb_read_frames", "-of", "json",
         str(path)],
        check=True, capture_output=True, text=True, timeout=60,
    ).stdout  # fmt: skip
    return json.loads(out)["streams"][0]


def test_the_cli_writes_the_sequence_and_its_movie(scene, tmp_path):
    out = tmp_path / "out"
    args = [sys.executable, "-m", "renderfarm", "render", str(scene), "-o", str(out / "s_###.exr")]
    args += ["--frames", "2-4", "--fps", "12", "--width", "64", "--height", "48"]
    args += ["--max-spp", "8", "--noise-threshold", "0", "--workers", "1", "--threads", "2"]
    args += ["--data-dir", str(tmp_path / "farm"), "--quiet", "--movie", str(out / "s.mp4")]
    done = subprocess.run(args, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    for f in (2, 3, 4):
        assert (out / f"s_{f:03d}.exr").is_file() and (out / f"s_{f:03d}.png").is_file()
        assert read_exr(str(out / f"s_{f:03d}.exr"))["spp"].min() == 8
    assert not (out / "s_001.exr").exists()
    movie = ffprobe(out / "s.mp4")
    assert movie["codec_name"] == "h264"
    assert (movie["width"], movie["height"]) == (64, 48)
    assert movie["avg_frame_rate"] == "12/1"
    assert int(movie["nb_read_frames"]) == 3
    assert f"movie: {(out / 's.mp4').resolve()}" in done.stdout


def test_a_movie_is_refused_for_a_still_and_before_any_frame(scene, tmp_path):
    with LocalFarm(workers=1, data_dir=tmp_path / "farm", threads=1) as farm:
        with Client(farm.url, timeout=60) as client:
            still = client.submit(scene, settings={"width": 32, "height": 24, "max_spp": 4})
            with pytest.raises(ApiError) as e:
                client.save_movie(still["id"], tmp_path / "still.mp4")
            assert e.value.status == 404 and "still" in str(e.value)
            # A sequence waiting for another job has no frame yet.
            blocker = client.submit(scene, settings={**settings("1-2", 1 << 16)})
            waiting = client.submit(scene, settings=settings("1-2", 4), after=[blocker["id"]])
            assert client.get(waiting["id"])["state"] == "waiting"
            with pytest.raises(ApiError) as e:
                client.save_movie(waiting["id"], tmp_path / "none.mp4")
            assert e.value.status == 409 and "no frame" in str(e.value)
            client.cancel(blocker["id"])
            client.wait(still["id"], poll_s=0.2, timeout_s=300)
