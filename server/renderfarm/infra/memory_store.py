"""The store's interface (JobStore) and an implementation in memory (MemoryStore).

store.Store keeps everything in PostgreSQL; MemoryStore keeps the same rows in dictionaries,
for unit tests of the layers above it (the service, the APIs) that need no database. Both are
held to one contract by server/tests/test_store_contract.py, which runs the same assertions
against each, so a test that passes on MemoryStore says something true of the real store.
MemoryStore is not a production store: nothing survives the process. It has no job leases
(a server on it owns every job, collaborators.SoleOwner): the fences its writes are given are
accepted and not checked.
"""

from __future__ import annotations

import copy
import itertools
import json
from dataclasses import replace
from datetime import UTC, datetime, timedelta
from typing import Any, Protocol

from .store import Fence, JobRow, TileRow, TileSummary, TokenRow, _clean, _finite, _ts

_UNFINISHED = ("waiting", "queued", "running", "paused")
_SOURCE_KEYS = ("source_format", "source_sha256", "source_filename")


class JobStore(Protocol):
    """What the server asks of its store (store.Store; MemoryStore for tests)."""

    errors: int
    unreachable: bool

    async def open(self) -> None: ...
    async def close(self) -> None: ...
    async def reconnect(self) -> None: ...
    async def migrate(self) -> int: ...
    async def ping(self) -> None: ...
    async def put_scene(self, sha256: str, fmt: str, filename: str, data: bytes) -> None: ...
    async def get_scene_info(self, sha256: str) -> dict[str, Any] | None: ...
    async def put_scene_source(
        self, sha256: str, source_format: str, source_sha256: str, source_filename: str
    ) -> None: ...
    async def get_scene_source(self, sha256: str) -> dict[str, Any] | None: ...
    async def get_job_scene_source(self, job_id: str) -> dict[str, Any] | None: ...
    async def read_scene(self, sha256: str, offset: int, length: int) -> bytes: ...
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
    ) -> JobRow: ...
    async def update_job(self, job_id: str, **fields: Any) -> None: ...
    async def update_job_spec(
        self, job_id: str, name: str, settings: dict[str, Any], fence: Fence | None = None
    ) -> None: ...
    async def reactivate_job(self, job_id: str, **fields: Any) -> None: ...
    async def waiting_for(self, job_id: str) -> list[str]: ...
    async def get_job(self, job_id: str) -> JobRow | None: ...
    async def list_jobs(
        self,
        state: str | None,
        limit: int,
        after: tuple[datetime, str] | None,
        owner: str | None = None,
    ) -> list[JobRow]: ...
    async def delete_job(self, job_id: str, replica_id: str | None = None) -> bool: ...
    async def unfinished_jobs(self) -> list[JobRow]: ...
    async def save_tiles(
        self, job_id: str, rows: list[TileRow], fence: Fence | None = None
    ) -> None: ...
    async def load_tiles(
        self, job_id: str, first: int = 0, count: int | None = None
    ) -> list[TileRow]: ...
    async def tile_summaries(self, job_id: str) -> list[TileSummary]: ...
    async def add_events(
        self,
        events: list[tuple[str | None, str, dict[str, Any]]],
        fences: dict[str, Fence] | None = None,
    ) -> None: ...
    async def add_events_once(
        self,
        events: list[tuple[str | None, str, dict[str, Any]]],
        fences: dict[str, Fence] | None = None,
    ) -> None: ...
    async def list_events(self, job_id: str, limit: int = 1000) -> list[dict[str, Any]]: ...
    async def worker_connected(
        self, worker_id: str, hostname: str, cores: int, version: str
    ) -> None: ...
    async def worker_disconnected(self, worker_id: str) -> None: ...
    async def mark_all_workers_disconnected(self) -> None: ...
    async def create_token(
        self, token_id: str, name: str, sha256: str, admin: bool
    ) -> TokenRow: ...
    async def list_tokens(self) -> list[TokenRow]: ...
    async def token_by_hash(self, sha256: str) -> TokenRow | None: ...
    async def live_token_count(self) -> int: ...
    async def ensure_token(self, token_id: str, name: str, sha256: str, admin: bool) -> bool: ...
    async def revoke_token(self, token_id: str) -> TokenRow | None: ...


class MemoryStore:
    """store.Store's rows in dictionaries (see the module's docstring). Values handed in and
    out are copies, as a database's would be, so a caller cannot change a stored row."""

    def __init__(self) -> None:
        self.errors = 0
        self.unreachable = False
        self._scenes: dict[str, dict[str, Any]] = {}
        self._jobs: dict[str, JobRow] = {}
        self._job_sources: dict[str, dict[str, str]] = {}  # job id -> its USD source
        self._tiles: dict[str, dict[int, TileRow]] = {}
        self._events: list[dict[str, Any]] = []
        self._event_ids = itertools.count(1)
        self._workers: dict[str, dict[str, Any]] = {}
        self._tokens: dict[str, TokenRow] = {}
        self._clock = datetime.now(UTC)

    def _now(self) -> datetime:
        """The time of a write: never the same twice, so rows created one after another sort
        in that order (as PostgreSQL's now() of separate transactions do)."""
        self._clock = max(datetime.now(UTC), self._clock + timedelta(microseconds=1))
        return self._clock

    # ------------------------------------------------------------------------ lifecycle
    async def open(self) -> None:
        return None

    async def close(self) -> None:
        return None

    async def reconnect(self) -> None:
        return None

    async def migrate(self) -> int:
        from .store import migrations

        return len(migrations())

    async def ping(self) -> None:
        return None

    # ---------------------------------------------------------------------------- scenes
    async def put_scene(self, sha256: str, fmt: str, filename: str, data: bytes) -> None:
        self._scenes.setdefault(
            sha256,
            {"sha256": sha256, "format": fmt, "filename": filename, "size_bytes": len(data),
             "data": bytes(data)},
        )  # fmt: skip

    async def put_scene_source(
        self, sha256: str, source_format: str, source_sha256: str, source_filename: str
    ) -> None:
        if sha256 in self._scenes:  # the database's foreign key to scenes
            self._scenes[sha256].setdefault(
                "source",
                {"source_format": source_format, "source_sha256": source_sha256,
                 "source_filename": source_filename},
            )  # fmt: skip

    async def get_scene_source(self, sha256: str) -> dict[str, Any] | None:
        row = self._scenes.get(sha256)
        return None if row is None or "source" not in row else dict(row["source"])

    async def get_job_scene_source(self, job_id: str) -> dict[str, Any] | None:
        source = self._job_sources.get(job_id)
        return None if source is None else dict(source)

    async def get_scene_info(self, sha256: str) -> dict[str, Any] | None:
        row = self._scenes.get(sha256)
        return (
            None if row is None else {k: v for k, v in row.items() if k not in ("data", "source")}
        )

    async def read_scene(self, sha256: str, offset: int, length: int) -> bytes:
        row = self._scenes.get(sha256)
        return b"" if row is None else row["data"][offset : offset + length]

    # ------------------------------------------------------------------------------ jobs
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
        if job_id in self._jobs:
            raise KeyError(f"duplicate job id {job_id!r}")
        if scene_sha256 not in self._scenes:  # the database's foreign key to scenes
            raise KeyError(f"no stored scene {scene_sha256!r} for job {job_id!r}")
        row = JobRow(
            id=job_id, name=name, state=state, settings=json.loads(json.dumps(settings)),
            scene_sha256=scene_sha256, error="", created_at=self._now(), started_at=None,
            finished_at=None, elapsed_s=0.0, samples_merged=0, mean_spp=0.0,
            error_estimate=None, tiles_total=tiles, tiles_done=0, owner=owner,
            tiles_previewed=0, after_jobs=list(after or []),
            require_tags=list(require_tags or []), variants=list(variants or []),
        )  # fmt: skip
        self._jobs[job_id] = row
        self._tiles[job_id] = {}
        if scene_source is not None:
            self._job_sources[job_id] = {k: str(scene_source[k]) for k in _SOURCE_KEYS}
        self._add_event(job_id, "job_submitted", {"name": name, "state": state,
                                                  "after": list(after or [])})  # fmt: skip
        return copy.deepcopy(row)

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
        row = self._jobs.get(job_id)
        if row is None:
            return
        self._jobs[job_id] = replace(
            row, state=state, error=error, started_at=row.started_at or _ts(started),
            finished_at=_ts(finished), elapsed_s=elapsed_s, samples_merged=samples_merged,
            mean_spp=mean_spp, error_estimate=error_estimate, tiles_done=tiles_done,
            tiles_previewed=tiles_previewed, frames_done=frames_done,
        )  # fmt: skip

    async def update_job_spec(
        self, job_id: str, name: str, settings: dict[str, Any], fence: Fence | None = None
    ) -> None:
        row = self._jobs.get(job_id)
        if row is not None:
            settings = json.loads(json.dumps(settings))
            self._jobs[job_id] = replace(row, name=name, settings=settings)

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
        row = self._jobs.get(job_id)
        if row is None:
            return
        stored = self._tiles[job_id]
        for index in render_again:
            stored.pop(index, None)
        for index, plan, basis, stop in tiles:
            if index in stored:
                stored[index] = replace(
                    stored[index], batch_plan=copy.deepcopy(plan),
                    plan_basis=copy.deepcopy(basis),
                    stop_batch=stop.batch_index if stop else None,
                    stop_spp=stop.spp if stop else None,
                    stop_error=_finite(stop.error) if stop else None,
                    stop_reason=stop.reason.value if stop else None,
                )  # fmt: skip
        self._jobs[job_id] = replace(
            row, settings=json.loads(json.dumps(settings)), state=state, error="",
            finished_at=None, elapsed_s=elapsed_s,
        )  # fmt: skip

    async def waiting_for(self, job_id: str) -> list[str]:
        return [r.id for r in self._jobs.values()
                if job_id in r.after_jobs and r.state in _UNFINISHED]  # fmt: skip

    async def get_job(self, job_id: str) -> JobRow | None:
        row = self._jobs.get(job_id)
        return None if row is None else copy.deepcopy(row)

    async def list_jobs(
        self,
        state: str | None,
        limit: int,
        after: tuple[datetime, str] | None,
        owner: str | None = None,
    ) -> list[JobRow]:
        rows = [
            r for r in self._jobs.values()
            if (not state or r.state == state) and (owner is None or r.owner == owner)
            and (after is None or (r.created_at, r.id) < after)
        ]  # fmt: skip
        rows.sort(key=lambda r: (r.created_at, r.id), reverse=True)
        return copy.deepcopy(rows[:limit])

    async def delete_job(self, job_id: str, replica_id: str | None = None) -> bool:
        row = self._jobs.pop(job_id, None)
        if row is None:
            return False
        self._tiles.pop(job_id, None)
        self._job_sources.pop(job_id, None)
        self._events = [e for e in self._events if e["job_id"] != job_id]
        for sha in {row.scene_sha256, row.settings.get("environment")} - {None, ""}:
            used = any(r.scene_sha256 == sha or r.settings.get("environment") == sha
                       for r in self._jobs.values())  # fmt: skip
            if not used:
                self._scenes.pop(sha, None)
        return True

    async def unfinished_jobs(self) -> list[JobRow]:
        rows = [r for r in self._jobs.values() if r.state in _UNFINISHED]
        return copy.deepcopy(sorted(rows, key=lambda r: r.created_at))

    # ----------------------------------------------------------------------------- tiles
    async def save_tiles(
        self, job_id: str, rows: list[TileRow], fence: Fence | None = None
    ) -> None:
        stored = self._tiles.get(job_id)
        if stored is None:  # the database refuses a tile of no job (foreign key)
            raise KeyError(f"no job {job_id!r}")
        for r in rows:
            old = stored.get(r.tile_index)
            if old is not None and old.batches > r.batches:
                continue  # never move a tile backwards
            stored[r.tile_index] = replace(
                copy.deepcopy(r), accumulators=bytes(r.accumulators), error=_finite(r.error),
                stop_error=_finite(r.stop_error),
                aovs=bytes(r.aovs) if r.aovs is not None else (old.aovs if old else None),
            )  # fmt: skip

    async def load_tiles(
        self, job_id: str, first: int = 0, count: int | None = None
    ) -> list[TileRow]:
        last = 2**31 - 1 if count is None else first + count - 1
        stored = self._tiles.get(job_id, {})
        return [copy.deepcopy(stored[i]) for i in sorted(stored) if first <= i <= last]

    async def tile_summaries(self, job_id: str) -> list[TileSummary]:
        stored = self._tiles.get(job_id, {})
        return [
            TileSummary(i, stored[i].samples, stored[i].error, stored[i].stop_reason is not None)
            for i in sorted(stored)
        ]

    # ---------------------------------------------------------------------------- events
    def _add_event(self, job_id: str | None, kind: str, data: dict[str, Any]) -> None:
        self._events.append({
            "id": next(self._event_ids), "job_id": job_id, "kind": kind,
            "data": json.loads(json.dumps(_clean(data), default=str)), "at": self._now(),
        })  # fmt: skip

    async def add_events(
        self,
        events: list[tuple[str | None, str, dict[str, Any]]],
        fences: dict[str, Fence] | None = None,
    ) -> None:
        for job_id, kind, data in events:
            if job_id in self._jobs:  # events of a job deleted meanwhile are dropped
                self._add_event(job_id, kind, data)

    async def add_events_once(
        self,
        events: list[tuple[str | None, str, dict[str, Any]]],
        fences: dict[str, Fence] | None = None,
    ) -> None:
        for job_id, kind, data in events:
            clean = json.loads(json.dumps(_clean(data), default=str))
            seen = any(e["job_id"] == job_id and e["kind"] == kind and e["data"] == clean
                       for e in self._events)  # fmt: skip
            if job_id in self._jobs and not seen:
                self._add_event(job_id, kind, data)

    async def list_events(self, job_id: str, limit: int = 1000) -> list[dict[str, Any]]:
        return [{k: copy.deepcopy(e[k]) for k in ("id", "kind", "data", "at")}
                for e in self._events if e["job_id"] == job_id][:limit]  # fmt: skip

    # --------------------------------------------------------------------------- workers
    async def worker_connected(self, worker_id: str, hostname: str, cores: int, version: str):
        now = self._now()
        self._workers[worker_id] = {
            "hostname": hostname, "cores": cores, "version": version,
            "connected_at": now, "last_seen": now, "connected": True,
        }  # fmt: skip

    async def worker_disconnected(self, worker_id: str) -> None:
        if worker_id in self._workers:
            self._workers[worker_id].update(connected=False, last_seen=self._now())

    async def mark_all_workers_disconnected(self) -> None:
        for worker in self._workers.values():
            worker["connected"] = False

    # ------------------------------------------------------------------------ api tokens
    async def create_token(self, token_id: str, name: str, sha256: str, admin: bool) -> TokenRow:
        if token_id in self._tokens or any(t.sha256 == sha256 for t in self._tokens.values()):
            raise KeyError("duplicate token id or hash")
        row = TokenRow(token_id, name, sha256, admin, self._now(), None)
        self._tokens[token_id] = row
        return row

    async def list_tokens(self) -> list[TokenRow]:
        return sorted(self._tokens.values(), key=lambda t: (t.created_at, t.id))

    async def token_by_hash(self, sha256: str) -> TokenRow | None:
        return next((t for t in self._tokens.values() if t.sha256 == sha256), None)

    async def live_token_count(self) -> int:
        return sum(t.revoked_at is None for t in self._tokens.values())

    async def ensure_token(self, token_id: str, name: str, sha256: str, admin: bool) -> bool:
        if await self.token_by_hash(sha256) is not None:
            return False
        for t in list(self._tokens.values()):
            if t.name == name and t.revoked_at is None:
                self._tokens[t.id] = replace(t, revoked_at=self._now())
        await self.create_token(token_id, name, sha256, admin)
        return True

    async def revoke_token(self, token_id: str) -> TokenRow | None:
        t = self._tokens.get(token_id)
        if t is None or t.revoked_at is not None:
            return None
        self._tokens[token_id] = replace(t, revoked_at=self._now())
        return self._tokens[token_id]
