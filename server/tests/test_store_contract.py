"""One contract for both stores: every scenario here runs against store.Store on the embedded
PostgreSQL and against memory_store.MemoryStore, and asserts values the test itself chose. A
unit test that uses MemoryStore in place of the database therefore relies only on behaviour the
real store has too."""

from __future__ import annotations

import asyncio
import hashlib
from datetime import datetime

import psycopg
import pytest
from psycopg.conninfo import make_conninfo

from renderfarm.domain.scheduler import StopRecord
from renderfarm.domain.states import StopReason
from renderfarm.infra.memory_store import JobStore, MemoryStore
from renderfarm.infra.store import Store, TileRow

T0 = 1_800_000_000.0  # 2027-01-15 08:00 UTC


@pytest.fixture(params=["postgres", "memory"])
def run(request):
    """run(body): `await body(store)` on a fresh, opened store of the parametrized kind."""
    kind = request.param
    url = None
    if kind == "postgres":
        server = request.getfixturevalue("postgres")
        name = "c_" + hashlib.sha256(request.node.nodeid.encode()).hexdigest()[:16]
        with psycopg.connect(server, autocommit=True) as conn:
            conn.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')
            conn.execute(f'CREATE DATABASE "{name}"')
        url = make_conninfo(server, dbname=name)

    def go(body):
        async def main():
            store: JobStore = Store(url, max_size=2, internal_size=2) if url else MemoryStore()
            await store.open()
            try:
                return await body(store)
            finally:
                await store.close()

        return asyncio.run(main())

    yield go
    if url is not None:
        with psycopg.connect(request.getfixturevalue("postgres"), autocommit=True) as conn:
            conn.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')


def sha(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


def tile(index: int, batches: int, fill: int, aovs: bytes | None = b"A" * 8, **kw) -> TileRow:
    defaults = dict(
        samples=batches * 2, nonfinite=0, error=0.5, stop_batch=None, stop_spp=None,
        stop_error=None, stop_reason=None, batch_plan=None, plan_basis=None,
    )  # fmt: skip
    defaults.update(kw)
    return TileRow(index, batches=batches, accumulators=bytes([fill]) * 16, aovs=aovs, **defaults)


def test_scenes_are_stored_once_and_read_in_chunks(run):
    data = bytes(range(256)) * 10

    async def body(store):
        await store.put_scene(sha("s"), "glb", "a.glb", data)
        await store.put_scene(sha("s"), "glb", "other-name.glb", b"ignored")  # first one stays
        info = await store.get_scene_info(sha("s"))
        chunks = [await store.read_scene(sha("s"), off, 1000) for off in range(0, 3000, 1000)]
        return info, chunks, await store.get_scene_info(sha("missing"))

    info, chunks, missing = run(body)
    assert info == {"sha256": sha("s"), "format": "glb", "filename": "a.glb", "size_bytes": 2560}
    assert b"".join(chunks) == data and len(chunks[2]) == 560
    assert missing is None


def test_jobs_insert_update_list_and_page(run):
    async def body(store):
        await store.put_scene(sha("s"), "glb", "s.glb", b"x")
        rows = []
        for i in range(5):
            rows.append(await store.insert_job(
                f"job{i}", f"n{i}", {"width": 8 + i}, sha("s"), tiles=4,
                owner="ann" if i % 2 else "bob", state="queued" if i < 4 else "waiting",
                after=["job0"] if i == 4 else None, require_tags=["gpu"] if i == 3 else None,
                variants=["Red", "Blue"] if i == 2 else None,
            ))  # fmt: skip
        await store.update_job(
            "job1",
            state="completed",
            error="",
            started=T0,
            finished=T0 + 10,
            elapsed_s=10.0,
            samples_merged=123,
            mean_spp=4.5,
            error_estimate=0.01,
            tiles_done=4,
            tiles_previewed=4,
        )
        # started_at is kept once set
        await store.update_job(
            "job1",
            state="completed",
            error="",
            started=T0 + 99,
            finished=T0 + 10,
            elapsed_s=10.0,
            samples_merged=123,
            mean_spp=4.5,
            error_estimate=0.01,
            tiles_done=4,
            tiles_previewed=4,
        )
        await store.update_job_spec("job2", "renamed", {"width": 99})
        first = await store.list_jobs(None, 2, None)
        second = await store.list_jobs(None, 2, (first[-1].created_at, first[-1].id))
        return (rows, await store.get_job("job1"), await store.get_job("job2"), first, second,
                await store.list_jobs("queued", 10, None), await store.list_jobs(None, 10, None,
                owner="ann"), await store.unfinished_jobs(), await store.waiting_for("job0"),
                await store.get_job("nope"))  # fmt: skip

    rows, done, renamed, first, second, queued, ann, unfinished, waiting, nope = run(body)
    assert rows[4].state == "waiting" and rows[4].after_jobs == ["job0"]
    assert rows[3].require_tags == ["gpu"] and rows[0].tiles_total == 4 and rows[0].error == ""
    assert rows[2].variants == ["Red", "Blue"] == renamed.variants and rows[0].variants == []
    assert isinstance(rows[0].created_at, datetime) and rows[0].started_at is None
    assert done.state == "completed" and done.started_at.timestamp() == T0
    assert done.finished_at.timestamp() == T0 + 10
    assert (done.samples_merged, done.mean_spp, done.error_estimate) == (123, 4.5, 0.01)
    assert (done.tiles_done, done.tiles_previewed) == (4, 4)
    assert renamed.name == "renamed" and renamed.settings == {"width": 99}
    assert [r.id for r in first] == ["job4", "job3"] and [r.id for r in second] == ["job2", "job1"]
    assert [r.id for r in queued] == ["job3", "job2", "job0"]
    assert [r.id for r in ann] == ["job3", "job1"]
    assert [r.id for r in unfinished] == ["job0", "job2", "job3", "job4"]
    assert waiting == ["job4"] and nope is None


def test_tiles_round_trip_and_never_move_backwards(run):
    async def body(store):
        await store.put_scene(sha("s"), "glb", "s.glb", b"x")
        await store.insert_job("j", "n", {}, sha("s"), tiles=3)
        await store.save_tiles(
            "j", [tile(0, 3, 1), tile(1, 2, 2), tile(2, 1, 3, error=float("inf"))]
        )
        # older batches lose; aovs None keeps the stored ones
        newer = tile(1, 4, 5, aovs=None, batch_plan=[8, 8], plan_basis=[[1, 2, None, 3]])
        await store.save_tiles("j", [tile(0, 2, 9), newer])
        return await store.load_tiles("j"), await store.load_tiles("j", first=1, count=1)

    rows, one = run(body)
    assert [(r.tile_index, r.batches, r.accumulators) for r in rows] == [
        (0, 3, b"\x01" * 16), (1, 4, b"\x05" * 16), (2, 1, b"\x03" * 16)]  # fmt: skip
    assert rows[1].aovs == b"A" * 8 and rows[1].batch_plan == [8, 8]
    assert rows[1].plan_basis == [[1, 2, None, 3]]
    assert rows[2].error is None  # infinities are stored as null
    assert [r.tile_index for r in one] == [1]


def test_reactivation_drops_and_rewrites_tiles_in_one_step(run):
    stop = StopRecord(tile_index=1, batch_index=3, spp=6, error=0.01, reason=StopReason.CONVERGED)

    async def body(store):
        await store.put_scene(sha("s"), "glb", "s.glb", b"x")
        await store.insert_job("j", "n", {"max_spp": 4}, sha("s"), tiles=3)
        await store.update_job(
            "j",
            state="completed",
            error="",
            started=T0,
            finished=T0 + 5,
            elapsed_s=5.0,
            samples_merged=1,
            mean_spp=1.0,
            error_estimate=0.1,
            tiles_done=3,
            tiles_previewed=3,
        )
        await store.save_tiles("j", [tile(0, 1, 1), tile(1, 1, 2), tile(2, 1, 3)])
        await store.reactivate_job(
            "j",
            settings={"max_spp": 64},
            state="queued",
            elapsed_s=5.0,
            render_again=[0],
            tiles=[(1, [8], [[1, 2, 0.5, 0]], stop), (2, None, None, None)],
        )
        return await store.get_job("j"), await store.load_tiles("j")

    job, rows = run(body)
    assert (job.state, job.settings, job.finished_at, job.error) == (
        "queued", {"max_spp": 64}, None, "")  # fmt: skip
    assert [r.tile_index for r in rows] == [1, 2]
    assert (rows[0].batch_plan, rows[0].stop_batch, rows[0].stop_spp, rows[0].stop_reason) == (
        [8], 3, 6, "converged")  # fmt: skip
    assert rows[1].stop_reason is None and rows[1].batch_plan is None


def test_events_in_order_once_and_dropped_for_missing_jobs(run):
    async def body(store):
        await store.put_scene(sha("s"), "glb", "s.glb", b"x")
        await store.insert_job("j", "n", {}, sha("s"), tiles=1)
        nan = {"v": float("nan")}
        await store.add_events([("j", "a", {"x": 1.5}), ("gone", "b", {}), ("j", "c", nan)])
        await store.add_events_once([("j", "a", {"x": 1.5}), ("j", "d", {"k": [1, 2]})])
        await store.add_events_once([("j", "d", {"k": [1, 2]})])
        return await store.list_events("j"), await store.list_events("j", limit=2)

    events, two = run(body)
    assert [(e["kind"], e["data"]) for e in events] == [
        ("job_submitted", {"name": "n", "state": "queued", "after": []}),
        ("a", {"x": 1.5}), ("c", {"v": None}), ("d", {"k": [1, 2]})]  # fmt: skip
    ids = [e["id"] for e in events]
    assert ids == sorted(ids) and len(set(ids)) == 4 and len(two) == 2
    assert all(isinstance(e["at"], datetime) for e in events)


def test_deleting_a_job_takes_its_rows_and_unshared_scenes(run):
    async def body(store):
        for s in ("shared", "own", "env"):
            await store.put_scene(sha(s), "glb", s, b"x")
        await store.insert_job("a", "a", {"environment": sha("env")}, sha("own"), tiles=1)
        await store.insert_job("b", "b", {}, sha("shared"), tiles=1)
        await store.insert_job("c", "c", {}, sha("shared"), tiles=1)
        await store.save_tiles("a", [tile(0, 1, 1)])
        gone = await store.delete_job("a"), await store.delete_job("b"), await store.delete_job("a")
        kept = [await store.get_scene_info(sha(s)) is not None for s in ("shared", "own", "env")]
        job, tiles = await store.get_job("a"), await store.load_tiles("a")
        return gone, job, tiles, await store.list_events("a"), kept

    gone, job, tiles, events, scenes = run(body)
    assert gone == (True, True, False) and job is None and tiles == [] and events == []
    assert scenes == [True, False, False]


def test_a_scene_remembers_its_source_once_and_loses_it_with_the_scene(run):
    async def body(store):
        await store.put_scene(sha("glb"), "glb", "shot.glb", b"x")
        before = await store.get_scene_source(sha("glb"))
        await store.put_scene_source(sha("glb"), "usd", sha("usd"), "shot.usdz")
        await store.put_scene_source(sha("glb"), "usd", sha("other"), "again.usdz")  # kept first
        source = await store.get_scene_source(sha("glb"))
        info = await store.get_scene_info(sha("glb"))
        await store.insert_job("j", "j", {}, sha("glb"), tiles=1)
        await store.delete_job("j")  # the scene goes with its last job, and its source with it
        return before, source, info, await store.get_scene_source(sha("glb"))

    before, source, info, after = run(body)
    assert before is None and after is None
    assert source == {"source_format": "usd", "source_sha256": sha("usd"),
                      "source_filename": "shot.usdz"}  # fmt: skip
    assert info == {"sha256": sha("glb"), "format": "glb", "filename": "shot.glb", "size_bytes": 1}


def test_a_job_keeps_the_source_it_was_submitted_with_and_loses_it_with_the_job(run):
    """Two uploads converted to one scene: each job names its own upload, whatever the scene's
    record (the first upload's) says; a job given no source has none; deleting a job drops
    its source and leaves the other's."""
    first = {"source_format": "usd", "source_sha256": sha("take 1"), "source_filename": "a.usda"}
    second = {"source_format": "usd", "source_sha256": sha("take 2"), "source_filename": "b.usda"}

    async def body(store):
        await store.put_scene(sha("glb"), "glb", "shot.glb", b"x")
        await store.put_scene_source(sha("glb"), "usd", sha("take 1"), "a.usda")
        await store.put_scene_source(sha("glb"), "usd", sha("take 2"), "b.usda")  # kept first
        await store.insert_job("one", "one", {}, sha("glb"), tiles=1, scene_source=first)
        await store.insert_job("two", "two", {}, sha("glb"), tiles=1, scene_source=second)
        await store.insert_job("bare", "bare", {}, sha("glb"), tiles=1)
        sources = [await store.get_job_scene_source(j) for j in ("one", "two", "bare")]
        await store.delete_job("one")
        after = [await store.get_job_scene_source(j) for j in ("one", "two")]
        return sources, after, await store.get_scene_source(sha("glb"))

    sources, after, scene = run(body)
    assert sources == [first, second, None]
    assert after == [None, second]
    assert scene == first  # the scene's own record: the first upload's


def test_a_job_needs_its_scene_stored(run):
    async def body(store):
        with pytest.raises(Exception) as refused:
            await store.insert_job("j", "n", {}, sha("never stored"), tiles=1)
        return refused.value, await store.get_job("j")

    refused, job = run(body)
    assert "scene" in str(refused) and job is None


def test_tokens_create_find_rotate_and_revoke(run):
    async def body(store):
        a = await store.create_token("t1", "ann", sha("secret-1"), admin=False)
        created = await store.ensure_token("t2", "ops", sha("secret-2"), admin=True)
        again = await store.ensure_token("t3", "ops", sha("secret-2"), admin=True)
        rotated = await store.ensure_token("t4", "ops", sha("secret-3"), admin=True)
        revoked = await store.revoke_token("t1")
        twice = await store.revoke_token("t1")
        tokens, found = await store.list_tokens(), await store.token_by_hash(sha("secret-3"))
        return (
            a,
            created,
            again,
            rotated,
            revoked,
            twice,
            tokens,
            found,
            await store.live_token_count(),
        )

    a, created, again, rotated, revoked, twice, tokens, found, live = run(body)
    assert (a.id, a.name, a.admin, a.revoked_at) == ("t1", "ann", False, None)
    assert (created, again, rotated) == (True, False, True)
    assert revoked.id == "t1" and revoked.revoked_at is not None and twice is None
    assert [t.id for t in tokens] == ["t1", "t2", "t4"]
    assert [t.revoked_at is None for t in tokens] == [False, False, True]
    assert found.id == "t4" and found.admin and live == 1


def test_workers_table_accepts_the_lifecycle(run):
    async def body(store):
        await store.worker_connected("w1", "host", 8, "1.0")
        await store.worker_connected("w1", "host2", 4, "1.1")  # a reconnect replaces the row
        await store.worker_disconnected("w1")
        await store.worker_disconnected("never-seen")
        await store.mark_all_workers_disconnected()
        await store.ping()
        return store.errors

    assert run(body) == 0
