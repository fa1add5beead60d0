"""The spool of unsaved state (spool.py): what is written is read back unchanged, a file that
is not whole is refused, and a replay writes events before tiles before job rows and removes
the file only once everything is written."""

from __future__ import annotations

import asyncio
import math

import pytest

from renderfarm.infra import spool
from renderfarm.infra.store import TileRow


def tile(index: int, aovs: bytes | None) -> TileRow:
    return TileRow(
        tile_index=index,
        samples=4,
        batches=3,
        nonfinite=0,
        error=math.inf,  # a tile with one batch has no error estimate yet
        accumulators=bytes(range(256)) * 3,
        stop_batch=2 if index else None,
        stop_spp=4 if index else None,
        stop_error=0.01 if index else None,
        stop_reason="max_spp" if index else None,
        aovs=aovs,
        batch_plan=[8, 16] if not index else None,
    )


FIELDS = {
    "state": "completed",
    "error": "",
    "started": 1700000000.25,
    "finished": 1700000003.5,
    "elapsed_s": 3.25,
    "samples_merged": 1024,
    "mean_spp": 4.0,
    "error_estimate": None,
    "tiles_done": 2,
    "tiles_previewed": 2,
}
EVENTS = [
    ("j1", "tile_stopped", {"tile": 1, "error": 0.01}),
    ("j1", "job_finished", {"state": "completed", "error": ""}),
    (None, "note", {"x": [1, 2.5, None]}),
]


def jobs() -> list[spool.UnsavedJob]:
    return [
        spool.UnsavedJob("j1", FIELDS, [tile(0, b"\x00\x01" * 40), tile(1, None)]),
        spool.UnsavedJob("j2", {**FIELDS, "state": "running", "finished": None}, []),
    ]


def test_what_is_written_is_read_back(tmp_path):
    path = spool.write(tmp_path / "spool", EVENTS, jobs())
    assert path.parent == tmp_path / "spool" and path.suffix == ".spool"
    assert [p.name for p in path.parent.iterdir()] == [path.name]  # no temporary file left
    events, read = spool.read(path)
    assert events == EVENTS
    assert [(j.job_id, j.fields) for j in read] == [(j.job_id, j.fields) for j in jobs()]
    for got, wrote in zip(read[0].tiles, jobs()[0].tiles, strict=True):
        assert got.__dict__.keys() == wrote.__dict__.keys()
        for name, value in wrote.__dict__.items():
            assert getattr(got, name) == value, name
    assert read[1].tiles == []


def test_a_truncated_or_foreign_file_is_refused(tmp_path):
    path = spool.write(tmp_path, EVENTS, jobs())
    whole = path.read_bytes()
    for cut in (len(whole) - 3, len(whole) // 2, len(spool.MAGIC) + 5):
        path.write_bytes(whole[:cut])
        with pytest.raises(ValueError):
            spool.read(path)
    path.write_bytes(b"something else\n")
    with pytest.raises(ValueError, match="not a renderfarm spool"):
        spool.read(path)


class RecordingStore:
    """Records the replay's writes; fail_at makes that write raise (the database went away)."""

    def __init__(self, known: set[str], fail_at: str | None = None):
        self.known, self.fail_at, self.log = known, fail_at, []

    def _write(self, what):
        if what[0] == self.fail_at:
            raise OSError("database unreachable")
        self.log.append(what)

    async def add_events_once(self, events, fences=None):
        self._write(("events", [(j, k) for j, k, _ in events]))

    async def get_job(self, job_id):
        return object() if job_id in self.known else None

    async def save_tiles(self, job_id, rows, fence=None):
        self._write(("tiles", job_id, [r.tile_index for r in rows]))

    async def update_job(self, job_id, fence=None, **fields):
        self._write(("job", job_id, fields["state"]))


def test_replay_writes_events_then_tiles_then_rows_and_removes_the_file(tmp_path):
    directory = spool.spool_dir(tmp_path)
    spool.write(directory, EVENTS, jobs())
    (directory / "unsaved-1.partial").write_bytes(b"renderfarm-spool 1\n{")  # a killed writer
    store = RecordingStore(known={"j1"})  # j2 was deleted meanwhile
    assert asyncio.run(spool.replay(store, tmp_path)) == 1
    assert store.log == [
        ("events", [("j1", "tile_stopped"), ("j1", "job_finished"), (None, "note")]),
        ("tiles", "j1", [0, 1]),
        ("job", "j1", "completed"),
    ]
    assert list(directory.iterdir()) == []


def test_a_replay_that_fails_keeps_the_file_for_the_next_start(tmp_path):
    directory = spool.spool_dir(tmp_path)
    path = spool.write(directory, EVENTS, jobs())
    with pytest.raises(OSError):
        asyncio.run(spool.replay(RecordingStore(known={"j1", "j2"}, fail_at="job"), tmp_path))
    assert path.exists()
    store = RecordingStore(known={"j1", "j2"})
    assert asyncio.run(spool.replay(store, tmp_path)) == 1
    assert [w[0] for w in store.log] == ["events", "tiles", "job", "tiles", "job"]
    assert not path.exists()
