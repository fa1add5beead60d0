"""The composition root of the job service: build_farm_service makes a FarmService with the
collaborators a server runs with (docs/architecture.md, "Composition"). The server (api/server.py),
and through it the CLI's local farm, and the tests build it here; a test may give any collaborator
a fake of its own.
"""

from __future__ import annotations

import time
from pathlib import Path

from ..domain.scheduler import Scheduler
from ..infra.config import Settings
from ..infra.leases import LeaseOwnership
from ..infra.memory_store import JobStore
from ..infra.scene_check import SceneChecker
from ..infra.spill import TileCache
from ..infra.store import Store
from ..infra.usd_import import UsdImporter
from ..infra.worker_binary import find_worker_binary
from .collaborators import Clock, Ownership, SceneInspector, SoleOwner, UsdConverter
from .jobs import FarmService


def build_farm_service(
    settings: Settings,
    store: JobStore,
    *,
    clock: Clock = time.time,
    ownership: Ownership | None = None,
    scene_checker: SceneInspector | None = None,
    usd_importer: UsdConverter | None = None,
) -> FarmService:
    """A FarmService over `store` with the default collaborators of `settings` (each one given
    here is used instead of its default). The scheduler and the service share `clock`. Over
    PostgreSQL jobs are owned through leases in the database (LeaseOwnership, so that several
    servers over one database form one farm, #39); over any other store (MemoryStore) the
    server owns every job (SoleOwner)."""
    # Tiles past the RAM budget wait in DATA_DIR/scratch (infra/spill.py), as do images being
    # written.
    cache = TileCache(settings.data_dir / "scratch", settings.tile_cache_mb * 2**20)
    scheduler = Scheduler(
        clock=clock,
        lease_s=settings.lease_s,
        max_task_failures=settings.max_task_failures,
        cache=cache,
    )
    if scene_checker is None:
        # Every new uploaded scene goes through the workers' own loader before it is stored.
        scene_checker = SceneChecker(
            settings.scene_inspector or find_worker_binary(),
            settings.scene_limits(),
            Path(settings.data_dir) / "tmp",
        )
    if usd_importer is None:
        # USD uploads become glTF in a limited child process before that check (usd_import.py).
        usd_importer = UsdImporter(
            Path(settings.data_dir) / "tmp",
            cpu_seconds=settings.scene_inspect_cpu_s,
            memory_mb=settings.max_scene_memory_mb,
            max_output_bytes=settings.max_upload_bytes,
        )
    if ownership is None:
        if isinstance(store, Store):
            ownership = LeaseOwnership(
                store,
                settings.replica_name(),
                lease_s=settings.job_lease_s,
                addresses=addresses(settings),
            )
        else:
            ownership = SoleOwner(settings.replica_name())
    service = FarmService(
        settings,
        store,
        scheduler=scheduler,
        scene_checker=scene_checker,
        usd_importer=usd_importer,
        clock=clock,
        ownership=ownership,
    )
    if isinstance(ownership, LeaseOwnership):
        ownership.merged = lambda: service.batches_merged  # its row in GET /api/v1/replicas
    return service


def addresses(settings: Settings, http_port: int | None = None, grpc_port: int | None = None):
    """Where a replica answers, as its row in the replicas table shows it (the bound ports
    when known: a port setting of 0 picks one)."""
    scheme = "https" if settings.tls_cert_file else "http"
    http = http_port if http_port is not None else settings.http_port
    grpc = grpc_port if grpc_port is not None else settings.grpc_port
    return {
        "http": f"{scheme}://{settings.http_host}:{http}",
        "grpc": f"{settings.grpc_host}:{grpc}",
    }
