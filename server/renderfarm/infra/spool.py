"""The spool: what a server stopping while the database is unreachable could not write.

At shutdown the server writes everything still unsaved (events, the state of every unfinished
job and of every finished job not yet stored, with their changed tiles) to one file in
DATA_DIR/spool, and at its next start writes that to the database before it resumes any job,
then deletes the file. So a restart never shows less than the server had merged. Replaying is
idempotent (tiles never move backwards, job rows are overwritten with the same values, events
already stored are left out), so a crash between the writes and the file's removal only makes
the next start replay it again.

A file is a header line, then records: one line of JSON each, followed by the binary fields it
announces (their lengths are in the JSON), and an end record. It is written to a temporary
name, synced, and renamed, so a spool file is always complete.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

from .store import Store, TileRow

log = logging.getLogger(__name__)

MAGIC = b"renderfarm-spool 1\n"
SUFFIX = ".spool"


@dataclass
class UnsavedJob:
    job_id: str
    fields: dict[str, Any]  # Store.update_job's keyword arguments
    tiles: list[TileRow] = field(default_factory=list)


def spool_dir(data_dir: Path) -> Path:
    return Path(data_dir) / "spool"


def write(
    directory: Path, events: list[tuple[str | None, str, dict[str, Any]]], jobs: list[UnsavedJob]
) -> Path:
    """Write one spool file; its path. Raises OSError (nothing is left behind then)."""
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / f"unsaved-{time.time_ns()}{SUFFIX}"
    partial = path.with_suffix(".partial")
    try:
        with open(partial, "wb") as out:
            out.write(MAGIC)
            _record(out, {"events": [[j, k, d] for j, k, d in events]})
            for job in jobs:
                header, blobs = _job_record(job)
                _record(out, header, blobs)
            _record(out, {"end": True})
            out.flush()
            os.fsync(out.fileno())
        os.replace(partial, path)
        _sync_dir(directory)
    except BaseException:
        with contextlib.suppress(OSError):
            partial.unlink()
        raise
    return path


def read(path: Path) -> tuple[list[tuple[str | None, str, dict[str, Any]]], list[UnsavedJob]]:
    """A spool file's events and jobs; ValueError for a file that is not a whole spool."""
    events: list[tuple[str | None, str, dict[str, Any]]] = []
    jobs: list[UnsavedJob] = []
    with open(path, "rb") as f:
        if f.readline() != MAGIC:
            raise ValueError(f"{path} is not a renderfarm spool file")
        for header, blobs in _records(f):
            if header.get("end"):
                return events, jobs
            if "events" in header:
                events.extend((j, k, d) for j, k, d in header["events"])
            else:
                jobs.append(_job_from(header, blobs))
    raise ValueError(f"{path} ends before its end record")


async def replay(store: Store, data_dir: Path) -> int:
    """Write every spool file of data_dir to the database, oldest first, deleting each once
    written; the number of files replayed. Database errors propagate (the file stays)."""
    directory = spool_dir(data_dir)
    if not directory.is_dir():
        return 0
    for partial in directory.glob("*.partial"):  # a server killed while writing its spool
        log.warning("removing %s, an incomplete spool file", partial)
        partial.unlink()
    done = 0
    for path in sorted(directory.glob(f"*{SUFFIX}")):
        events, jobs = read(path)
        # Events first, as the server writes them: a job is never stored finished before its
        # job_finished event.
        await store.add_events_once(events)
        for job in jobs:
            if await store.get_job(job.job_id) is None:
                continue  # deleted meanwhile by someone else
            await store.save_tiles(job.job_id, job.tiles)
            await store.update_job(job.job_id, **job.fields)
        path.unlink()
        _sync_dir(directory)
        log.info(
            "replayed the spool %s: %d events, %d jobs (%s)",
            path.name, len(events), len(jobs), ", ".join(j.job_id for j in jobs) or "-",
        )  # fmt: skip
        done += 1
    return done


# ------------------------------------------------------------------------------ encoding
_TILE_BYTES = ("accumulators", "aovs")


def _job_record(job: UnsavedJob) -> tuple[dict[str, Any], list[bytes]]:
    tiles, blobs = [], []
    for t in job.tiles:
        entry = {k: v for k, v in t.__dict__.items() if k not in _TILE_BYTES}
        for name in _TILE_BYTES:
            value = getattr(t, name)
            entry[name] = None if value is None else len(value)
            if value is not None:
                blobs.append(bytes(value))
        tiles.append(entry)
    return {"job": job.job_id, "fields": job.fields, "tiles": tiles}, blobs


def _job_from(header: dict[str, Any], blobs: Iterator[bytes]) -> UnsavedJob:
    tiles = []
    for entry in header["tiles"]:
        values = dict(entry)
        for name in _TILE_BYTES:
            values[name] = None if entry[name] is None else next(blobs)
        tiles.append(TileRow(**values))
    return UnsavedJob(header["job"], header["fields"], tiles)


def _record(out: BinaryIO, header: dict[str, Any], blobs: list[bytes] | None = None) -> None:
    blobs = blobs or []
    header = {**header, "blobs": [len(b) for b in blobs]}
    out.write(json.dumps(header, default=str).encode() + b"\n")
    for b in blobs:
        out.write(b)


def _records(f: BinaryIO) -> Iterator[tuple[dict[str, Any], Iterator[bytes]]]:
    while line := f.readline():
        header = json.loads(line)
        blobs = []
        for n in header.pop("blobs"):
            b = f.read(n)
            if len(b) != n:
                raise ValueError("a spool record ends early")
            blobs.append(b)
        yield header, iter(blobs)


def _sync_dir(directory: Path) -> None:
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
