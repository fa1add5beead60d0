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

from ..errors import LeaseLost
from .store import Fence, Store, TileRow

log = logging.getLogger(__name__)

MAGIC = b"renderfarm-spool 1\n"
SUFFIX = ".spool"


@dataclass
class UnsavedJob:
    job_id: str
    fields: dict[str, Any]  # Store.update_job's keyword arguments
    tiles: list[TileRow] = field(default_factory=list)
    # The owner's fence when it was written (a farm of several servers): replayed only while
    # the job's lease still names that replica and epoch. None: written as it is.
    fence: Fence | None = None


def spool_dir(data_dir: Path) -> Path:
    return Path(data_dir) / "spool"


def write(
    directory: Path,
    events: list[tuple[str | None, str, dict[str, Any]]],
    jobs: list[UnsavedJob],
    fences: dict[str, Fence] | None = None,
) -> Path:
    """Write one spool file; its path. Raises OSError (nothing is left behind then)."""
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / f"unsaved-{time.time_ns()}{SUFFIX}"
    partial = path.with_suffix(".partial")
    try:
        with open(partial, "wb") as out:
            out.write(MAGIC)
            _record(
                out,
                {
                    "events": [[j, k, d] for j, k, d in events],
                    "fences": {j: list(f) for j, f in (fences or {}).items()},
                },
            )
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
    events, jobs, _ = read_fenced(path)
    return events, jobs


def read_fenced(
    path: Path,
) -> tuple[list[tuple[str | None, str, dict[str, Any]]], list[UnsavedJob], dict[str, Fence]]:
    """read, with the fences of the events' jobs."""
    events: list[tuple[str | None, str, dict[str, Any]]] = []
    jobs: list[UnsavedJob] = []
    fences: dict[str, Fence] = {}
    with open(path, "rb") as f:
        if f.readline() != MAGIC:
            raise ValueError(f"{path} is not a renderfarm spool file")
        for header, blobs in _records(f):
            if header.get("end"):
                return events, jobs, fences
            if "events" in header:
                events.extend((j, k, d) for j, k, d in header["events"])
                fences.update({j: (f[0], f[1]) for j, f in header.get("fences", {}).items()})
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
        events, jobs, fences = read_fenced(path)
        # Events first, as the server writes them: a job is never stored finished before its
        # job_finished event. A job another server took over meanwhile (its fence refused)
        # is its new owner's: what was kept of it here is dropped.
        lost: set[str] = set()
        try:
            await store.add_events_once(events, fences)
        except LeaseLost as e:
            lost.update(e.job_ids)
        for job in jobs:
            if job.job_id in lost or await store.get_job(job.job_id) is None:
                continue  # deleted meanwhile by someone else
            try:
                await store.save_tiles(job.job_id, job.tiles, fence=job.fence)
                await store.update_job(job.job_id, **job.fields, fence=job.fence)
            except LeaseLost:
                lost.add(job.job_id)
        if lost:
            log.warning(
                "the spool's jobs %s are owned by another server now; left to it",
                ", ".join(sorted(lost)),
            )
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
    header = {"job": job.job_id, "fields": job.fields, "tiles": tiles}
    if job.fence is not None:
        header["fence"] = list(job.fence)
    return header, blobs


def _job_from(header: dict[str, Any], blobs: Iterator[bytes]) -> UnsavedJob:
    tiles = []
    for entry in header["tiles"]:
        values = dict(entry)
        for name in _TILE_BYTES:
            values[name] = None if entry[name] is None else next(blobs)
        tiles.append(TileRow(**values))
    fence = header.get("fence")
    return UnsavedJob(
        header["job"], header["fields"], tiles, None if fence is None else (fence[0], fence[1])
    )


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
