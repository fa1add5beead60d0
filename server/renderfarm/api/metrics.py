"""Prometheus metrics of the server (GET /metrics). Gauges are read from the farm at scrape time."""

from __future__ import annotations

from collections import Counter as Tally
from typing import TYPE_CHECKING

from prometheus_client import CollectorRegistry, Counter, Histogram, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

from ..domain.states import JobState

if TYPE_CHECKING:
    from ..app.jobs import FarmService


class _FarmCollector:
    def __init__(self, farm: FarmService):
        self.farm = farm

    def collect(self):
        farm = self.farm
        sched = farm.scheduler
        jobs = GaugeMetricFamily(
            "renderfarm_jobs", "Jobs held by the scheduler, by state", labels=["state"]
        )
        by_state = Tally(job.state.value for job in sched.jobs.values())
        for state in JobState:
            jobs.add_metric([state.value], by_state.get(state.value, 0))
        yield jobs
        queued = sum(
            1
            for job in sched.jobs.values()
            if not job.state.finished
            for t in job.tiles
            if not t.stopped and not t.in_flight
        )
        yield GaugeMetricFamily(
            "renderfarm_queue_depth", "Open tiles with no task leased", value=queued
        )
        yield GaugeMetricFamily("renderfarm_tasks_leased", "Tasks leased", value=len(sched.leases))
        yield CounterMetricFamily(
            "renderfarm_leases_expired",
            "Leases that ran out without a heartbeat (their batches re-queued)",
            value=sched.leases_expired,
        )
        yield GaugeMetricFamily(
            "renderfarm_workers_connected", "Connected workers", value=len(farm.sessions)
        )
        samples = GaugeMetricFamily(
            "renderfarm_worker_samples_per_second", "Samples/s per worker", labels=["worker"]
        )
        rays = GaugeMetricFamily(
            "renderfarm_worker_rays_per_second", "Rays/s per worker", labels=["worker"]
        )
        for s in farm.sessions.values():
            samples.add_metric([s.worker_id], s.samples_per_s)
            rays.add_metric([s.worker_id], s.rays_per_s)
        yield samples
        yield rays
        cache = sched.cache
        yield GaugeMetricFamily(
            "renderfarm_tile_memory_bytes",
            "Tile accumulators held in RAM (at most RENDERFARM_TILE_CACHE_MB)",
            value=cache.resident_bytes if cache is not None else 0,
        )
        yield GaugeMetricFamily(
            "renderfarm_tile_spill_bytes",
            "Tile accumulator files in the scratch directory",
            value=cache.spill_bytes if cache is not None else 0,
        )
        owns = farm.ownership.owns
        yield GaugeMetricFamily(
            "renderfarm_jobs_owned",
            "Unfinished jobs this server owns now (several servers over one database)",
            value=sum(not j.state.finished and owns(j.job_id) for j in sched.jobs.values()),
        )
        yield CounterMetricFamily(
            "renderfarm_jobs_lost",
            "Jobs this server dropped because another server holds them now",
            value=farm.jobs_lost,
        )
        yield CounterMetricFamily(
            "renderfarm_jobs_handed_off",
            "Jobs this server checkpointed and released for a server below its share to take",
            value=farm.jobs_handed_off,
        )
        yield CounterMetricFamily(
            "renderfarm_database_errors",
            "Database operations that failed (connection lost, timeout, SQL error)",
            value=farm.store.errors,
        )


class Metrics:
    def __init__(self, farm: FarmService):
        self.registry = CollectorRegistry()
        self.registry.register(_FarmCollector(farm))
        self.jobs_submitted = Counter(
            "renderfarm_jobs_submitted", "Jobs accepted", registry=self.registry
        )
        self.tasks_completed = Counter(
            "renderfarm_tasks_completed",
            "Task results received, by outcome",
            ["outcome"],
            registry=self.registry,
        )
        self.tasks_assigned = Counter(
            "renderfarm_tasks_assigned", "Tasks leased to workers", registry=self.registry
        )
        self.tasks_failed = Counter(
            "renderfarm_tasks_failed",
            "Tasks a worker reported as failed, by whether they may be retried",
            ["retryable"],
            registry=self.registry,
        )
        for retryable in ("true", "false"):  # exposed at 0 before the first failure
            self.tasks_failed.labels(retryable)
        # A result's outcome counter, looked up once per outcome (labels() locks and hashes).
        self._completed = {"merged": self.tasks_completed.labels("merged")}
        self.samples_merged = Counter(
            "renderfarm_samples_merged", "Pixel samples merged", registry=self.registry
        )
        self.task_seconds = Histogram(
            "renderfarm_task_duration_seconds",
            "Worker-side render time of a task",
            buckets=(0.01, 0.03, 0.1, 0.3, 1, 3, 10, 30, 100),
            registry=self.registry,
        )
        self.merge_seconds = Histogram(
            "renderfarm_merge_latency_seconds",
            "Time to merge one task result",
            buckets=(1e-5, 3e-5, 1e-4, 3e-4, 1e-3, 3e-3, 1e-2, 3e-2, 0.1),
            registry=self.registry,
        )

    def task_completed(self, outcome: str) -> None:
        """Count a result by its outcome's kind ("mismatch: ..." counts as "mismatch")."""
        kind = outcome.split(":")[0]
        counter = self._completed.get(kind)
        if counter is None:
            counter = self._completed[kind] = self.tasks_completed.labels(kind)
        counter.inc()

    def render(self) -> bytes:
        return generate_latest(self.registry)
