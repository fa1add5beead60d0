"""PostgreSQL: the only durable store. Every SQL statement of the server lives in this module.

Schema changes are numbered files in migrations/ (NNNN_name.sql), applied in order at start in
one transaction each, under an advisory lock so two servers starting together do not race. A
database whose schema is newer than this code knows is refused.

One module although long: every SQL statement in one place is the point (a schema change is
checked against all of its queries here).
"""

from __future__ import annotations

import contextlib
import json
import math
import re
from collections.abc import AsyncIterator
from dataclasses import dataclass
from dataclasses import field as dataclass_field
from datetime import UTC, datetime
from importlib import resources
from typing import Any

import psycopg
from psycopg.rows import dict_row
from psycopg.types.json import Jsonb
from psycopg_pool import AsyncConnectionPool, TooManyRequests

from ..errors import LeaseLost, SchemaTooNew

_MIGRATION_LOCK = 0x52464D31  # advisory lock key for migrations ("RFM1")

Fence = tuple[str, int]
"""(replica id, epoch): what a write of a job's owner carries in a farm of several servers
(#39). A fenced write is made, in its transaction, only while the job's lease row names that
replica and epoch (locked FOR SHARE, so a takeover waits for it), and raises LeaseLost
otherwise. None: no condition (a server alone, collaborators.SoleOwner)."""

# Seconds a client is told to wait (Retry-After) when the database is away (a restarted
# embedded PostgreSQL answers again within about this), and when the queue is full.
RETRY_AFTER_S = 2
BUSY_RETRY_AFTER_S = 1
# While the last connection attempt failed, a request waits this long for a connection at
# most: enough for a database that has just come back, without holding clients for the whole
# wait of a busy one.
UNREACHABLE_WAIT_S = 1.0


class DatabaseUnavailable(psycopg.OperationalError):
    """The database cannot serve a request now: unreachable, or no connection free within the
    wait. The APIs answer 503 / UNAVAILABLE with Retry-After (an OperationalError, so callers
    that tolerate database failures, such as the background writer, treat it as one)."""

    status = 503

    def __init__(self, message: str, retry_after_s: int = RETRY_AFTER_S):
        super().__init__(message)
        self.message = message
        self.retry_after_s = retry_after_s


class DatabaseBusy(DatabaseUnavailable):
    """More API requests wait for a database connection than the queue holds (REST 429)."""

    status = 429


def migrations() -> list[tuple[int, str, str]]:
    """(version, name, sql) of every migration shipped with the package, in order."""
    found = []
    for entry in resources.files("renderfarm.infra.migrations").iterdir():
        match = re.fullmatch(r"(\d{4})_(\w+)\.sql", entry.name)
        if match:
            found.append((int(match.group(1)), match.group(2), entry.read_text()))
    found.sort()
    versions = [v for v, _, _ in found]
    if versions != list(range(1, len(versions) + 1)):
        raise RuntimeError(f"migrations must be numbered 1..N without gaps, found {versions}")
    return found


@dataclass(frozen=True)
class JobRow:
    id: str
    name: str
    state: str
    settings: dict[str, Any]
    scene_sha256: str
    error: str
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    elapsed_s: float
    samples_merged: int
    mean_spp: float
    error_estimate: float | None
    tiles_total: int
    tiles_done: int
    owner: str = ""
    tiles_previewed: int = 0
    after_jobs: list[str] = dataclass_field(default_factory=list)  # ids of the jobs it waits for
    require_tags: list[str] = dataclass_field(default_factory=list)  # worker tags it needs
    frames_done: int = 0  # frames whose every tile has stopped
    # settings.variant "all": the scene's variants, one image each (domain/frames.py)
    variants: list[str] = dataclass_field(default_factory=list)
    replica: str = ""  # the replica holding the job's lease now; "" when none does (#39)


@dataclass(frozen=True)
class TokenRow:
    id: str
    name: str
    sha256: str
    admin: bool
    created_at: datetime
    revoked_at: datetime | None


@dataclass(frozen=True)
class TileRow:
    tile_index: int
    samples: int
    batches: int
    nonfinite: int
    error: float | None
    accumulators: bytes | bytearray
    stop_batch: int | None
    stop_spp: int | None
    stop_error: float | None
    stop_reason: str | None
    # Albedo and normal sums; None on save keeps the stored ones (they stop changing early).
    aovs: bytes | bytearray | None = None
    # Planned batch sizes (Scheduler.planned_batches); None: nothing planned.
    batch_plan: list[int] | None = None
    # [count, samples, error or None, before] of each planned batch from PLANNED_FROM on
    # (Scheduler.plan_basis); None: none recorded.
    plan_basis: list[list] | None = None


@dataclass(frozen=True)
class TileSummary:
    tile_index: int
    samples: int
    error: float | None
    stopped: bool


_JOB_COLUMNS = (
    "id, name, state, settings, scene_sha256, error, created_at, started_at, finished_at, "
    "elapsed_s, samples_merged, mean_spp, error_estimate, tiles_total, tiles_done, owner, "
    "tiles_previewed, after_jobs, require_tags, frames_done, variants"
)
# The replica holding a live lease on the job ("" when none does), read beside its columns.
_JOB_SELECT = (
    _JOB_COLUMNS + ", coalesce((SELECT l.replica_id FROM job_leases l WHERE l.job_id = jobs.id"
    " AND l.expires_at > now()), '') AS replica"
)
_TOKEN_COLUMNS = "id, name, sha256, admin, created_at, revoked_at"


class Store:
    """Two connection pools: `pool` for API requests (at most max_size connections, `queue`
    requests waiting for one, each at most `wait_s`), and `internal`, a few connections of the
    server's own (checkpoints, events, finished jobs, the worker table, scene downloads by
    workers, readiness), so that a flood of requests never holds up the writes that finish
    jobs."""

    def __init__(
        self,
        url: str,
        min_size: int = 1,
        max_size: int = 8,
        queue: int = 0,
        wait_s: float = 5.0,
        internal_size: int = 3,
    ):
        self.url = url
        self.wait_s = wait_s
        # True from a failed connection attempt until the next one succeeds.
        self.unreachable = False
        # check: a connection is tested before it is handed out, so connections broken by a
        # database restart are replaced instead of failing a request. reconnect_timeout=0:
        # a failed connection attempt is given up at once (reconnect_failed), and the next
        # request that finds no connection makes the pool try again, so it reconnects as soon
        # as the database answers rather than after a growing backoff.
        common: dict[str, Any] = {
            "open": False,
            "kwargs": {"autocommit": True},
            "check": AsyncConnectionPool.check_connection,
            "reconnect_timeout": 0,
            "configure": self._connected,
            "reconnect_failed": self._connect_failed,
        }
        self.pool = AsyncConnectionPool(
            url,
            min_size=min(min_size, max_size),
            max_size=max_size,
            max_waiting=queue,
            timeout=wait_s,
            name="api",
            **common,
        )
        self.internal = AsyncConnectionPool(
            url, min_size=1, max_size=internal_size, timeout=5.0, name="internal", **common
        )
        # One connection for renewing job leases and the replica's row alone, opened on first
        # use (a farm of several servers): a renewal never waits behind checkpoints or a
        # thousand workers connecting at once, which would let the leases lapse under load.
        self.lease_pool = AsyncConnectionPool(
            url, min_size=1, max_size=1, timeout=5.0, name="leases", **common
        )
        self._lease_pool_open = False
        # Failed database operations since start (renderfarm_database_errors_total).
        self.errors = 0

    async def _connected(self, conn: Any) -> None:
        self.unreachable = False

    def _connect_failed(self, pool: Any) -> None:
        self.unreachable = True

    @contextlib.asynccontextmanager
    async def _connection(
        self, timeout: float | None = None, internal: bool = False, leases: bool = False
    ) -> AsyncIterator[Any]:
        """A pooled connection (of the API's pool, the internal one, or with `leases` the
        lease renewals' own). Every database failure inside is counted; a full queue is
        raised as DatabaseBusy, a database out of reach (or no connection within the wait) as
        DatabaseUnavailable, anything else as it is."""
        if self.unreachable:
            timeout = min(timeout or self.wait_s, UNREACHABLE_WAIT_S)
        pool = self.internal if internal else self.pool
        if leases:
            if not self._lease_pool_open:
                self._lease_pool_open = True
                await self.lease_pool.open(wait=False)
            pool = self.lease_pool
        try:
            async with pool.connection(timeout) as conn:
                yield conn
        except TooManyRequests as e:
            self.errors += 1
            raise DatabaseBusy(f"database busy: {e}", BUSY_RETRY_AFTER_S) from e
        except (psycopg.OperationalError, psycopg.InterfaceError, OSError) as e:
            self.errors += 1
            raise DatabaseUnavailable(f"database unavailable: {e}") from e
        except psycopg.Error:
            self.errors += 1
            raise

    async def open(self) -> None:
        await self.internal.open(wait=True, timeout=30)
        await self.pool.open(wait=True, timeout=30)
        await self.migrate()

    async def close(self) -> None:
        await self.pool.close()
        await self.internal.close()
        if self._lease_pool_open:
            await self.lease_pool.close()

    async def reconnect(self) -> None:
        """Replace the connections a database restart broke now rather than on their next
        use (called when the embedded PostgreSQL was restarted)."""
        self.unreachable = False
        await self.internal.check()
        await self.pool.check()
        if self._lease_pool_open:
            await self.lease_pool.check()

    async def migrate(self) -> int:
        """Apply pending migrations; return the schema version."""
        known = migrations()
        async with self._connection(internal=True) as conn:
            await conn.execute("SELECT pg_advisory_lock(%s)", (_MIGRATION_LOCK,))
            try:
                await conn.execute(
                    "CREATE TABLE IF NOT EXISTS schema_migrations ("
                    " version integer PRIMARY KEY, name text NOT NULL,"
                    " applied_at timestamptz NOT NULL DEFAULT now())"
                )
                cur = await conn.execute("SELECT coalesce(max(version), 0) FROM schema_migrations")
                (current,) = await cur.fetchone()
                if current > len(known):
                    raise SchemaTooNew(
                        f"the database schema is version {current}, newer than this server "
                        f"knows ({len(known)}); upgrade the server instead of downgrading it"
                    )
                for version, name, sql in known[current:]:
                    async with conn.transaction():
                        await conn.execute(sql)
                        await conn.execute(
                            "INSERT INTO schema_migrations (version, name) VALUES (%s, %s)",
                            (version, name),
                        )
                return len(known)
            finally:
                await conn.execute("SELECT pg_advisory_unlock(%s)", (_MIGRATION_LOCK,))

    async def ping(self) -> None:
        async with self._connection(timeout=5, internal=True) as conn:
            await conn.execute("SELECT 1")

    # ----------------------------------------------------------------------------- scenes
    async def put_scene(self, sha256: str, fmt: str, filename: str, data: bytes) -> None:
        async with self._connection() as conn:
            await conn.execute(
                "INSERT INTO scenes (sha256, format, filename, size_bytes, data)"
                " VALUES (%s, %s, %s, %s, %s) ON CONFLICT (sha256) DO NOTHING",
                (sha256, fmt, filename, len(data), data),
            )

    async def put_scene_source(
        self, sha256: str, source_format: str, source_sha256: str, source_filename: str
    ) -> None:
        """Record what a stored scene was converted from (the first record stays)."""
        async with self._connection() as conn:
            await conn.execute(
                "INSERT INTO scene_sources (sha256, source_format, source_sha256, source_filename)"
                " VALUES (%s, %s, %s, %s) ON CONFLICT (sha256) DO NOTHING",
                (sha256, source_format, source_sha256, source_filename),
            )

    async def get_scene_source(self, sha256: str) -> dict[str, Any] | None:
        async with self._connection() as conn:
            cur = conn.cursor(row_factory=dict_row)
            await cur.execute(
                "SELECT source_format, source_sha256, source_filename FROM scene_sources"
                " WHERE sha256 = %s",
                (sha256,),
            )
            return await cur.fetchone()

    async def get_job_scene_source(self, job_id: str) -> dict[str, Any] | None:
        """What a job's scene was converted from, as submitted with the job (None: no
        converted upload was submitted with it)."""
        async with self._connection() as conn:
            cur = conn.cursor(row_factory=dict_row)
            await cur.execute(
                "SELECT source_format, source_sha256, source_filename FROM job_scene_sources"
                " WHERE job_id = %s",
                (job_id,),
            )
            return await cur.fetchone()

    async def get_scene_info(self, sha256: str) -> dict[str, Any] | None:
        async with self._connection() as conn:
            cur = conn.cursor(row_factory=dict_row)
            await cur.execute(
                "SELECT sha256, format, filename, size_bytes FROM scenes WHERE sha256 = %s",
                (sha256,),
            )
            return await cur.fetchone()

    async def read_scene(self, sha256: str, offset: int, length: int) -> bytes:
        async with self._connection(internal=True) as conn:
            cur = await conn.execute(
                "SELECT substring(data FROM %s FOR %s) FROM scenes WHERE sha256 = %s",
                (offset + 1, length, sha256),
            )
            row = await cur.fetchone()
            return bytes(row[0]) if row else b""

    # ------------------------------------------------------------------------------- jobs
    async def insert_job(
        self,
        job_id: str,
        name: str,
        settings: dict[str, Any],
        scene_sha256: str,
        tiles: int,
        owner: str = "",
        after: list[str] | None = None,
        state: str = "queued",
        require_tags: list[str] | None = None,
        variants: list[str] | None = None,
        scene_source: dict[str, str] | None = None,
    ) -> JobRow:
        """Insert a job with its first event and, for a converted upload, its source (the
        USD upload's format, sha256 and file name: the job's own, whoever else's upload
        converted to the same scene)."""
        # One statement: the job, its first event and its source are committed together, in
        # one round trip (a burst of submissions holds each pooled connection as briefly as it
        # can).
        source = scene_source or {}
        async with self._connection() as conn:
            cur = conn.cursor(row_factory=dict_row)
            await cur.execute(
                "WITH job AS (INSERT INTO jobs"
                " (id, name, state, settings, scene_sha256, tiles_total, owner, after_jobs,"
                " require_tags, variants)"
                f" VALUES (%s, %s, %s, %s, %s, %s, %s, %s, %s, %s) RETURNING {_JOB_COLUMNS}),"
                " submitted AS (INSERT INTO events (job_id, kind, data)"
                " SELECT id, 'job_submitted', %s FROM job),"
                " source AS (INSERT INTO job_scene_sources"
                " (job_id, source_format, source_sha256, source_filename)"
                " SELECT id, %s, %s, %s FROM job WHERE %s)"
                " SELECT * FROM job",
                (job_id, name, state, json.dumps(settings), scene_sha256, tiles, owner,
                 list(after or []), list(require_tags or []), list(variants or []),
                 json.dumps({"name": name, "state": state, "after": list(after or [])}),
                 str(source.get("source_format", "")), str(source.get("source_sha256", "")),
                 str(source.get("source_filename", "")), scene_source is not None),
            )  # fmt: skip
            return JobRow(**await cur.fetchone())

    async def update_job(
        self,
        job_id: str,
        *,
        state: str,
        error: str,
        started: float | None,
        finished: float | None,
        elapsed_s: float,
        samples_merged: int,
        mean_spp: float,
        error_estimate: float | None,
        tiles_done: int,
        tiles_previewed: int,
        frames_done: int = 0,
        fence: Fence | None = None,
    ) -> None:
        async with self._connection(internal=True) as conn, conn.transaction():
            await _check_fence(conn, job_id, fence)
            await conn.execute(
                "UPDATE jobs SET state = %s, error = %s,"
                " started_at = coalesce(started_at, %s), finished_at = %s, elapsed_s = %s,"
                " samples_merged = %s, mean_spp = %s, error_estimate = %s, tiles_done = %s,"
                " tiles_previewed = %s, frames_done = %s WHERE id = %s",
                (
                    state,
                    error,
                    _ts(started),
                    _ts(finished),
                    elapsed_s,
                    samples_merged,
                    mean_spp,
                    error_estimate,
                    tiles_done,
                    tiles_previewed,
                    frames_done,
                    job_id,
                ),
            )

    async def update_job_spec(
        self, job_id: str, name: str, settings: dict[str, Any], fence: Fence | None = None
    ) -> None:
        """A job's name and settings after an update or a continue (job control)."""
        async with self._connection() as conn, conn.transaction():
            await _check_fence(conn, job_id, fence)
            await conn.execute(
                "UPDATE jobs SET name = %s, settings = %s WHERE id = %s",
                (name, json.dumps(settings), job_id),
            )

    async def reactivate_job(
        self,
        job_id: str,
        *,
        settings: dict[str, Any],
        state: str,
        elapsed_s: float,
        render_again: list[int],
        tiles: list[tuple[int, list[int] | None, list[list] | None, Any]],
        fence: Fence | None = None,
    ) -> None:
        """A finished job brought back (retry, continue), in one transaction: its new settings
        and state, the checkpoints of the tiles that render again from their first sample
        dropped, and each kept tile's plan, plan basis and stop record (index, batch_plan,
        plan_basis, scheduler.StopRecord or None) as the new settings have them. A crash then
        finds the job either as it was or as it is now, never half way."""
        async with self._connection() as conn, conn.transaction():
            await _check_fence(conn, job_id, fence)
            await conn.execute(
                "DELETE FROM tiles WHERE job_id = %s AND tile_index = ANY(%s)",
                (job_id, render_again),
            )
            async with conn.cursor() as cur:
                await cur.executemany(
                    "UPDATE tiles SET batch_plan = %s, plan_basis = %s, stop_batch = %s,"
                    " stop_spp = %s, stop_error = %s, stop_reason = %s"
                    " WHERE job_id = %s AND tile_index = %s",
                    [
                        (
                            plan,
                            None if basis is None else Jsonb(basis),
                            stop.batch_index if stop else None,
                            stop.spp if stop else None,
                            _finite(stop.error) if stop else None,
                            stop.reason.value if stop else None,
                            job_id,
                            index,
                        )
                        for index, plan, basis, stop in tiles
                    ],
                )
            await conn.execute(
                "UPDATE jobs SET settings = %s, state = %s, error = '', finished_at = NULL,"
                " elapsed_s = %s WHERE id = %s",
                (json.dumps(settings), state, elapsed_s, job_id),
            )

    async def waiting_for(self, job_id: str) -> list[str]:
        """Ids of the unfinished jobs that wait for this one (`after`)."""
        async with self._connection() as conn:
            cur = await conn.execute(
                "SELECT id FROM jobs WHERE %s = ANY(after_jobs)"
                " AND state IN ('waiting', 'queued', 'running', 'paused')",
                (job_id,),
            )
            return [r[0] for r in await cur.fetchall()]

    async def get_job(self, job_id: str) -> JobRow | None:
        async with self._connection() as conn:
            cur = conn.cursor(row_factory=dict_row)
            await cur.execute(f"SELECT {_JOB_SELECT} FROM jobs WHERE id = %s", (job_id,))
            row = await cur.fetchone()
            return JobRow(**row) if row else None

    async def list_jobs(
        self,
        state: str | None,
        limit: int,
        after: tuple[datetime, str] | None,
        owner: str | None = None,
    ) -> list[JobRow]:
        """Newest first; `after` is the (created_at, id) of the last row of the previous page;
        `owner` (when not None) keeps only that owner's jobs."""
        where, params = [], []
        if state:
            where.append("state = %s")
            params.append(state)
        if owner is not None:
            where.append("owner = %s")
            params.append(owner)
        if after:
            where.append("(created_at, id) < (%s, %s)")
            params.extend(after)
        sql = f"SELECT {_JOB_SELECT} FROM jobs"
        if where:
            sql += " WHERE " + " AND ".join(where)
        sql += " ORDER BY created_at DESC, id DESC LIMIT %s"
        params.append(limit)
        async with self._connection() as conn:
            cur = conn.cursor(row_factory=dict_row)
            await cur.execute(sql, params)
            return [JobRow(**r) for r in await cur.fetchall()]

    async def delete_job(self, job_id: str, replica_id: str | None = None) -> bool:
        """Delete a job with its tiles and events; its scene and environment map too when no
        other job uses them. False when there was no such job. With `replica_id` (a farm of
        several servers), LeaseLost while another replica holds a live lease on the job (it
        was brought back meanwhile)."""
        async with self._connection() as conn:
            async with conn.transaction():
                if replica_id is not None:
                    # Locked whoever holds it: an acquire racing the delete waits for it.
                    cur = await conn.execute(
                        "SELECT replica_id, expires_at > now() FROM job_leases"
                        " WHERE job_id = %s FOR UPDATE",
                        (job_id,),
                    )
                    lease = await cur.fetchone()
                    if lease is not None and lease[1] and lease[0] != replica_id:
                        raise LeaseLost(job_id, f"job {job_id} is held by server {lease[0]}")
                cur = await conn.execute(
                    "DELETE FROM jobs WHERE id = %s"
                    " RETURNING scene_sha256, settings->>'environment'",
                    (job_id,),
                )
                row = await cur.fetchone()
                if row is None:
                    return False
                for sha in {row[0], row[1]} - {None, ""}:
                    await conn.execute(
                        "DELETE FROM scenes WHERE sha256 = %s AND NOT EXISTS (SELECT 1 FROM jobs"
                        " WHERE scene_sha256 = %s OR settings->>'environment' = %s)",
                        (sha, sha, sha),
                    )
                return True

    async def unfinished_jobs(self) -> list[JobRow]:
        async with self._connection(internal=True) as conn:
            cur = conn.cursor(row_factory=dict_row)
            await cur.execute(
                f"SELECT {_JOB_SELECT} FROM jobs"
                " WHERE state IN ('queued', 'running', 'paused', 'waiting')"
                " ORDER BY created_at"
            )
            return [JobRow(**r) for r in await cur.fetchall()]

    # ------------------------------------------------------------------------------ tiles
    async def save_tiles(
        self, job_id: str, rows: list[TileRow], fence: Fence | None = None
    ) -> None:
        if not rows:
            return
        # One transaction: one commit (one WAL flush) per checkpoint, not one per tile.
        async with self._connection(internal=True) as conn, conn.transaction():
            await _check_fence(conn, job_id, fence)
            async with conn.cursor() as cur:
                await cur.executemany(
                    "INSERT INTO tiles (job_id, tile_index, samples, batches, nonfinite, error,"
                    " accumulators, stop_batch, stop_spp, stop_error, stop_reason, aovs,"
                    " batch_plan, plan_basis)"
                    " VALUES (%s, %s, %s, %s, %s, %s, %s, %s, %s, %s, %s, %s, %s, %s)"
                    " ON CONFLICT (job_id, tile_index) DO UPDATE SET samples = excluded.samples,"
                    " batches = excluded.batches, nonfinite = excluded.nonfinite,"
                    " error = excluded.error, accumulators = excluded.accumulators,"
                    " stop_batch = excluded.stop_batch, stop_spp = excluded.stop_spp,"
                    " stop_error = excluded.stop_error, stop_reason = excluded.stop_reason,"
                    " aovs = COALESCE(excluded.aovs, tiles.aovs),"
                    " batch_plan = excluded.batch_plan, plan_basis = excluded.plan_basis,"
                    " updated_at = now()"
                    # Never move a tile backwards (a slow writer racing a newer checkpoint).
                    " WHERE tiles.batches <= excluded.batches",
                    [
                        (
                            job_id,
                            r.tile_index,
                            r.samples,
                            r.batches,
                            r.nonfinite,
                            _finite(r.error),
                            r.accumulators,
                            r.stop_batch,
                            r.stop_spp,
                            _finite(r.stop_error),
                            r.stop_reason,
                            r.aovs,
                            r.batch_plan,
                            None if r.plan_basis is None else Jsonb(r.plan_basis),
                        )
                        for r in rows
                    ],
                )

    async def load_tiles(
        self, job_id: str, first: int = 0, count: int | None = None
    ) -> list[TileRow]:
        """The job's checkpointed tiles with index first .. first + count - 1 (all when count
        is None), in index order."""
        last = 2**31 - 1 if count is None else first + count - 1
        async with self._connection() as conn:
            cur = conn.cursor(row_factory=dict_row)
            await cur.execute(
                "SELECT tile_index, samples, batches, nonfinite, error, accumulators,"
                " stop_batch, stop_spp, stop_error, stop_reason, aovs, batch_plan, plan_basis"
                " FROM tiles WHERE job_id = %s AND tile_index BETWEEN %s AND %s"
                " ORDER BY tile_index",
                (job_id, first, last),
            )
            return [
                TileRow(
                    **{
                        **r,
                        "accumulators": bytes(r["accumulators"]),
                        "aovs": None if r["aovs"] is None else bytes(r["aovs"]),
                    }
                )
                for r in await cur.fetchall()
            ]

    async def tile_summaries(self, job_id: str) -> list[TileSummary]:
        """Every checkpointed tile of the job without its arrays (per-frame progress of a job
        no longer held in memory), in index order."""
        async with self._connection() as conn:
            cur = conn.cursor()
            await cur.execute(
                "SELECT tile_index, samples, error, stop_reason IS NOT NULL FROM tiles"
                " WHERE job_id = %s ORDER BY tile_index",
                (job_id,),
            )
            return [TileSummary(*r) for r in await cur.fetchall()]

    # ----------------------------------------------------------------------------- events
    async def add_events(
        self,
        events: list[tuple[str | None, str, dict[str, Any]]],
        fences: dict[str, Fence] | None = None,
    ) -> None:
        """Store events in order. `fences` (job id -> Fence): the events of a job named there
        are written only while its lease matches; the others of the batch are written anyway
        (one transaction), then LeaseLost names the jobs whose events were refused."""
        if not events:
            return
        async with self._connection(internal=True) as conn, conn.transaction():
            events, lost = await _fenced_events(conn, events, fences)
            async with conn.cursor() as cur:
                # Events of a job deleted meanwhile are dropped rather than failing the batch.
                await cur.executemany(
                    "INSERT INTO events (job_id, kind, data) SELECT %s, %s, %s"
                    " WHERE EXISTS (SELECT 1 FROM jobs WHERE id = %s)",
                    [(j, k, json.dumps(_clean(d), default=str), j) for j, k, d in events],
                )
        if lost:
            raise LeaseLost(lost)

    async def add_events_once(
        self,
        events: list[tuple[str | None, str, dict[str, Any]]],
        fences: dict[str, Fence] | None = None,
    ) -> None:
        """add_events, leaving out every event already stored with the same job, kind and
        data: replaying a spool a second time (after a crash between its writes and its
        removal) adds nothing."""
        if not events:
            return
        async with self._connection(internal=True) as conn, conn.transaction():
            events, lost = await _fenced_events(conn, events, fences)
            async with conn.cursor() as cur:
                await cur.executemany(
                    "INSERT INTO events (job_id, kind, data) SELECT %s, %s, %s::jsonb"
                    " WHERE EXISTS (SELECT 1 FROM jobs WHERE id = %s) AND NOT EXISTS"
                    " (SELECT 1 FROM events WHERE job_id = %s AND kind = %s"
                    " AND data = %s::jsonb)",
                    [
                        (j, k, text, j, j, k, text)
                        for j, k, d in events
                        for text in [json.dumps(_clean(d), default=str)]
                    ],
                )
        if lost:
            raise LeaseLost(lost)

    async def list_events(self, job_id: str, limit: int = 1000) -> list[dict[str, Any]]:
        async with self._connection() as conn:
            cur = conn.cursor(row_factory=dict_row)
            await cur.execute(
                "SELECT id, kind, data, at FROM events WHERE job_id = %s ORDER BY id LIMIT %s",
                (job_id, limit),
            )
            return list(await cur.fetchall())

    # ---------------------------------------------------------------------------- workers
    async def worker_connected(self, worker_id: str, hostname: str, cores: int, version: str):
        async with self._connection(internal=True) as conn:
            await conn.execute(
                "INSERT INTO workers (id, hostname, cores, version, connected_at, last_seen,"
                " connected) VALUES (%s, %s, %s, %s, now(), now(), true)"
                " ON CONFLICT (id) DO UPDATE SET hostname = excluded.hostname,"
                " cores = excluded.cores, version = excluded.version,"
                " connected_at = now(), last_seen = now(), connected = true",
                (worker_id, hostname, cores, version),
            )

    async def worker_disconnected(self, worker_id: str) -> None:
        async with self._connection(internal=True) as conn:
            await conn.execute(
                "UPDATE workers SET connected = false, last_seen = now() WHERE id = %s",
                (worker_id,),
            )

    async def mark_all_workers_disconnected(self) -> None:
        async with self._connection(internal=True) as conn:
            await conn.execute("UPDATE workers SET connected = false WHERE connected")

    # ------------------------------------------------------------------- leases, replicas
    async def acquire_lease(self, job_id: str, replica_id: str, lease_s: float) -> int | None:
        """Take the job's lease for lease_s seconds of the database's clock, in one statement:
        a job without a lease row gets one at epoch 1; a lease that has expired, or that names
        this replica (a restart under the same id), is taken at its epoch + 1. The epoch now
        held, or None when another replica holds a live lease."""
        async with self._connection(internal=True) as conn:
            cur = await conn.execute(
                "INSERT INTO job_leases (job_id, replica_id, epoch, expires_at)"
                " SELECT %s, %s, 1, now() + make_interval(secs => %s)"
                " WHERE EXISTS (SELECT 1 FROM jobs WHERE id = %s)"
                " ON CONFLICT (job_id) DO UPDATE SET replica_id = excluded.replica_id,"
                " epoch = job_leases.epoch + 1, expires_at = excluded.expires_at"
                " WHERE job_leases.expires_at <= now()"
                " OR job_leases.replica_id = excluded.replica_id"
                " RETURNING epoch",
                (job_id, replica_id, lease_s, job_id),
            )
            row = await cur.fetchone()
            return None if row is None else row[0]

    async def renew_leases(
        self, replica_id: str, held: dict[str, int], lease_s: float
    ) -> dict[str, int]:
        """Extend this replica's leases (job id -> epoch) to lease_s seconds from now; those
        renewed (a lease taken over since, at a higher epoch, is not). An expired lease that
        nobody took is renewed: no one else has written the job since."""
        if not held:
            return {}
        ids = sorted(held)
        async with self._connection(leases=True) as conn:
            cur = await conn.execute(
                "UPDATE job_leases l SET expires_at = now() + make_interval(secs => %s)"
                " FROM unnest(%s::text[], %s::bigint[]) AS h(job_id, epoch)"
                " WHERE l.job_id = h.job_id AND l.epoch = h.epoch AND l.replica_id = %s"
                " RETURNING l.job_id, l.epoch",
                (lease_s, ids, [held[j] for j in ids], replica_id),
            )
            return {j: e for j, e in await cur.fetchall()}

    async def release_lease(self, job_id: str, replica_id: str, epoch: int) -> None:
        """Let a lease go now (it expires; the row and its epoch stay)."""
        async with self._connection(internal=True) as conn:
            await conn.execute(
                "UPDATE job_leases SET expires_at = now() WHERE job_id = %s AND replica_id = %s"
                " AND epoch = %s AND expires_at > now()",
                (job_id, replica_id, epoch),
            )

    async def lease_of(self, job_id: str) -> tuple[str, int, bool] | None:
        """(replica, epoch, live) of the job's lease row; None when it has none."""
        async with self._connection() as conn:
            cur = await conn.execute(
                "SELECT replica_id, epoch, expires_at > now() FROM job_leases WHERE job_id = %s",
                (job_id,),
            )
            row = await cur.fetchone()
            return None if row is None else (row[0], row[1], row[2])

    async def unleased_jobs(self, limit: int = 100) -> list[str]:
        """Ids of unfinished jobs that no replica holds a live lease on, oldest first."""
        async with self._connection(internal=True) as conn:
            cur = await conn.execute(
                "SELECT j.id FROM jobs j LEFT JOIN job_leases l ON l.job_id = j.id"
                " WHERE j.state IN ('queued', 'running', 'paused', 'waiting')"
                " AND (l.job_id IS NULL OR l.expires_at <= now())"
                " ORDER BY j.created_at, j.id LIMIT %s",
                (limit,),
            )
            return [r[0] for r in await cur.fetchall()]

    async def replica_heartbeat(
        self,
        replica_id: str,
        addresses: dict[str, str],
        started: float,
        batches_merged: int,
        merge_rate: float,
        live_s: float = 60.0,
    ) -> int:
        """Record that the replica is alive (its row made on its first heartbeat); how many
        other replicas heartbeat within the last live_s seconds."""
        async with self._connection(leases=True) as conn:
            await conn.execute(
                "INSERT INTO replicas (id, addresses, started_at, heartbeat_at, batches_merged,"
                " merge_rate) VALUES (%s, %s, %s, now(), %s, %s)"
                " ON CONFLICT (id) DO UPDATE SET addresses = excluded.addresses,"
                " started_at = excluded.started_at, heartbeat_at = now(),"
                " batches_merged = excluded.batches_merged, merge_rate = excluded.merge_rate",
                (replica_id, Jsonb(addresses), _ts(started), batches_merged, merge_rate),
            )
            cur = await conn.execute(
                "SELECT count(*) FROM replicas WHERE id <> %s"
                " AND heartbeat_at > now() - make_interval(secs => %s)",
                (replica_id, live_s),
            )
            (others,) = await cur.fetchone()
            return others

    async def remove_replica(self, replica_id: str) -> None:
        """The replica stopped cleanly (its jobs released): it is no longer one of the farm's
        servers, so the others share its jobs among themselves at once."""
        async with self._connection(internal=True) as conn:
            await conn.execute("DELETE FROM replicas WHERE id = %s", (replica_id,))

    async def list_replicas(self, live_s: float) -> list[dict[str, Any]]:
        """Every replica recorded, with the jobs it holds live leases on; `live` when its last
        heartbeat is less than live_s seconds old (the database's clock)."""
        async with self._connection() as conn:
            cur = conn.cursor(row_factory=dict_row)
            await cur.execute(
                "SELECT r.id, r.addresses, r.started_at, r.heartbeat_at, r.batches_merged,"
                " r.merge_rate, r.heartbeat_at > now() - make_interval(secs => %s) AS live,"
                " (SELECT count(*) FROM job_leases l WHERE l.replica_id = r.id"
                " AND l.expires_at > now()) AS jobs_owned"
                " FROM replicas r ORDER BY r.id",
                (live_s,),
            )
            return list(await cur.fetchall())

    async def request_control(self, job_id: str, action: str, data: dict[str, Any]) -> int:
        """Ask the job's owner for a job-control action (job_requests); the request's id."""
        async with self._connection() as conn:
            cur = await conn.execute(
                "INSERT INTO job_requests (job_id, action, data) VALUES (%s, %s, %s) RETURNING id",
                (job_id, action, Jsonb(data)),
            )
            (request_id,) = await cur.fetchone()
            return request_id

    async def control_pending(self, request_id: int) -> bool:
        async with self._connection() as conn:
            cur = await conn.execute("SELECT 1 FROM job_requests WHERE id = %s", (request_id,))
            return await cur.fetchone() is not None

    async def controls_for(self, replica_id: str) -> list[tuple[int, str, str, dict[str, Any]]]:
        """(id, job, action, data) of the requests for jobs this replica holds, oldest first."""
        async with self._connection(internal=True) as conn:
            cur = await conn.execute(
                "SELECT r.id, r.job_id, r.action, r.data FROM job_requests r"
                " JOIN job_leases l ON l.job_id = r.job_id"
                " WHERE l.replica_id = %s AND l.expires_at > now() ORDER BY r.id",
                (replica_id,),
            )
            return [tuple(r) for r in await cur.fetchall()]

    async def controls_done(self, request_ids: list[int]) -> None:
        if not request_ids:
            return
        async with self._connection(internal=True) as conn:
            await conn.execute("DELETE FROM job_requests WHERE id = ANY(%s)", (request_ids,))

    # ------------------------------------------------------------------------- api tokens
    async def create_token(self, token_id: str, name: str, sha256: str, admin: bool) -> TokenRow:
        async with self._connection() as conn:
            cur = conn.cursor(row_factory=dict_row)
            await cur.execute(
                "INSERT INTO api_tokens (id, name, sha256, admin) VALUES (%s, %s, %s, %s)"
                f" RETURNING {_TOKEN_COLUMNS}",
                (token_id, name, sha256, admin),
            )
            return TokenRow(**await cur.fetchone())

    async def list_tokens(self) -> list[TokenRow]:
        async with self._connection() as conn:
            cur = conn.cursor(row_factory=dict_row)
            await cur.execute(f"SELECT {_TOKEN_COLUMNS} FROM api_tokens ORDER BY created_at, id")
            return [TokenRow(**r) for r in await cur.fetchall()]

    async def token_by_hash(self, sha256: str) -> TokenRow | None:
        async with self._connection() as conn:
            cur = conn.cursor(row_factory=dict_row)
            await cur.execute(
                f"SELECT {_TOKEN_COLUMNS} FROM api_tokens WHERE sha256 = %s", (sha256,)
            )
            row = await cur.fetchone()
            return TokenRow(**row) if row else None

    async def live_token_count(self) -> int:
        async with self._connection() as conn:
            cur = await conn.execute("SELECT count(*) FROM api_tokens WHERE revoked_at IS NULL")
            (count,) = await cur.fetchone()
            return count

    async def ensure_token(self, token_id: str, name: str, sha256: str, admin: bool) -> bool:
        """Make sure a token with this hash exists (a revoked one stays revoked); a live token of
        the same name with another hash is revoked (the configured secret was rotated).
        True when a token was created."""
        async with self._connection() as conn:
            async with conn.transaction():
                cur = await conn.execute("SELECT 1 FROM api_tokens WHERE sha256 = %s", (sha256,))
                if await cur.fetchone() is not None:
                    return False
                await conn.execute(
                    "UPDATE api_tokens SET revoked_at = now()"
                    " WHERE name = %s AND revoked_at IS NULL",
                    (name,),
                )
                await conn.execute(
                    "INSERT INTO api_tokens (id, name, sha256, admin) VALUES (%s, %s, %s, %s)",
                    (token_id, name, sha256, admin),
                )
                return True

    async def revoke_token(self, token_id: str) -> TokenRow | None:
        """Revoke a live token (by id); None when there is no such live token."""
        async with self._connection() as conn:
            cur = conn.cursor(row_factory=dict_row)
            await cur.execute(
                "UPDATE api_tokens SET revoked_at = now() WHERE id = %s AND revoked_at IS NULL"
                f" RETURNING {_TOKEN_COLUMNS}",
                (token_id,),
            )
            row = await cur.fetchone()
            return TokenRow(**row) if row else None


async def _check_fence(conn: Any, job_id: str, fence: Fence | None) -> None:
    """Inside a write's transaction: LeaseLost unless the job's lease names fence's replica
    and epoch. The row is locked FOR SHARE until the commit, so a takeover (which updates it)
    waits for this write, and its new owner reads what it wrote."""
    if fence is None:
        return
    cur = await conn.execute(
        "SELECT 1 FROM job_leases WHERE job_id = %s AND replica_id = %s AND epoch = %s FOR SHARE",
        (job_id, fence[0], fence[1]),
    )
    if await cur.fetchone() is None:
        raise LeaseLost(job_id)


async def _fenced_events(
    conn: Any,
    events: list[tuple[str | None, str, dict[str, Any]]],
    fences: dict[str, Fence] | None,
) -> tuple[list[tuple[str | None, str, dict[str, Any]]], list[str]]:
    """The events whose job's lease matches its fence (or that have none), in order, and the
    jobs whose events are refused; the matching lease rows stay locked until the commit."""
    fenced = {j: fences[j] for j, _, _ in events if fences and j in fences}
    if not fenced:
        return events, []
    ids = sorted(fenced)
    cur = await conn.execute(
        "SELECT l.job_id FROM job_leases l"
        " JOIN unnest(%s::text[], %s::text[], %s::bigint[]) AS f(job_id, replica_id, epoch)"
        " ON l.job_id = f.job_id AND l.replica_id = f.replica_id AND l.epoch = f.epoch"
        " ORDER BY l.job_id FOR SHARE OF l",
        (ids, [fenced[j][0] for j in ids], [fenced[j][1] for j in ids]),
    )
    held = {r[0] for r in await cur.fetchall()}
    lost = [j for j in ids if j not in held]
    return [e for e in events if e[0] not in lost], lost


def _ts(unix: float | None) -> datetime | None:
    return None if unix is None else datetime.fromtimestamp(unix, tz=UTC)


def _finite(x: float | None) -> float | None:
    return x if x is not None and math.isfinite(x) else None


def _clean(value: Any) -> Any:
    """JSON has no inf/NaN: store them as null."""
    if isinstance(value, float):
        return _finite(value)
    if isinstance(value, dict):
        return {k: _clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_clean(v) for v in value]
    return value


__all__ = [
    "DatabaseBusy",
    "DatabaseUnavailable",
    "Fence",
    "JobRow",
    "Store",
    "TileRow",
    "TokenRow",
    "migrations",
    "psycopg",
]
