"""Running the server: embedded or external PostgreSQL, REST (uvicorn) and gRPC on one loop."""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import logging
import signal
import socket
import time
from collections.abc import Awaitable, Callable

import uvicorn

from ..app.auth import Authenticator, check_exposure, ensure_configured_token
from ..app.composition import addresses, build_farm_service
from ..infra.config import Settings
from ..infra.embedded_db import EmbeddedPostgres
from ..infra.store import Store
from .grpc_api import start_grpc
from .metrics import Metrics
from .rest import create_app

log = logging.getLogger(__name__)

CLOSE_S = 3.0  # of the drain timeout, kept for stopping the APIs and the embedded database

# glibc's malloc returns freed memory above 128 KiB to the kernel at once and serves blocks
# from 128 KiB up with fresh mmaps (or from 32 MiB once its threshold has drifted), so every
# merge's new accumulator arrays would page-fault freshly zeroed pages in. Keep freed memory
# for reuse instead (the server's arrays are recycled at the merge rate).
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3


def tune_allocator() -> bool:
    """Raise glibc's trim and mmap thresholds (64 MiB, 16 MiB); False where not glibc."""
    try:
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        return bool(
            libc.mallopt(_M_MMAP_THRESHOLD, 16 << 20) and libc.mallopt(_M_TRIM_THRESHOLD, 64 << 20)
        )
    except (OSError, AttributeError):
        return False


def _http_socket(host: str, port: int) -> socket.socket:
    """The REST API's socket, bound here: uvicorn, binding it itself, logs a failure and exits
    the process, where this raises an OSError the CLI reports in one line."""
    sock = socket.socket(family=socket.AF_INET6 if ":" in host else socket.AF_INET)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host, port))
    except OSError as e:
        sock.close()
        raise OSError(e.errno, f"cannot listen for HTTP on {host}:{port}: {e.strerror}") from None
    return sock


async def serve(
    settings: Settings,
    on_ready: Callable[[int, int], Awaitable[None]] | None = None,
    stop_event: asyncio.Event | None = None,
) -> None:
    """Run until SIGINT/SIGTERM (or stop_event). on_ready(http_port, grpc_port) runs once both
    APIs listen (the local farm starts its workers there)."""
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    tune_allocator()
    embedded = None
    url = settings.database_url
    if not url:
        embedded = EmbeddedPostgres(settings.data_dir)
        url = await asyncio.to_thread(embedded.start)
    store = Store(
        url, max_size=settings.db_pool_size, queue=settings.db_queue, wait_s=settings.db_wait_s
    )
    supervisor = None
    grpc_server = None
    try:
        await store.open()
        if embedded is not None:  # restarts the postmaster when it dies
            supervisor = asyncio.create_task(embedded.supervise(on_restart=store.reconnect))
        tls = settings.tls()
        await ensure_configured_token(store, settings.admin_token)
        refusal = check_exposure(
            settings.http_host,
            settings.grpc_host,
            await store.live_token_count(),
            settings.worker_token,
        )
        if refusal:
            raise RuntimeError(refusal)
        auth = Authenticator.for_settings(store, settings)
        farm = build_farm_service(settings, store)
        metrics = Metrics(farm)
        farm.metrics = metrics
        await farm.start()
        grpc_server, grpc_port = await start_grpc(
            farm,
            settings.grpc_host,
            settings.grpc_port,
            auth=auth,
            tls=tls,
            client_ca=settings.client_ca(),
        )
        app = create_app(farm, metrics, auth=auth)
        config = uvicorn.Config(
            app,
            host=settings.http_host,
            port=settings.http_port,
            log_level="warning",
            lifespan="off",
            timeout_graceful_shutdown=3,
            ssl_certfile=str(tls[0]) if tls else None,
            ssl_keyfile=str(tls[1]) if tls else None,
        )
        http = uvicorn.Server(config)
        http.install_signal_handlers = lambda: None  # we handle signals below
        stop = stop_event or asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            with contextlib.suppress(NotImplementedError, RuntimeError):
                loop.add_signal_handler(sig, stop.set)
        http_task = asyncio.create_task(
            http.serve(sockets=[_http_socket(settings.http_host, settings.http_port)])
        )
        while not http.started:
            if http_task.done():
                http_task.result()
                raise OSError(
                    f"cannot listen for HTTP on {settings.http_host}:{settings.http_port}"
                )
            await asyncio.sleep(0.02)
        http_port = http.servers[0].sockets[0].getsockname()[1]
        if hasattr(farm.ownership, "addresses"):  # its row in the replicas table (#39)
            farm.ownership.addresses = addresses(settings, http_port, grpc_port)
        log.info(
            "renderfarm server ready: %s://%s:%d  gRPC %s:%d%s",
            "https" if tls else "http", settings.http_host, http_port, settings.grpc_host,
            grpc_port, " (TLS)" if tls else "",
        )  # fmt: skip
        if on_ready is not None:
            await on_ready(http_port, grpc_port)
        await stop.wait()
        # The whole shutdown fits in the drain timeout (a container's grace period is set to
        # it): waiting for tasks in flight leaves the last checkpoint the time it is expected
        # to take, and the servers and the database CLOSE_S at the end.
        deadline = time.monotonic() + settings.drain_timeout_s
        log.info(
            "draining: no new tasks; waiting up to %g s for tasks in flight",
            settings.drain_timeout_s,
        )
        await farm.drain(max(0.0, settings.drain_timeout_s - CLOSE_S))
        log.info("shutting down")
        await farm.stop(timeout_s=deadline - CLOSE_S - time.monotonic())
        http.should_exit = True
        left = max(0.5, deadline - time.monotonic())
        await grpc_server.stop(grace=min(1.0, left / 3))
        grpc_server = None
        with contextlib.suppress(Exception):
            await asyncio.wait_for(http_task, timeout=min(5.0, left / 3))
    finally:
        if grpc_server is not None:
            # Failed after it started (the HTTP port taken): stopped here, on the loop, rather
            # than by the garbage collector after the loop has closed (a traceback on stderr).
            await grpc_server.stop(None)
        if supervisor is not None:
            supervisor.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await supervisor
        await store.close()
        if embedded is not None:
            await asyncio.to_thread(embedded.stop)
