"""Fixtures shared by the cross-component tests: a real local farm on loopback."""

from __future__ import annotations

from pathlib import Path

import pytest

from renderfarm.cli.localfarm import LocalFarm
from renderfarm.client import Client
from renderfarm.infra.worker_binary import find_worker_binary

ROOT = Path(__file__).resolve().parents[1]
CORNELL = ROOT / "examples" / "cornell-box.gltf"


@pytest.fixture(scope="session")
def worker_binary() -> str:
    return find_worker_binary()


@pytest.fixture(scope="session")
def farm(tmp_path_factory, worker_binary):
    """Embedded PostgreSQL + server + 2 workers (1 thread each), stopped after the session."""
    data = tmp_path_factory.mktemp("farm")
    with LocalFarm(workers=2, data_dir=data, threads=1) as running:
        yield running


@pytest.fixture()
def client(farm):
    with Client(farm.url, timeout=30) as c:
        yield c
