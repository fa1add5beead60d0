"""A farm on this machine: the server (embedded PostgreSQL) and N worker processes."""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

from ..client import Client
from ..infra.worker_binary import find_worker_binary


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def threads_per_worker(workers: int) -> int:
    return max(1, (os.cpu_count() or 1) // max(1, workers))


WORKER_NICE = 10  # scheduling priority of local workers (spawn_workers)


def spawn_workers(
    count: int,
    grpc_address: str,
    threads: int | None = None,
    log_dir: Path | None = None,
    first_index: int = 0,
    extra_args: list[str] | None = None,
) -> list[subprocess.Popen]:
    """Start `count` workers named HOSTNAME-local-I for I from first_index (ids must differ:
    a worker connecting with the id of a connected one replaces it)."""
    binary = find_worker_binary()
    threads = threads or threads_per_worker(count)
    # Local workers share the machine with the server and its database: at a lower priority
    # (nice WORKER_NICE, for the whole process from exec) they still take every idle cycle,
    # but a preview, a download or a merge never waits behind a render thread.
    nice = ["nice", "-n", str(WORKER_NICE)] if shutil.which("nice") else []
    procs = []
    for i in range(first_index, first_index + count):
        args = [*nice, binary, "connect", "--server", grpc_address, "--threads", str(threads)]
        args += ["--id", f"{socket.gethostname()}-local-{i}", *(extra_args or [])]
        out = open(log_dir / f"worker-{i}.log", "ab") if log_dir else subprocess.DEVNULL  # noqa: SIM115
        procs.append(subprocess.Popen(args, stdout=out, stderr=subprocess.STDOUT))
    return procs


def stop_processes(procs: list[subprocess.Popen], timeout: float = 10.0) -> None:
    for p in procs:
        if p.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                p.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + timeout
    for p in procs:
        try:
            p.wait(timeout=max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


class LocalFarm:
    """Server and workers as child processes; `with LocalFarm(...) as farm:` stops them."""

    def __init__(
        self,
        workers: int = 2,
        data_dir: Path | None = None,
        http_port: int = 0,
        grpc_port: int = 0,
        threads: int | None = None,
        env: dict[str, str] | None = None,
        worker_args: list[str] | None = None,
        ca_file: str | None = None,
    ):
        """env: the server's RENDERFARM_* settings (RENDERFARM_TLS_CERT_FILE makes it serve
        https; ca_file is then the CA the farm's own client checks it against); worker_args:
        more `renderfarm-worker connect` flags (e.g. --tls --ca-file CA)."""
        self.workers = workers
        self.worker_args = list(worker_args or [])
        self.ca_file = ca_file
        self.data_dir = data_dir
        self.http_port = http_port or free_port()
        self.grpc_port = grpc_port or free_port()
        self.threads = threads
        self.env = env
        self.server: subprocess.Popen | None = None
        self.worker_procs: list[subprocess.Popen] = []

    @property
    def url(self) -> str:
        scheme = "https" if (self.env or {}).get("RENDERFARM_TLS_CERT_FILE") else "http"
        return f"{scheme}://127.0.0.1:{self.http_port}"

    @property
    def grpc_address(self) -> str:
        return f"127.0.0.1:{self.grpc_port}"

    def start(self, ready_timeout_s: float = 120.0) -> LocalFarm:
        self.start_server(ready_timeout_s)
        log_dir = Path(self.data_dir) if self.data_dir else None
        self.worker_procs = spawn_workers(
            self.workers, self.grpc_address, self.threads, log_dir, extra_args=self.worker_args
        )
        return self

    def add_workers(self, count: int, threads: int | None = None, extra_args=None, tags=()) -> None:
        """Start `count` more workers (numbered after the running ones), with more flags and
        the worker tags `tags` (--tag each)."""
        extra_args = [*(extra_args or []), *(a for t in tags for a in ("--tag", t))]
        log_dir = Path(self.data_dir) if self.data_dir else None
        self.worker_procs += spawn_workers(
            count,
            self.grpc_address,
            threads or self.threads,
            log_dir,
            first_index=len(self.worker_procs),
            extra_args=[*self.worker_args, *(extra_args or [])],
        )

    def start_server(self, ready_timeout_s: float = 120.0) -> None:
        """(Re)start the server process on the same ports and data directory."""
        args = [sys.executable, "-m", "renderfarm", "server"]
        args += ["--http-port", str(self.http_port), "--grpc-port", str(self.grpc_port)]
        if self.data_dir is not None:
            args += ["--data-dir", str(self.data_dir)]
        log_dir = Path(self.data_dir) if self.data_dir else None
        if log_dir:
            log_dir.mkdir(parents=True, exist_ok=True)
        log = open(log_dir / "server.log", "ab") if log_dir else subprocess.DEVNULL  # noqa: SIM115
        env = {**os.environ, **(self.env or {})}
        self.server = subprocess.Popen(args, stdout=log, stderr=subprocess.STDOUT, env=env)
        with Client(self.url, ca_file=self.ca_file) as client:
            deadline = time.monotonic() + ready_timeout_s
            while not client.ready():
                if self.server.poll() is not None:
                    where = f" (see {log_dir / 'server.log'})" if log_dir else ""
                    raise RuntimeError(f"the server exited with {self.server.returncode}{where}")
                if time.monotonic() > deadline:
                    self.stop()
                    raise TimeoutError(f"the server was not ready after {ready_timeout_s} s")
                time.sleep(0.1)

    def stop(self, timeout: float = 30.0) -> None:
        """Stop workers, then the server; the server gets `timeout` seconds to write its last
        checkpoint and stop its embedded database before it is killed."""
        stop_processes(self.worker_procs)
        if self.server is not None:
            stop_processes([self.server], timeout=timeout)

    def __enter__(self) -> LocalFarm:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
