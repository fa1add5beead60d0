"""Operator control of workers in the scheduler: drain, disable, enable, and what a worker id
keeps across reconnects (a fake worker set; no processes)."""

import pytest
from test_scheduler import FakeClock, render

from renderfarm.domain.jobspec import JobSettings, check_tags
from renderfarm.domain.scheduler import Scheduler
from renderfarm.domain.states import JobState
from renderfarm.errors import SettingsError

# 4 tiles of one batch each: every task is a whole tile.
ONE_BATCH = JobSettings(width=16, height=16, tile_size=8, noise_threshold=0, max_spp=1)


def _farm(*workers, credit=2):
    sched = Scheduler(clock=FakeClock())
    sched.add_job("j", ONE_BATCH, "scene")
    for w in workers:
        sched.add_worker(w, credit)
    return sched


def test_draining_worker_finishes_its_tasks_then_takes_none():
    sched = _farm("a", "b")
    held = sched.assign("a")
    assert len(held) == 2
    sched.set_worker_mode("a", "draining")
    assert sched.worker_state("a") == "draining"
    assert sched.take_cancellations("a") == []  # its tasks stay with it
    for lease in held:
        assert sched.complete(lease.task_id, render(ONE_BATCH, lease)) == "merged"
    assert sched.assign("a") == []
    assert sched.worker_state("a") == "drained"
    rest = sched.assign("b")
    assert sorted(x.tile_index for x in rest + held) == [0, 1, 2, 3]
    for lease in rest:
        sched.complete(lease.task_id, render(ONE_BATCH, lease))
    assert sched.jobs["j"].state == JobState.COMPLETED


def test_disabled_worker_hands_its_tasks_back_at_once():
    sched = _farm("a", "b")
    held = sched.assign("a")
    back = sched.set_worker_mode("a", "disabled")
    assert sorted(x.task_id for x in back) == sorted(x.task_id for x in held)
    assert sorted(sched.take_cancellations("a")) == sorted(x.task_id for x in held)
    assert sched.workers["a"].leases == {}
    assert sched.worker_state("a") == "disabled"
    assert sched.assign("a") == []
    # A late result of a handed-back task is not a lease any more: the batch goes to "b".
    taken = sched.assign("b") + sched.assign("b")
    assert {(x.tile_index, x.batch_index) for x in held} <= {
        (x.tile_index, x.batch_index) for x in taken
    }


def test_enable_lets_the_worker_take_tasks_again_and_mode_survives_reconnects():
    sched = _farm("a")
    sched.set_worker_mode("a", "disabled")
    sched.remove_worker("a")
    sched.add_worker("a", 2)  # the same id reconnecting
    assert sched.worker_state("a") == "disabled"
    assert sched.assign("a") == []
    sched.set_worker_mode("a", "active")
    assert len(sched.assign("a")) == 2
    assert sched.worker_state("a") == "active"


def test_failures_are_counted_per_worker_with_the_last_errors():
    sched = Scheduler(clock=FakeClock(), max_task_failures=100)
    sched.add_job("j", ONE_BATCH, "scene")
    sched.add_worker("a", 1)
    for i in range(7):
        (lease,) = sched.assign("a")
        sched.failed(lease.task_id, f"error {i}", retryable=True)
    record = sched.record("a")
    assert record.tasks_failed == 7
    assert list(record.errors) == [f"error {i}" for i in range(2, 7)]
    assert sched.record("b").tasks_failed == 0


def test_a_jobs_tasks_go_only_to_workers_with_all_its_tags():
    sched = Scheduler(clock=FakeClock())
    sched.add_job("j", ONE_BATCH, "scene", require_tags=("big-mem", "gpu-less"))
    sched.add_worker("plain", 4)
    sched.add_worker("half", 4, tags=("big-mem",))
    assert sched.assign("plain") == []
    assert sched.assign("half") == []
    assert sched.jobs["j"].state == JobState.QUEUED  # nobody can take it: it stays queued
    sched.add_worker("both", 4, tags=("big-mem", "gpu-less", "extra"))
    assert len(sched.assign("both")) == 4
    # An untagged job goes anywhere.
    sched.add_job("k", ONE_BATCH, "scene")
    assert {x.job_id for x in sched.assign("plain")} == {"k"}


def test_tags_are_checked_and_name_the_field():
    assert check_tags("require_tags", "gpu-less, big-mem big-mem") == ["big-mem", "gpu-less"]
    for bad in (["Big"], ["-x"], ["a" * 65], [3], "a b!"):
        with pytest.raises(SettingsError) as e:
            check_tags("require_tags", bad)
        assert e.value.field == "require_tags"
