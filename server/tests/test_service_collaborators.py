"""FarmService with fakes for its collaborators (app/composition.build_farm_service): a clock the
test moves and an Ownership the test decides. The background round leases tasks and writes
checkpoints of the jobs this server owns only, and its lease expiry and checkpoint interval
follow the clock it was given, not the wall clock (docs/architecture.md, "Composition")."""

from __future__ import annotations

import asyncio

from test_scheduler import render

from renderfarm.app.composition import build_farm_service
from renderfarm.domain.jobspec import JobSettings
from renderfarm.infra.config import Settings

JOB = JobSettings(width=16, height=16, tile_size=8, max_spp=64, noise_threshold=0)
LEASE_S, CHECKPOINT_S = 30.0, 5.0


class FakeClock:
    def __init__(self, now: float = 1_000_000.0):
        self.now = now

    def __call__(self) -> float:
        return self.now

    def advance(self, seconds: float) -> None:
        self.now += seconds


class FakeOwnership:
    """Owns the jobs in `owned`; counts heartbeats."""

    replica_id = "fake"
    shared = False

    def __init__(self, owned: set[str] | None = None):
        self.owned = set(owned or ())
        self.heartbeats = 0

    def owns(self, job_id: str) -> bool:
        return job_id in self.owned

    def epoch(self, job_id: str) -> int:
        return 7

    def fence(self, job_id: str):
        return None

    def take_lost(self) -> list[str]:
        return []

    async def acquire(self, job_id: str) -> bool:
        return job_id in self.owned

    async def release(self, job_id: str) -> None:
        self.owned.discard(job_id)

    async def heartbeat(self) -> None:
        self.heartbeats += 1

    async def leave(self) -> None:
        self.left = True


class NoScenes:
    """Nothing is uploaded here: the scene checker and USD importer are never asked."""

    async def check(self, data, filename, sha256):
        raise AssertionError("no scene is checked in these tests")

    def is_usd(self, data, filename=""):
        return False

    async def convert(self, data, filename):
        raise AssertionError("no scene is converted in these tests")


class RecordingStore:
    def __init__(self):
        self.saved: list[tuple[str, list[int]]] = []  # (job, tile indices) per save_tiles
        self.updated: list[str] = []

    async def save_tiles(self, job_id, rows, fence=None):
        self.saved.append((job_id, [r.tile_index for r in rows]))

    async def update_job(self, job_id, fence=None, **fields):
        self.updated.append(job_id)

    async def add_events(self, events, fences=None):
        pass

    async def worker_connected(self, worker_id, hostname, cores, version):
        pass


def farm(tmp_path, ownership: FakeOwnership, clock: FakeClock):
    store = RecordingStore()
    settings = Settings(data_dir=tmp_path, lease_s=LEASE_S, checkpoint_interval_s=CHECKPOINT_S)
    service = build_farm_service(
        settings, store, clock=clock, ownership=ownership, scene_checker=NoScenes(),
        usd_importer=NoScenes(),
    )  # fmt: skip
    service.scheduler.add_job("j", JOB, "0" * 64)
    return service, store


def sent(session) -> list[tuple]:
    """What the service queued for the worker since the last call."""
    out = []
    while not session.outbox.empty():
        out.append(session.outbox.get_nowait())
    return out


def test_a_job_it_does_not_own_is_neither_leased_nor_checkpointed(tmp_path):
    clock, ownership = FakeClock(), FakeOwnership()
    service, store = farm(tmp_path, ownership, clock)
    job = service.scheduler.jobs["j"]

    async def main():
        session = await service.worker_hello("w", "host", 2, 4, "test", token="")
        for t in job.tiles:  # merged while it was owned
            t.dirty = True
        clock.advance(2 * CHECKPOINT_S)
        await service._round()
        dirty = [t.dirty for t in job.tiles]
        unowned = (sent(session), dict(service.scheduler.leases), list(store.saved), dirty)
        ownership.owned.add("j")  # the same round, once it owns the job (and a checkpoint is due)
        clock.advance(CHECKPOINT_S)
        await service._round()
        return unowned, sent(session), store.saved

    (messages, leases, saved, dirty), owned_messages, owned_saved = asyncio.run(main())
    assert messages == [] and leases == {} and saved == []
    assert all(dirty)  # left for the owner to write
    assert ownership.heartbeats == 2  # one per round
    assert [m[0] for m in owned_messages] == ["assign"] * 4
    assert owned_saved == [("j", [0, 1, 2, 3])] and store.updated == ["j"]


def test_the_clock_given_drives_lease_expiry_and_checkpoints(tmp_path):
    clock = FakeClock()
    service, store = farm(tmp_path, FakeOwnership({"j"}), clock)

    async def main():
        session = await service.worker_hello("w", "host", 2, 4, "test", token="")
        assigned = sent(session)
        _, lease, _ = assigned[0]
        result = render(JOB, lease)
        assert await service.worker_result(session, lease.task_id, result) == "merged"
        steps = {"assigned": assigned, "after merge": sent(session)}
        await service._round()  # the checkpoint interval has not passed on the clock
        steps["before interval"] = list(store.saved)
        clock.advance(CHECKPOINT_S)
        await service._round()
        steps["at interval"] = list(store.saved)
        clock.advance(LEASE_S - CHECKPOINT_S - 1)  # 1 s before the leases' deadline
        await service._round()
        steps["before deadline"] = (service.scheduler.leases_expired, sent(session))
        clock.advance(2)
        await service._round()
        steps["past deadline"] = (service.scheduler.leases_expired, sent(session))
        return steps

    steps = asyncio.run(main())
    assert [m[0] for m in steps["assigned"]] == ["assign"] * 4
    assert [m[0] for m in steps["after merge"]] == ["assign"]  # its slot filled again
    assert steps["before interval"] == []
    assert steps["at interval"] == [("j", [0])]
    assert steps["before deadline"] == (0, [])
    expired, messages = steps["past deadline"]
    assert expired == 4 and [m[0] for m in messages] == ["cancel"] and len(messages[0][1]) == 4


def test_idle_workers_cost_one_try_and_a_tagged_worker_still_gets_its_job(tmp_path):
    """Work runs short: 50 workers without tags want more than the job's tiles allow, so most
    are idle. A change tries the first idle one and skips the others (their tags are a subset
    of its own: they would get nothing either), but still offers a worker tagged `gpu` the job
    that requires that tag."""
    clock, ownership = FakeClock(), FakeOwnership({"j", "gpu-job"})
    service, _ = farm(tmp_path, ownership, clock)
    tries: list[str] = []
    assign = service.scheduler.assign
    service.scheduler.assign = lambda w, owns=None: tries.append(w) or assign(w, owns)

    async def main():
        plain = [await service.worker_hello(f"w{i}", "h", 1, 8, "t", token="") for i in range(50)]
        busy = {w for w, s in service.scheduler.workers.items() if s.leases}
        tries.clear()
        service.scheduler.add_job("gpu-job", JOB, "0" * 64, require_tags=("gpu",))
        gpu = await service.worker_hello("g", "h", 1, 2, "t", token="", tags=["gpu"])
        return plain, busy, list(tries), sent(gpu)

    plain, busy, tried, gpu_messages = asyncio.run(main())
    idle = [f"w{i}" for i in range(50) if f"w{i}" not in busy]
    assert len(idle) > 20  # the job's 4 tiles cannot keep 50 workers of 8 tasks busy
    assert len(service.scheduler.jobs["j"].tiles) == 4
    # The gpu worker's hello: one idle plain worker tried, the rest skipped, the gpu one served.
    assert tried.count("g") == 1 and len([w for w in tried if w in idle]) == 1
    assert [m[0] for m in gpu_messages] == ["assign"] * 2
    assert {m[1].job_id for m in gpu_messages} == {"gpu-job"}


def test_a_job_with_outputs_goes_only_to_workers_that_render_them(tmp_path):
    """Hello.channels: a worker that does not name the rows a job's settings.aovs turn on (an
    older worker names none) is never leased its tasks, and the job says why it waits."""
    clock, ownership = FakeClock(), FakeOwnership({"j", "depth-job"})
    service, _ = farm(tmp_path, ownership, clock)
    depth_job = JobSettings(width=16, height=16, tile_size=8, max_spp=64, noise_threshold=0,
                            aovs="depth")  # fmt: skip

    async def main():
        old = await service.worker_hello("old", "h", 1, 64, "t", token="", renders=[])
        service.scheduler.add_job("depth-job", depth_job, "0" * 64)
        await service._after_change()
        waiting = service._unplaced(service.scheduler.jobs["depth-job"])
        new = await service.worker_hello("new", "h", 1, 64, "t", token="",
                                         renders=["rgb", "luminance", "depth"])  # fmt: skip
        return sent(old), sent(new), waiting

    old_messages, new_messages, waiting = asyncio.run(main())
    assert {m[1].job_id for m in old_messages if m[0] == "assign"} == {"j"}
    depth_tasks = [m[1] for m in new_messages if m[0] == "assign" and m[1].job_id == "depth-job"]
    assert {t.tile_index for t in depth_tasks} == {0, 1, 2, 3}  # every tile of it
    assert waiting == (
        "waiting for a worker that renders depth (settings.aovs; workers older than the server "
        "do not: upgrade them)"
    )
    # Once a worker that renders it is there, nothing is said.
    assert service._unplaced(service.scheduler.jobs["depth-job"]) == ""
