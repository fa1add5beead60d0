"""The CLI's errors as a user meets them: one line `renderfarm: MESSAGE` on stderr, never a
traceback, and exit 1 (refused or failed), 2 (usage, a local file missing or unreadable) or 130
(Ctrl-C)."""

from __future__ import annotations

import json
import os
import pty
import re
import select
import signal
import socket
import subprocess
import sys
import time

import pytest

from renderfarm.cli.localfarm import LocalFarm, free_port
from renderfarm.client import Client

from .conftest import CORNELL
from .test_auth import _self_signed
from .waiting import wait_until

CLI = [sys.executable, "-m", "renderfarm"]
# The CLI as a terminal starts it, with SIGINT at its default. A test runner started in the
# background by a non-interactive shell (`make test &`) has SIGINT ignored, its children inherit
# that, and Python keeps an inherited SIG_IGN: Ctrl-C would then be a no-op, as it should for a
# background job. exec keeps SIG_DFL, so the child below sees Ctrl-C as a terminal's would.
CLI_AT_A_TERMINAL = [
    sys.executable, "-c",
    "import os, signal, sys; signal.signal(signal.SIGINT, signal.SIG_DFL); "
    "os.execv(sys.executable, [sys.executable, '-m', 'renderfarm', *sys.argv[1:]])",
]  # fmt: skip
TINY = ["--width", "32", "--height", "32", "--tile-size", "16", "--spp", "4"]


def _env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("RENDERFARM_")}
    return {**env, **extra}


def _run(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(CLI + list(args), capture_output=True, text=True, timeout=120,
                          env=env or _env())  # fmt: skip


def _fails_with(done: subprocess.CompletedProcess, code: int, line: str) -> None:
    assert "Traceback" not in done.stderr, done.stderr
    assert done.stderr.splitlines() == [line], done.stderr
    assert done.returncode == code, done.stderr


@pytest.fixture(scope="module")
def idle_farm(tmp_path_factory):
    """A farm without workers: its jobs stay queued."""
    with LocalFarm(workers=0, data_dir=tmp_path_factory.mktemp("idle")) as farm:
        yield farm


@pytest.fixture()
def no_meshes(tmp_path):
    path = tmp_path / "empty.gltf"
    path.write_text(json.dumps({"asset": {"version": "2.0"}}))
    return path


def test_local_files_that_are_missing_or_not_files_are_usage_errors(tmp_path, no_meshes):
    dead = f"http://127.0.0.1:{free_port()}"  # nothing is asked of it: the checks come first
    missing, directory = tmp_path / "missing.glb", tmp_path
    exr = str(tmp_path / "out.exr")
    for command in (["submit"], ["render", "-o", exr]):
        _fails_with(_run(*command, str(missing), "--url", dead), 2,
                    f"renderfarm: scene file not found: {missing}")  # fmt: skip
        _fails_with(_run(*command, str(directory), "--url", dead), 2,
                    f"renderfarm: scene file is a directory, not a file: {directory}")  # fmt: skip
        _fails_with(
            _run(*command, str(CORNELL), "--environment", str(tmp_path / "sky.hdr"), "--url", dead),
            2, f"renderfarm: environment map not found: {tmp_path / 'sky.hdr'}",
        )  # fmt: skip
        # The client packs a .gltf and refuses what the server would, naming the field.
        _fails_with(_run(*command, str(no_meshes), "--url", dead), 1,
                    f"renderfarm: {no_meshes}: the scene has no meshes, so there is nothing to "
                    "render [scene.meshes]")  # fmt: skip
    _fails_with(_run("render", str(CORNELL), "-o", str(tmp_path / "x.png")), 2,
                "renderfarm: -o must name an .exr file (a .png is written beside it)")  # fmt: skip
    _fails_with(_run("render", str(CORNELL), "-o", str(tmp_path / "s_##.exr")), 2,
                "renderfarm: -o has a #### frame number but no --frames were given")  # fmt: skip
    _fails_with(_run("render", str(CORNELL), "-o", exr, "--movie", str(tmp_path / "m.mp4")), 2,
                "renderfarm: --movie needs --frames (a still has no movie)")  # fmt: skip
    _fails_with(
        _run("render", str(CORNELL), "-o", exr, "--frames", "1-2", "--movie", exr), 2,
        "renderfarm: --movie must name an .mp4 file",
    )  # fmt: skip
    _fails_with(_run("get", "0123456789ab", "-o", exr, "--movie", "m.mp4", "--url", dead), 2,
                "renderfarm: -o and --movie download one thing each: give one")  # fmt: skip


def test_every_client_command_reports_a_server_that_is_not_running():
    url = f"http://127.0.0.1:{free_port()}"
    line = f"renderfarm: cannot connect to {url}: connection refused (is the server running?)"
    for command in (
        ["submit", str(CORNELL)],
        ["submit", str(CORNELL), "--wait"],
        ["render", str(CORNELL), "-o", "/tmp/never-written.exr"],
        ["ls"],
        ["get", "0123456789ab"],
        ["watch", "0123456789ab"],
        ["cancel", "0123456789ab"],
        ["rm", "0123456789ab"],
        ["workers"],
    ):
        _fails_with(_run(*command, "--url", url), 1, line)
        _fails_with(_run(*command, env=_env(RENDERFARM_URL=url)), 1, line)


def test_bad_client_settings_are_usage_errors():
    url = f"http://127.0.0.1:{free_port()}"
    _fails_with(_run("ls", "--url", "ftp://farm"), 2,
                "renderfarm: bad server URL 'ftp://farm': give http://HOST:PORT or "
                "https://HOST:PORT")  # fmt: skip
    _fails_with(_run("ls", env=_env(RENDERFARM_URL=url, RENDERFARM_TIMEOUT_S="soon")), 2,
                "renderfarm: RENDERFARM_TIMEOUT_S must be a positive number of seconds, not "
                "'soon'")  # fmt: skip
    done = _run("ls", env=_env(RENDERFARM_URL=url, RENDERFARM_CA_FILE="/no/such/ca.pem"))
    _fails_with(done, 2, "renderfarm: cannot read RENDERFARM_CA_FILE /no/such/ca.pem: "
                "[Errno 2] No such file or directory")  # fmt: skip


def test_bad_server_settings_and_a_busy_port_are_reported_in_one_line(tmp_path):
    done = _run("server", env=_env(RENDERFARM_HTTP_PORT="eighty"))
    _fails_with(done, 2, "renderfarm: server setting --http-port (RENDERFARM_HTTP_PORT): Input "
                "should be a valid integer, unable to parse string as an integer")  # fmt: skip
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        done = _run("--log-level", "error", "server", "--data-dir", str(tmp_path / "d"),
                    "--http-port", str(port), "--grpc-port", "0")  # fmt: skip
    assert "Traceback" not in done.stderr and done.returncode == 1, done.stderr
    assert done.stderr.splitlines()[-1] == (
        f"renderfarm: cannot listen for HTTP on 127.0.0.1:{port}: Address already in use"
    ), done.stderr


def test_an_https_server_whose_certificate_is_not_trusted(tmp_path):
    cert, key = _self_signed(tmp_path)
    env = {"RENDERFARM_TLS_CERT_FILE": cert, "RENDERFARM_TLS_KEY_FILE": key}
    farm = LocalFarm(workers=0, data_dir=tmp_path / "d", env=env)
    url = f"https://127.0.0.1:{farm.http_port}"
    with Client(url, ca_file=cert) as client:
        try:
            _start_tls_server(farm, client)
            _fails_with(_run("ls", "--url", url), 1,
                        f"renderfarm: cannot verify the TLS certificate of {url} (self-signed "
                        "certificate); set RENDERFARM_CA_FILE to the PEM certificate of the CA "
                        "that signed it")  # fmt: skip
            trusted = _run("ls", "--url", url, env=_env(RENDERFARM_CA_FILE=cert))
            assert trusted.returncode == 0 and trusted.stdout.startswith("ID"), trusted.stderr
        finally:
            farm.stop()


def _start_tls_server(farm: LocalFarm, client: Client) -> None:
    """LocalFarm waits for readiness over plain http; this one serves https only."""
    args = CLI + ["server", "--http-port", str(farm.http_port), "--grpc-port",
                  str(farm.grpc_port), "--data-dir", str(farm.data_dir)]  # fmt: skip
    farm.data_dir.mkdir(parents=True)
    log = open(farm.data_dir / "server.log", "ab")  # noqa: SIM115
    farm.server = subprocess.Popen(args, stdout=log, stderr=subprocess.STDOUT,
                                   env={**os.environ, **farm.env})  # fmt: skip

    def ready() -> bool:
        assert farm.server.poll() is None, (farm.data_dir / "server.log").read_text()
        return client.ready()

    wait_until(ready, 120, "the TLS server to be ready", poll_s=0.2)


def test_refusals_and_unfinished_jobs_are_one_line(idle_farm):
    env = _env(RENDERFARM_URL=idle_farm.url)
    _fails_with(_run("get", "0123456789ab", env=env), 1,
                "renderfarm: no job with id '0123456789ab'")  # fmt: skip
    _fails_with(_run("submit", str(CORNELL), "--sampler", "magic", env=env), 1,
                "renderfarm: settings.sampler must be one of sobol, halton, stratified, "
                "independent [settings.sampler]")  # fmt: skip
    with Client(idle_farm.url) as client:
        job = client.submit(CORNELL, settings={"width": 32, "height": 32})
        client.cancel(job["id"])
    watched = _run("watch", job["id"], env=env)
    assert watched.returncode == 1 and "Traceback" not in watched.stderr
    *progress, last = watched.stderr.splitlines()
    assert last == f"renderfarm: job {job['id']} cancelled"
    assert "tiles" in progress[-1] and progress[-1].endswith("cancelled")


def _await_stderr(proc: subprocess.Popen, words: str, deadline: float) -> str:
    seen = b""
    while words.encode() not in seen:
        assert time.monotonic() < deadline, f"no {words!r} on stderr: {seen.decode()!r}"
        ready, _, _ = select.select([proc.stderr], [], [], max(0.0, deadline - time.monotonic()))
        if ready:
            chunk = os.read(proc.stderr.fileno(), 65536)
            assert chunk, f"stderr closed (exit {proc.wait()}) before {words!r}: {seen!r}"
            seen += chunk
    return seen.decode()


def _exit_or_stacks(proc: subprocess.Popen, timeout: float) -> str:
    """The rest of the process's stderr once it exits; if it does not within timeout, fail
    with the Python stacks faulthandler (PYTHONFAULTHANDLER) prints on SIGABRT."""
    try:
        return proc.communicate(timeout=timeout)[1].decode()
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGABRT)
        stacks = proc.communicate(timeout=30)[1].decode()
        pytest.fail(f"{proc.args} still running {timeout} s after Ctrl-C:\n{stacks}")


def test_ctrl_c_exits_130_quietly_and_render_cancels_its_job(idle_farm, tmp_path):
    env = _env(RENDERFARM_URL=idle_farm.url, PYTHONFAULTHANDLER="1")
    with Client(idle_farm.url) as client:
        queued = client.submit(CORNELL, settings={"width": 32, "height": 32})
    deadline = time.monotonic() + 120
    for command in (
        ["watch", queued["id"]],
        [
            "render",
            str(CORNELL),
            "-o",
            str(tmp_path / "x.exr"),
            "--url",
            idle_farm.url,
            "--name",
            "ctrl-c",
            *TINY,
        ],
    ):
        proc = subprocess.Popen(CLI_AT_A_TERMINAL + command, stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, env=env)  # fmt: skip
        seen = _await_stderr(proc, "queued", deadline)  # following the job now
        proc.send_signal(signal.SIGINT)
        stderr = seen + _exit_or_stacks(proc, 60)
        assert proc.returncode == 130, stderr
        assert "Traceback" not in stderr and "renderfarm:" not in stderr, stderr
    with Client(idle_farm.url) as client:
        (rendered,) = [j for j in client.list()["jobs"] if j["name"] == "ctrl-c"]
        assert rendered["state"] == "cancelled"
    assert f"cancelled job {rendered['id']}" in stderr


def test_on_a_terminal_watch_draws_a_rich_progress_bar(idle_farm):
    with Client(idle_farm.url) as client:
        job = client.submit(CORNELL, settings={"width": 32, "height": 32, "tile_size": 16})
        client.cancel(job["id"])
    controller, terminal = pty.openpty()
    proc = subprocess.Popen(
        CLI + ["watch", job["id"], "--url", idle_farm.url], stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE, stderr=terminal,
        env=_env(TERM="xterm-256color", COLUMNS="160", LINES="40"),
    )  # fmt: skip
    os.close(terminal)
    drawn = b""
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        ready, _, _ = select.select([controller], [], [], max(0.0, deadline - time.monotonic()))
        if not ready:
            continue
        try:
            chunk = os.read(controller, 65536)
        except OSError:  # EIO: the CLI closed the terminal
            break
        if not chunk:
            break
        drawn += chunk
    os.close(controller)
    assert proc.wait(timeout=60) == 1
    text = drawn.decode(errors="replace")
    assert "\x1b[" in text and "━" in text, text  # rich's live bar, not the plain line
    text = re.sub(r"\x1b\[[0-9;?]*[A-Za-z]", "", text)  # its colours and cursor moves
    assert "0/4 tiles" in text and "cancelled" in text and "[-----" not in text, text
    assert f"renderfarm: job {job['id']} cancelled" in text and "Traceback" not in text
