"""renderfarm.api.metrics: the Prometheus text exposition, parsed back with prometheus_client's own
parser after the counters and gauges were driven through their public functions (a real
Scheduler on a clock of the test's, the counters the service increments)."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
from prometheus_client.parser import text_string_to_metric_families

from renderfarm.api.metrics import Metrics
from renderfarm.domain.jobspec import JobSettings
from renderfarm.domain.scheduler import Scheduler


class Clock:
    def __init__(self):
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def exposition(metrics: Metrics) -> dict[str, tuple[str, dict]]:
    """family name -> (type, {(sample name, sorted labels): value}) of the rendered text."""
    families = {}
    for family in text_string_to_metric_families(metrics.render().decode()):
        samples = {(s.name, tuple(sorted(s.labels.items()))): s.value for s in family.samples}
        families[family.name] = (family.type, samples)
    return families


def value(families, family: str, sample: str | None = None, **labels) -> float:
    return families[family][1][(sample or family, tuple(sorted(labels.items())))]


@pytest.fixture()
def farm():
    """What the collector reads of a FarmService: a real scheduler (2 s leases, the test's
    clock), two worker sessions with their heartbeat figures, and the store's error count."""
    clock = Clock()
    scheduler = Scheduler(clock=clock, lease_s=2.0)
    sessions = {
        "w1": SimpleNamespace(worker_id="w1", samples_per_s=1500.0, rays_per_s=9000.0),
        "w2": SimpleNamespace(worker_id="w2", samples_per_s=250.5, rays_per_s=1e6),
    }
    return SimpleNamespace(
        scheduler=scheduler, sessions=sessions, store=SimpleNamespace(errors=3), clock=clock,
        ownership=SimpleNamespace(owns=lambda job_id: True), jobs_lost=0, jobs_handed_off=0,
    )  # fmt: skip


def test_an_idle_farm_exposes_every_family_at_zero(farm):
    farm.sessions.clear()
    farm.store.errors = 0
    got = exposition(Metrics(farm))
    # prometheus_client adds the creation time of its own counters and histograms (those
    # of Metrics, not the collector's), which the text parser reads as gauges <name>_created.
    created = {name for name in got if name.endswith("_created")}
    assert created == {
        f"renderfarm_{name}_created"
        for name in ("jobs_submitted", "tasks_completed", "tasks_assigned", "tasks_failed",
                     "samples_merged", "task_duration_seconds", "merge_latency_seconds")
    }  # fmt: skip
    assert {name: kind for name, (kind, _) in got.items() if name not in created} == {
        "renderfarm_jobs": "gauge",
        "renderfarm_queue_depth": "gauge",
        "renderfarm_tasks_leased": "gauge",
        "renderfarm_leases_expired": "counter",
        "renderfarm_workers_connected": "gauge",
        "renderfarm_worker_samples_per_second": "gauge",
        "renderfarm_worker_rays_per_second": "gauge",
        "renderfarm_tile_memory_bytes": "gauge",
        "renderfarm_tile_spill_bytes": "gauge",
        "renderfarm_database_errors": "counter",
        "renderfarm_jobs_owned": "gauge",
        "renderfarm_jobs_lost": "counter",
        "renderfarm_jobs_handed_off": "counter",
        "renderfarm_jobs_submitted": "counter",
        "renderfarm_tasks_completed": "counter",
        "renderfarm_tasks_assigned": "counter",
        "renderfarm_tasks_failed": "counter",
        "renderfarm_samples_merged": "counter",
        "renderfarm_task_duration_seconds": "histogram",
        "renderfarm_merge_latency_seconds": "histogram",
    }
    # One sample per job state, every one 0.
    assert got["renderfarm_jobs"][1] == {
        ("renderfarm_jobs", (("state", s),)): 0.0
        for s in ("queued", "running", "completed", "failed", "cancelled", "paused", "waiting")
    }
    for name in ("queue_depth", "tasks_leased", "workers_connected", "tile_memory_bytes"):
        assert value(got, f"renderfarm_{name}") == 0.0, name
    assert value(got, "renderfarm_leases_expired", "renderfarm_leases_expired_total") == 0.0
    assert value(got, "renderfarm_database_errors", "renderfarm_database_errors_total") == 0.0
    assert value(got, "renderfarm_jobs_owned") == 0.0
    assert value(got, "renderfarm_jobs_lost", "renderfarm_jobs_lost_total") == 0.0
    assert value(got, "renderfarm_jobs_handed_off", "renderfarm_jobs_handed_off_total") == 0.0
    assert got["renderfarm_worker_samples_per_second"][1] == {}  # no worker, no sample
    # Exposed before the first one: both kinds of failure, and merged results.
    failed = got["renderfarm_tasks_failed"][1]
    assert failed[("renderfarm_tasks_failed_total", (("retryable", "true"),))] == 0.0
    assert failed[("renderfarm_tasks_failed_total", (("retryable", "false"),))] == 0.0
    completed = got["renderfarm_tasks_completed"][1]
    assert completed[("renderfarm_tasks_completed_total", (("outcome", "merged"),))] == 0.0


def test_gauges_follow_the_scheduler_and_the_sessions(farm):
    sched = farm.scheduler
    settings = JobSettings(width=32, height=16, tile_size=8, max_spp=64)  # 4 x 2 = 8 tiles
    sched.add_job("a", settings, "0" * 64)
    sched.add_job("b", settings, "1" * 64)
    sched.add_job("c", settings, "2" * 64)
    sched.pause_job("b")
    sched.cancel_job("c")
    sched.add_worker("w1", credit=3)
    leases = sched.assign("w1")
    assert len(leases) == 3 and {lease.job_id for lease in leases} == {"a"}
    metrics = Metrics(farm)
    got = exposition(metrics)
    jobs = {labels[0][1]: v for (_, labels), v in got["renderfarm_jobs"][1].items()}
    assert jobs == {"queued": 0, "running": 1, "completed": 0, "failed": 0, "cancelled": 1,
                    "paused": 1, "waiting": 0}  # fmt: skip
    # Open tiles of unfinished jobs with no task out: all 8 of the paused job, and those of
    # the running one that hold none of the 3 leases.
    assert value(got, "renderfarm_queue_depth") == 8 + 8 - len({ls.tile_index for ls in leases})
    assert value(got, "renderfarm_tasks_leased") == 3
    assert value(got, "renderfarm_workers_connected") == 2
    per_worker = got["renderfarm_worker_samples_per_second"][1]
    assert per_worker == {
        ("renderfarm_worker_samples_per_second", (("worker", "w1"),)): 1500.0,
        ("renderfarm_worker_samples_per_second", (("worker", "w2"),)): 250.5,
    }
    assert value(got, "renderfarm_worker_rays_per_second", worker="w2") == 1e6
    assert value(got, "renderfarm_database_errors", "renderfarm_database_errors_total") == 3

    # The worker goes silent: past its 2 s lease the three leases expire and are counted.
    farm.clock.now += 2.5
    sched.tick()
    farm.store.errors = 5
    got = exposition(metrics)
    assert value(got, "renderfarm_tasks_leased") == 0
    assert value(got, "renderfarm_leases_expired", "renderfarm_leases_expired_total") == 3
    assert value(got, "renderfarm_queue_depth") == 16
    assert value(got, "renderfarm_database_errors", "renderfarm_database_errors_total") == 5


def test_counters_and_histograms_count_what_the_service_records(farm):
    metrics = Metrics(farm)
    metrics.jobs_submitted.inc()
    metrics.jobs_submitted.inc()
    for _ in range(4):
        metrics.tasks_assigned.inc()
    metrics.tasks_completed.labels("merged").inc(3)
    metrics.tasks_completed.labels("duplicate").inc()
    metrics.tasks_failed.labels("true").inc()
    metrics.samples_merged.inc(16 * 16 * 4)
    metrics.samples_merged.inc(8 * 8 * 2)
    for seconds in (0.005, 0.05, 2.0, 500.0):
        metrics.task_seconds.observe(seconds)
    metrics.merge_seconds.observe(2e-4)
    got = exposition(metrics)

    assert value(got, "renderfarm_jobs_submitted", "renderfarm_jobs_submitted_total") == 2
    assert value(got, "renderfarm_tasks_assigned", "renderfarm_tasks_assigned_total") == 4
    completed = "renderfarm_tasks_completed", "renderfarm_tasks_completed_total"
    assert value(got, *completed, outcome="merged") == 3
    assert value(got, *completed, outcome="duplicate") == 1
    failed = "renderfarm_tasks_failed", "renderfarm_tasks_failed_total"
    assert value(got, *failed, retryable="true") == 1
    assert value(got, *failed, retryable="false") == 0
    assert value(got, "renderfarm_samples_merged", "renderfarm_samples_merged_total") == 1152

    # Cumulative buckets: 0.005 <= 0.01, 0.05 <= 0.1, 2.0 <= 3, 500 only in +Inf.
    task = "renderfarm_task_duration_seconds"
    buckets = {
        labels[0][1]: v for (name, labels), v in got[task][1].items() if name == f"{task}_bucket"
    }
    assert buckets == {"0.01": 1, "0.03": 1, "0.1": 2, "0.3": 2, "1.0": 2, "3.0": 3, "10.0": 3,
                       "30.0": 3, "100.0": 3, "+Inf": 4}  # fmt: skip
    assert value(got, task, f"{task}_count") == 4
    assert value(got, task, f"{task}_sum") == pytest.approx(502.055)
    merge = "renderfarm_merge_latency_seconds"
    assert value(got, merge, f"{merge}_bucket", le="0.0001") == 0
    assert value(got, merge, f"{merge}_bucket", le="0.0003") == 1
    assert value(got, merge, f"{merge}_count") == 1
    assert value(got, merge, f"{merge}_sum") == pytest.approx(2e-4)


def test_each_farm_has_a_registry_of_its_own(farm):
    one, two = Metrics(farm), Metrics(farm)
    one.jobs_submitted.inc()
    submitted = "renderfarm_jobs_submitted", "renderfarm_jobs_submitted_total"
    assert value(exposition(one), *submitted) == 1
    assert value(exposition(two), *submitted) == 0
