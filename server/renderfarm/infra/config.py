"""Server settings: one typed object, from defaults < environment (RENDERFARM_*) < CLI flags."""

from __future__ import annotations

import os
import socket
from pathlib import Path

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict

from ..domain.jobspec import Limits
from .scene_check import SceneLimits


def machine_memory_bytes() -> int:
    """The memory this process may use: the machine's, or less under a cgroup limit (a
    container's memory limit, v2 memory.max or v1 memory.limit_in_bytes); 0 if unknown."""
    try:
        total = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError):
        total = 0
    for path in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            limit = int(Path(path).read_text().strip())  # "max" (no limit) is not a number
        except (OSError, ValueError):
            continue
        if 0 < limit and (total == 0 or limit < total):
            total = limit
    return total


def default_max_job_memory_mb() -> int:
    """Half of the machine's (or the container's) memory, in MB (4096 when unknown)."""
    total = machine_memory_bytes()
    return max(1, total // 2 // 2**20) if total else 4096


def default_data_dir() -> Path:
    base = os.environ.get("XDG_DATA_HOME") or os.path.join(os.path.expanduser("~"), ".local/share")
    return Path(base) / "renderfarm"


class Settings(BaseSettings):
    """Every server setting, documented in docs/settings.md (`renderfarm server --help` lists
    them)."""

    model_config = SettingsConfigDict(env_prefix="RENDERFARM_", extra="forbid")

    data_dir: Path = Field(default_factory=default_data_dir, description="state directory")
    database_url: str = Field(
        "", description="PostgreSQL URL; empty starts an embedded PostgreSQL in data_dir/pg"
    )
    http_host: str = Field("127.0.0.1", description="address of the REST API and dashboard")
    http_port: int = Field(8080, ge=0, le=65535, description="port of the REST API")
    grpc_host: str = Field("127.0.0.1", description="address of the gRPC API (jobs, workers)")
    grpc_port: int = Field(50051, ge=0, le=65535, description="port of the gRPC API")
    lease_s: float = Field(30.0, gt=0, description="lease of a task; heartbeats extend it")
    heartbeat_interval_s: float = Field(2.0, gt=0, description="how often workers heartbeat")
    replica_id: str = Field(
        "",
        max_length=200,
        description="this server's name in a farm of several servers over one database; "
        "empty: host name and HTTP port (host:port)",
    )
    job_lease_s: float = Field(
        8.0,
        ge=1.0,
        le=300.0,
        description="lease of a server on a job it renders (several servers over one "
        "database): renewed every quarter of it; a server that stops renewing loses its jobs "
        "to the others after it",
    )
    checkpoint_interval_s: float = Field(
        2.0, gt=0, description="most seconds of merged work a server crash may lose"
    )
    drain_timeout_s: float = Field(
        30.0, ge=0, description="on SIGTERM, how long to wait for tasks in flight to come back"
    )
    db_pool_size: int = Field(
        20, gt=0, description="connections to PostgreSQL for API requests (3 more of its own)"
    )
    db_queue: int = Field(
        1000, gt=0, description="API requests that may wait for a connection; more get 429"
    )
    db_wait_s: float = Field(
        30.0, gt=0, description="longest wait of a request for a database connection (then 503)"
    )
    max_upload_bytes: int = Field(256 * 2**20, gt=0, description="largest scene upload")
    max_width: int = Field(16384, gt=0, description="largest image width a job may ask for")
    max_height: int = Field(16384, gt=0, description="largest image height a job may ask for")
    max_pixels: int = Field(64 * 2**20, gt=0, description="largest width x height")
    max_spp: int = Field(1 << 20, gt=0, description="largest max_spp a job may ask for")
    max_frames: int = Field(10000, gt=0, description="most frames one job may name (frames)")
    max_job_memory_mb: int = Field(
        default_factory=default_max_job_memory_mb,
        gt=0,
        description="largest estimated accumulator memory of one job, in MB (default: half "
        "of the machine's or the container's memory)",
    )
    tile_cache_mb: int = Field(
        512,
        gt=0,
        description="RAM for merged tile statistics over all jobs, in MB; tiles beyond it "
        "wait in files in data_dir/scratch",
    )
    max_task_failures: int = Field(
        3, gt=0, description="failed tasks after which a worker is kept off a job"
    )
    worker_token: str = Field("", description="shared token workers must present, if set")
    admin_token: str = Field(
        "",
        description="an admin API token (named admin) the server makes sure exists; for "
        "deployments that keep it in a secret",
    )
    tls_cert_file: str = Field(
        "", description="PEM certificate (chain): serve REST and gRPC over TLS when set"
    )
    tls_key_file: str = Field("", description="PEM private key of tls_cert_file")
    tls_client_ca_file: str = Field(
        "",
        description="PEM CA bundle: the gRPC port then requires client certificates signed by "
        "it (mutual TLS for workers and gRPC clients); needs tls_cert_file",
    )
    scene_inspector: str = Field(
        "",
        description="the renderfarm-worker binary whose loader checks every uploaded scene; "
        "empty: RENDERFARM_WORKER_BINARY, renderfarm-worker on PATH, or this checkout's build",
    )
    max_scene_nodes: int = Field(1_000_000, gt=0, description="most nodes a scene may have")
    max_scene_depth: int = Field(1024, gt=0, description="deepest node hierarchy accepted")
    max_scene_triangles: int = Field(
        1_000_000_000, gt=0, description="most triangles over every mesh use (instances count)"
    )
    max_texture_pixels: int = Field(
        1 << 30, ge=0, description="most pixels in all the images a scene's textures use"
    )
    max_scene_memory_mb: int = Field(
        default_factory=lambda: max(1, machine_memory_bytes() // 2 // 10**6),
        gt=0,
        description="most memory a scene may need once loaded on a worker, as the loader "
        "estimates it (default: half of this machine's memory)",
    )
    scene_inspect_cpu_s: float = Field(
        60.0, gt=0, description="CPU time the server's check of one uploaded scene may take"
    )
    sse_ping_interval_s: float = Field(
        15.0,
        gt=0,
        description="seconds between keep-alive comments on a Server-Sent Events stream (watch)",
    )

    def replica_name(self) -> str:
        """replica_id, or host:port (the host name and the HTTP port) when it is empty."""
        return self.replica_id or f"{socket.gethostname()}:{self.http_port}"

    def tls(self) -> tuple[Path, Path] | None:
        """(certificate, key) when TLS is configured; ValueError when only one is set."""
        if not self.tls_cert_file and not self.tls_key_file:
            return None
        if not (self.tls_cert_file and self.tls_key_file):
            raise ValueError("TLS needs both tls_cert_file and tls_key_file")
        return Path(self.tls_cert_file), Path(self.tls_key_file)

    def client_ca(self) -> Path | None:
        """The CA of mutual TLS on the gRPC port, if configured (it needs TLS itself)."""
        if not self.tls_client_ca_file:
            return None
        if self.tls() is None:
            raise ValueError("tls_client_ca_file needs tls_cert_file and tls_key_file")
        return Path(self.tls_client_ca_file)

    def scene_limits(self) -> SceneLimits:
        return SceneLimits(
            max_nodes=self.max_scene_nodes,
            max_depth=self.max_scene_depth,
            max_triangles=self.max_scene_triangles,
            max_texture_pixels=self.max_texture_pixels,
            max_memory_mb=self.max_scene_memory_mb,
            cpu_seconds=self.scene_inspect_cpu_s,
        )

    def limits(self) -> Limits:
        return Limits(
            max_width=self.max_width,
            max_height=self.max_height,
            max_pixels=self.max_pixels,
            max_spp=self.max_spp,
            max_frames=self.max_frames,
            max_job_memory_bytes=self.max_job_memory_mb * 2**20,
        )
