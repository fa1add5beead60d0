"""Several servers over one database (#39): two FarmServices, replicas "A" and "B", each with
its own Store and LeaseOwnership, over one embedded PostgreSQL (a Unix socket in a temporary
directory; a database of its own per test). Workers are fakes that render with
test_scheduler.render, so an image is a pure function of the job's settings and a test can
compare bits (docs/architecture.md, "Ownership, leases and fencing").

Nothing here sleeps for a fixed time: a takeover is waited for by running B's background round
until B holds the job, with a deadline. The job lease is LEASE_S seconds of the database's
clock; A "stops" by no longer being driven (no rounds, no heartbeats), and A's owns() is kept
true by a clock that does not move (a process paused between its check and its write), so
only the database's fence stands between A's late writes and B's work."""

from __future__ import annotations

import asyncio
import dataclasses
import hashlib
import time
from pathlib import Path

import httpx
from test_scheduler import render
from test_service_collaborators import NoScenes

from renderfarm.api.rest import create_app
from renderfarm.app.auth import LOCAL_USER, Authenticator
from renderfarm.app.composition import build_farm_service
from renderfarm.domain.states import JobState
from renderfarm.errors import LeaseLost
from renderfarm.infra.config import Settings
from renderfarm.infra.leases import LeaseOwnership
from renderfarm.infra.store import Store

LEASE_S = 1.0  # the shortest the setting allows: a takeover within a few seconds
JOB = {"width": 16, "height": 16, "tile_size": 8, "max_spp": 64, "noise_threshold": 0, "seed": 7}
TASKS = 4 * 7  # 4 tiles x batches of 1, 1, 2, 4, 8, 16, 32 samples
SCENE = b"glTF\x02\x00\x00\x00" + bytes(range(256)) * 4
SCENE_SHA = hashlib.sha256(SCENE).hexdigest()


class StoppedClock:
    """A monotonic clock that moves only when told: the replica's owns() stays as it was."""

    def __init__(self):
        self.now = time.monotonic()

    def __call__(self) -> float:
        return self.now


class Replica:
    """A FarmService named `name` over its own Store, driven by the test (its background task
    is not started: each round is called)."""

    def __init__(
        self, url: str, data_dir: Path, name: str, monotonic=time.monotonic, lease_s=LEASE_S
    ):
        self.name = name
        self.store = Store(url, max_size=2, internal_size=2)
        settings = Settings(
            data_dir=data_dir / name, replica_id=name, job_lease_s=lease_s,
            checkpoint_interval_s=3600.0,  # checkpoints when the test says (force)
        )  # fmt: skip
        self.ownership = LeaseOwnership(self.store, name, lease_s=lease_s, monotonic=monotonic)
        self.service = build_farm_service(
            settings, self.store, ownership=self.ownership, scene_checker=NoScenes(),
            usd_importer=NoScenes(),
        )  # fmt: skip
        self.session = None

    async def open(self) -> Replica:
        await self.store.open()
        await self.service.ownership.heartbeat()
        self.session = await self.service.worker_hello(
            f"worker-{self.name}", "host", 2, 4, "test", token=""
        )
        return self

    async def close(self) -> None:
        await self.store.close()

    async def work(self, results: int) -> int:
        """Render and send back up to `results` of the tasks leased to this replica's worker;
        how many it sent."""
        sent = 0
        while sent < results and not self.session.outbox.empty():
            message = self.session.outbox.get_nowait()
            if message is None or message[0] != "assign":
                continue
            _, lease, job = message
            result = render(job.settings, lease)
            await self.service.worker_result(self.session, lease.task_id, result)
            sent += 1
        return sent


async def submit(replica: Replica, name: str = "job", after: list[str] | None = None) -> str:
    await replica.store.put_scene(SCENE_SHA, "glb", "scene.glb", SCENE)
    view = await replica.service.submit(
        scene_data=None, scene_sha256=SCENE_SHA, filename="scene.glb", name=name,
        raw_settings=dict(JOB), caller=LOCAL_USER, after=after,
    )  # fmt: skip
    return view.id


async def until(condition, timeout_s: float, what: str):
    """condition()'s (awaited) first truthy value; AssertionError naming `what` at the deadline."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = await condition()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        await asyncio.sleep(0.02)


async def finish(replica: Replica, job: str) -> None:
    """Render the job on the replica until its row says completed."""

    async def done():
        await replica.work(100)
        await replica.service._round()
        row = await replica.store.get_job(job)
        return row.state == "completed"

    await until(done, 60, f"job {job} completed on {replica.name}")


async def stored_tiles(store: Store, job_id: str) -> list[tuple]:
    return [
        (t.tile_index, t.samples, t.batches, bytes(t.accumulators), t.stop_batch, t.stop_reason)
        for t in await store.load_tiles(job_id)
    ]


async def take_over(b: Replica, job_id: str) -> float:
    """Run B's rounds until B holds the job; seconds it took."""
    started = time.monotonic()

    async def holds():
        await b.service._round()
        return b.ownership.owns(job_id)

    await until(holds, 10 * LEASE_S, f"replica {b.name} to take job {job_id} over")
    return time.monotonic() - started


def test_only_one_replica_acquires_a_job(db_url, tmp_path):
    async def main():
        a = await Replica(db_url, tmp_path, "A").open()
        b = await Replica(db_url, tmp_path, "B").open()
        try:
            job = await submit(a)
            refused = await b.ownership.acquire(job)
            await b.service._round()  # its takeover leaves a job A holds alone
            views = (await a.service.get(job, LOCAL_USER), await b.service.get(job, LOCAL_USER))
            # A job nobody holds yet (as just after an insert): both ask at once.
            await a.store.insert_job("race", "race", {}, SCENE_SHA, 4)
            raced = await asyncio.gather(a.ownership.acquire("race"), b.ownership.acquire("race"))
            lease = await a.store.lease_of("race")
            return (
                job,
                refused,
                b.service.scheduler.jobs,
                views,
                raced,
                lease,
                await a.store.lease_of(job),
            )
        finally:
            await a.close()
            await b.close()

    job, refused, b_jobs, views, raced, lease, job_lease = asyncio.run(main())
    assert refused is False and job not in b_jobs
    assert job_lease == ("A", 1, True)
    assert [v.replica for v in views] == ["A", "A"]  # B answers for it from the database
    assert [v.to_json()["replica"] for v in views] == ["A", "A"]
    assert sorted(raced) == [False, True]
    assert lease[1:] == (1, True) and lease[0] == ("A" if raced[0] else "B")


def test_a_replica_that_stops_renewing_loses_the_job_and_its_late_writes_are_refused(
    db_url, tmp_path
):
    paused = StoppedClock()

    async def main():
        a = await Replica(db_url, tmp_path, "A", monotonic=paused).open()
        b = await Replica(db_url, tmp_path, "B").open()
        try:
            job = await submit(a)
            assert await a.work(6) == 6
            await a.service.checkpoint(force=True)
            checkpointed = await stored_tiles(a.store, job)
            assert await a.work(4) == 4  # merged, not checkpointed: lost with A
            a.service._pending_events.append((job, "a_late_event", {}))
            # A stops here: no heartbeat, no round. Its owns() stays true (a paused process).
            took = await take_over(b, job)
            resumed = {i: t.acc.batches for i, t in enumerate(b.service.scheduler.jobs[job].tiles)}
            assert await b.work(5) == 5
            await b.service.checkpoint(force=True)
            b_tiles = await stored_tiles(b.store, job)
            b_row = await b.store.get_job(job)
            # A wakes up and writes as if it still owned the job.
            assert a.ownership.owns(job)
            refused = {}
            a_job = a.service.scheduler.jobs[job]
            for t in a_job.tiles:
                t.dirty = True
            await a.service.checkpoint(force=True)  # refused: A drops the job
            dropped = job not in a.service.scheduler.jobs and a.service.jobs_lost == 1
            ahead = [  # rows a tile ahead of B's: only the fence keeps them out
                dataclasses.replace(t, batches=t.batches + 1, samples=t.samples + 64)
                for t in await a.store.load_tiles(job)
            ]
            for name, write in {
                "save_tiles": a.store.save_tiles(job, ahead, fence=("A", 1)),
                "update_job": a.store.update_job(
                    job, state="completed", error="", started=None, finished=None,
                    elapsed_s=1.0, samples_merged=1, mean_spp=1.0, error_estimate=None,
                    tiles_done=4, tiles_previewed=4, fence=("A", 1),
                ),
                "update_job_spec": a.store.update_job_spec(job, "A's", {}, fence=("A", 1)),
                "reactivate_job": a.store.reactivate_job(
                    job, settings={}, state="queued", elapsed_s=0.0, render_again=[0], tiles=[],
                    fence=("A", 1),
                ),
                "add_events": a.store.add_events([(job, "a_late", {})], {job: ("A", 1)}),
            }.items():  # fmt: skip
                try:
                    await write
                    refused[name] = False
                except LeaseLost as e:
                    refused[name] = e.job_ids == [job]
            await a.service.flush(force=True)  # A's pending event: dropped with the job
            after = (
                await stored_tiles(b.store, job), await b.store.get_job(job),
                [e["kind"] for e in await b.store.list_events(job)],
            )  # fmt: skip
            # A's heartbeat, once it runs again, finds the job gone as well.
            paused.now += 10 * LEASE_S
            await a.ownership.heartbeat()
            return (
                job, checkpointed, took, resumed, b_tiles, b_row, refused, dropped, after,
                await b.store.lease_of(job), a.ownership.owns(job), a.session,
            )  # fmt: skip
        finally:
            await a.close()
            await b.close()

    (job, checkpointed, took, resumed, b_tiles, b_row, refused, dropped, after, lease, a_owns,
     a_session) = asyncio.run(main())  # fmt: skip
    # B took the job with the next epoch within the lease (and a quarter, its takeover period).
    assert lease == ("B", 2, True)
    assert took < LEASE_S + LEASE_S / 4 + 2.0
    # ... from A's checkpoint: the batches A merged after it are not there.
    assert resumed == {t[0]: t[2] for t in checkpointed}
    assert b_tiles != checkpointed
    # The database still holds B's work: every late write of A was refused.
    stored_tiles_after, row_after, kinds = after
    assert stored_tiles_after == b_tiles
    assert row_after == b_row and row_after.replica == "B"
    assert "a_late_event" not in kinds and "a_late" not in kinds
    assert refused == dict.fromkeys(refused, True) and len(refused) == 5
    assert dropped and not a_owns


def test_a_job_taken_over_after_its_owner_died_renders_the_bits_of_an_undisturbed_run(
    db_url, tmp_path
):
    async def main():
        alone = await Replica(db_url, tmp_path, "C").open()
        a = await Replica(db_url, tmp_path, "A").open()
        b = await Replica(db_url, tmp_path, "B").open()
        try:
            undisturbed = await submit(alone, "undisturbed")
            await finish(alone, undisturbed)
            job = await submit(a, "disturbed")
            await a.work(9)
            await a.service.checkpoint(force=True)
            await a.work(5)  # merged after the checkpoint: A dies with them ("kill -9")
            await a.close()
            await take_over(b, job)
            await finish(b, job)
            return (
                await stored_tiles(b.store, undisturbed), await stored_tiles(b.store, job),
                await b.store.get_job(job), await b.store.lease_of(job),
            )  # fmt: skip
        finally:
            await alone.close()
            await b.close()

    reference, resumed, row, lease = asyncio.run(main())
    assert len(reference) == 4 and all(t[2] == 7 for t in reference)
    assert resumed == reference  # the same samples, batches, bytes and stops
    assert row.state == JobState.COMPLETED.value and row.samples_merged > 0
    assert lease[0] == "B" and lease[1] == 2 and not lease[2]  # released once stored


def test_every_replica_is_listed_with_its_jobs(db_url, tmp_path):
    async def main():
        a = await Replica(db_url, tmp_path, "A").open()
        b = await Replica(db_url, tmp_path, "B").open()
        try:
            await submit(a)
            await submit(a, "second")
            await a.work(3)
            a.ownership._next_renewal = 0.0  # the next heartbeat now, not in a quarter lease
            await a.ownership.heartbeat()
            app = create_app(b.service, None, auth=Authenticator(b.store, loopback_only=True))
            transport = httpx.ASGITransport(app=app, client=("127.0.0.1", 5000))
            async with httpx.AsyncClient(transport=transport, base_url="http://test") as http:
                listed = (await http.get("/api/v1/replicas")).json()
                jobs = (await http.get("/api/v1/jobs")).json()["jobs"]
            return listed, jobs
        finally:
            await a.close()
            await b.close()

    listed, jobs = asyncio.run(main())
    assert [r["id"] for r in listed] == ["A", "B"]
    by_id = {r["id"]: r for r in listed}
    assert by_id["A"]["jobs_owned"] == 2 and by_id["B"]["jobs_owned"] == 0
    assert all(r["live"] for r in listed)
    assert by_id["A"]["batches_merged"] == 3 and by_id["B"]["batches_merged"] == 0
    assert [j["replica"] for j in jobs] == ["A", "A"]


def test_control_of_a_job_another_replica_owns_is_applied_by_its_owner(db_url, tmp_path):
    async def main():
        a = await Replica(db_url, tmp_path, "A").open()
        b = await Replica(db_url, tmp_path, "B").open()
        try:
            job = await submit(a)
            await a.work(2)
            answers = {}
            for action, call in {
                "pause": lambda: b.service.pause(job, LOCAL_USER),
                "update": lambda: b.service.update(job, LOCAL_USER, priority=5, name="renamed"),
                "resume": lambda: b.service.resume(job, LOCAL_USER),
                "cancel": lambda: b.service.cancel(job, LOCAL_USER),
            }.items():
                asked = asyncio.create_task(call())

                async def answered(asked=asked):
                    await a.service._round()  # A applies what B forwarded
                    return asked.done()

                await until(answered, 10, f"the {action} forwarded to A")
                view = asked.result()
                live = a.service.scheduler.jobs[job]
                answers[action] = (view.state.value, live.state.value, view.name)
            row = await b.store.get_job(job)
            return answers, row, job in b.service.scheduler.jobs
        finally:
            await a.close()
            await b.close()

    answers, row, b_has_it = asyncio.run(main())
    assert answers == {
        "pause": ("paused", "paused", "job"),
        "update": ("paused", "paused", "renamed"),
        "resume": ("running", "running", "renamed"),
        "cancel": ("cancelled", "cancelled", "renamed"),
    }
    assert row.state == "cancelled" and row.settings["priority"] == 5 and not b_has_it


def test_owns_turns_false_before_the_lease_expires_unless_the_replica_is_alone(db_url, tmp_path):
    clock = StoppedClock()
    lease_s = 30.0  # of the database's clock: it does not expire while this test runs

    async def main():
        a = await Replica(db_url, tmp_path, "A", monotonic=clock, lease_s=lease_s).open()
        try:
            job = await submit(a)
            alone = (a.ownership.alone, a.ownership.owns(job))
            clock.now += 10 * lease_s  # no renewal: a server alone keeps its jobs (an outage)
            alone_later = a.ownership.owns(job)
            b = await Replica(db_url, tmp_path, "B", lease_s=lease_s).open()
            a.ownership._next_renewal = -float("inf")  # its next heartbeat now
            await a.ownership.heartbeat()  # renews at clock.now and sees B
            margin = lease_s / 4
            clock.now += lease_s - margin - 0.01
            before = a.ownership.owns(job)
            clock.now += 0.02
            after = a.ownership.owns(job)
            taken = await b.ownership.acquire(job)  # the database still says A's
            lease = await b.store.lease_of(job)
            await b.close()
            return alone, alone_later, a.ownership.alone, before, after, taken, lease
        finally:
            await a.close()

    alone, alone_later, now_alone, before, after, taken, lease = asyncio.run(main())
    assert alone == (True, True) and alone_later
    assert not now_alone and before and not after
    assert taken is False and lease == ("A", 1, True)


def test_a_job_waits_for_and_is_continued_across_replicas(db_url, tmp_path):
    async def main():
        a = await Replica(db_url, tmp_path, "A").open()
        b = await Replica(db_url, tmp_path, "B").open()
        try:
            first = await submit(a, "first")
            second = await submit(b, "second", after=[first])  # B owns it; it waits
            await b.service._round()  # B has looked at its dependency: running, on A
            waiting = (await b.service.get(second, LOCAL_USER)).state.value
            await finish(a, first)

            async def queued():
                await b.service._round()  # B looks at its waiting jobs again
                return (await b.service.get(second, LOCAL_USER)).state != JobState.WAITING

            await until(queued, 10, "the second job released on B")
            # The first job, completed on A (and still in A's memory), continued on B.
            continued = await b.service.continue_(first, LOCAL_USER, {"max_spp": 128})
            seen_by_a = await a.service.get(first, LOCAL_USER)
            lease = await b.store.lease_of(first)
            await finish(b, first)
            row = await b.store.get_job(first)
            return waiting, continued, seen_by_a, lease, row
        finally:
            await a.close()
            await b.close()

    waiting, continued, seen_by_a, lease, row = asyncio.run(main())
    assert waiting == "waiting"
    assert continued.replica == "B" and continued.state == JobState.QUEUED
    assert seen_by_a.replica == "B" and seen_by_a.state == JobState.QUEUED  # not A's old run
    assert lease == ("B", 2, True)
    assert row.mean_spp == 128 and row.settings["max_spp"] == 128


def test_a_server_stopped_cleanly_hands_its_jobs_over_at_once(db_url, tmp_path):
    async def main():
        a = await Replica(db_url, tmp_path, "A", lease_s=30.0).open()
        b = await Replica(db_url, tmp_path, "B", lease_s=30.0).open()
        try:
            job = await submit(a)
            await a.work(7)
            await a.service.stop(timeout_s=5)  # SIGTERM: last checkpoint, then release
            released = await b.store.lease_of(job)
            checkpoint = await stored_tiles(b.store, job)
            await b.service._round()  # long before the 30 s lease would have run out
            resumed = {i: t.acc.batches for i, t in enumerate(b.service.scheduler.jobs[job].tiles)}
            return released, checkpoint, resumed, await b.store.lease_of(job)
        finally:
            await a.close()
            await b.close()

    released, checkpoint, resumed, lease = asyncio.run(main())
    assert released[:2] == ("A", 1) and not released[2]
    assert sum(t[2] for t in checkpoint) == 7  # every merged batch was written
    assert resumed == {t[0]: t[2] for t in checkpoint}
    assert lease == ("B", 2, True)
