"""The client commands of the CLI against a running farm, scripted through --json."""

from __future__ import annotations

import json
import os
import select
import subprocess
import sys
import time

import httpx
import pytest

from renderfarm.cli.localfarm import LocalFarm, spawn_workers
from renderfarm.client import Client

from .conftest import CORNELL, ROOT

CLI = [sys.executable, "-m", "renderfarm"]
TINY = ["--width", "32", "--height", "32", "--tile-size", "16", "--spp", "4"]


def _run(farm, *args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    environment = {**os.environ, "RENDERFARM_URL": farm.url, **(env or {})}
    environment.pop("RENDERFARM_TOKEN", None)
    return subprocess.run(CLI + list(args), capture_output=True, text=True, timeout=300,
                          env={**environment, **(env or {})})  # fmt: skip


def test_submit_watch_get_ls_rm_with_json(farm):
    submitted = _run(farm, "submit", str(CORNELL), "--json", "--name", "cli", *TINY)
    assert submitted.returncode == 0, submitted.stderr
    job = json.loads(submitted.stdout)
    watched = _run(farm, "watch", job["id"], "--json")
    assert watched.returncode == 0, watched.stderr
    updates = [json.loads(line) for line in watched.stdout.splitlines()]
    assert updates and updates[-1]["state"] == "completed"
    got = json.loads(_run(farm, "get", job["id"], "--json").stdout)
    assert got["progress"]["mean_spp"] == 4 and got["stops"]
    listed = json.loads(_run(farm, "ls", "--json", "--limit", "500").stdout)
    assert job["id"] in {j["id"] for j in listed["jobs"]}
    workers = json.loads(_run(farm, "workers", "--json").stdout)
    assert len(workers) == 2
    removed = _run(farm, "rm", job["id"])
    assert removed.returncode == 0 and f"{job['id']} deleted" in removed.stdout
    gone = _run(farm, "get", job["id"])
    assert gone.returncode == 1 and "no job" in gone.stderr


def test_watch_draws_a_progress_bar_and_cancel_works(farm):
    submitted = _run(farm, "submit", str(CORNELL), *TINY[:-2], "--spp", "100000",
                     "--noise-threshold", "0.0001")  # fmt: skip
    job_id = submitted.stdout.strip()
    cancelled = _run(farm, "cancel", job_id, "--json")
    assert json.loads(cancelled.stdout)["state"] == "cancelled"
    watched = _run(farm, "watch", job_id)
    assert watched.returncode == 1  # the job did not complete, and the last line says so
    *_, line, verdict = watched.stderr.strip().splitlines()
    assert "tiles" in line and "spp" in line and "ETA" in line and "cancelled" in line
    assert verdict == f"renderfarm: job {job_id} cancelled"


def test_a_wrong_token_from_the_environment_is_reported(farm):
    done = _run(farm, "ls", env={"RENDERFARM_TOKEN": "rf_wrong"})
    assert done.returncode == 1 and "unknown API token" in done.stderr
    assert "[authorization]" in done.stderr


def _await_line(proc: subprocess.Popen, words: str, deadline: float) -> str:
    """Read proc's stderr (a binary pipe) until a line containing `words`, by the deadline."""
    seen = b""
    while True:
        remaining = deadline - time.monotonic()
        assert remaining > 0, f"no line with {words!r} on stderr: {seen.decode()!r}"
        ready, _, _ = select.select([proc.stderr], [], [], remaining)
        if not ready:
            continue
        chunk = os.read(proc.stderr.fileno(), 65536)
        assert chunk, f"stderr closed (exit {proc.wait()}) before {words!r}: {seen.decode()!r}"
        seen += chunk
        for line in seen.decode(errors="replace").splitlines():
            if words in line:
                return line


def test_watchers_follow_a_job_queued_longer_than_their_read_timeout(tmp_path, worker_binary):
    """A farm without workers keeps the jobs queued; the server's keep-alive comments (every
    0.5 s here) hold the streams of `submit --wait`, `watch` and `render` open for longer than
    the client's read timeout (2 s here), and once a worker joins, each of them exits 0."""
    timeout_s = 2.0
    env = {"RENDERFARM_SSE_PING_INTERVAL_S": "0.5"}
    with LocalFarm(workers=0, data_dir=tmp_path / "farm", env=env) as farm:
        cli_env = {**os.environ, "RENDERFARM_URL": farm.url, "RENDERFARM_TIMEOUT_S": "2"}
        cli_env.pop("RENDERFARM_TOKEN", None)

        def start(*args: str) -> subprocess.Popen:
            return subprocess.Popen(CLI + list(args), stdout=subprocess.PIPE,
                                    stderr=subprocess.PIPE, env=cli_env)  # fmt: skip

        deadline = time.monotonic() + 120
        waiting = start("submit", str(CORNELL), "--wait", "--name", "queued-wait", *TINY)
        _await_line(waiting, "queued", deadline)
        with Client(farm.url) as client:
            (job,) = [j for j in client.list()["jobs"] if j["name"] == "queued-wait"]
        watching = start("watch", job["id"])
        _await_line(watching, "queued", deadline)
        out = tmp_path / "queued.exr"
        rendering = start("render", str(CORNELL), "-o", str(out), "--url", farm.url, *TINY)
        _await_line(rendering, "queued", deadline)
        followed_from = time.monotonic()  # all three are now following a queued job

        # The raw stream: the job's event as always, then only keep-alive comments.
        pings: list[float] = []
        url = f"{farm.url}/api/v1/jobs/{job['id']}/watch"
        try:
            with httpx.stream("GET", url, timeout=httpx.Timeout(5.0)) as stream:
                lines = stream.iter_lines()
                assert next(lines) == "event: job"
                first = next(lines)
                assert first.startswith("data: ")
                assert json.loads(first[len("data: ") :])["state"] == "queued"
                for line in lines:
                    assert time.monotonic() < deadline, "the keep-alives were not seen in time"
                    assert not line.startswith(("event:", "data:")), line  # nothing changed
                    if line.startswith(":"):
                        pings.append(time.monotonic())
                    if len(pings) >= 3 and pings[-1] - followed_from > 3 * timeout_s:
                        break
        except httpx.ReadTimeout:
            pytest.fail(f"the stream went silent for 5 s after {len(pings)} keep-alives")
        assert max(b - a for a, b in zip(pings, pings[1:], strict=False)) < timeout_s
        for proc in (waiting, watching, rendering):
            assert proc.poll() is None, proc.stderr.read().decode()  # still following

        farm.worker_procs += spawn_workers(1, farm.grpc_address, threads=1)
        for proc in (waiting, watching, rendering):
            stdout, stderr = proc.communicate(timeout=max(1.0, deadline - time.monotonic()))
            assert proc.returncode == 0, stderr.decode()
            assert "Traceback" not in stderr.decode() and "completed" in stderr.decode()
        assert stdout.decode().splitlines()[0] == f"EXR: {out}" and out.is_file()


def test_submit_takes_the_example_usd_scene_as_a_user_makes_it(farm, tmp_path):
    """examples/make_usd_scene.py writes the .usdz; `renderfarm submit` sends it as it is; the
    server converts it and the job renders, its EXR naming the package as its source."""
    import hashlib

    import OpenImageIO as oiio

    package = tmp_path / "still-life.usdz"
    made = subprocess.run(
        [sys.executable, str(ROOT / "examples" / "make_usd_scene.py"), "-o", str(package)],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert made.returncode == 0, made.stderr
    submitted = _run(farm, "submit", str(package), "--json", *TINY)
    assert submitted.returncode == 0, submitted.stderr
    job = json.loads(submitted.stdout)
    assert job["name"] == "still-life"  # the CLI's default: the file's stem
    watched = _run(farm, "watch", job["id"], "--json")
    assert watched.returncode == 0, watched.stderr
    assert json.loads(watched.stdout.splitlines()[-1])["state"] == "completed"
    exr = tmp_path / "still-life.exr"
    got = _run(farm, "get", job["id"], "-o", str(exr))
    assert got.returncode == 0, got.stderr
    spec = oiio.ImageInput.open(str(exr)).spec()
    source = hashlib.sha256(package.read_bytes()).hexdigest()
    assert spec.getattribute("renderfarm:scene_source_sha256") == source
    assert spec.getattribute("renderfarm:scene_source_filename") == "still-life.usdz"
