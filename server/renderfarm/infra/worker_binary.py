"""Where the renderfarm-worker binary is: the server runs its loader on every uploaded scene
(scene_check.py), and the local farm starts workers from it."""

from __future__ import annotations

import os
import shutil
from pathlib import Path


def find_worker_binary() -> str:
    """RENDERFARM_WORKER_BINARY, else renderfarm-worker on PATH, else this checkout's build."""
    explicit = os.environ.get("RENDERFARM_WORKER_BINARY")
    if explicit:
        return explicit
    on_path = shutil.which("renderfarm-worker")
    if on_path:
        return on_path
    built = Path(__file__).resolve().parents[3] / "build" / "worker" / "renderfarm-worker"
    if built.exists():
        return str(built)
    raise FileNotFoundError(
        "renderfarm-worker not found: run `make build`, put it on PATH, "
        "or set RENDERFARM_WORKER_BINARY"
    )
