"""Job states, mirrored from renderfarm.v1.JobState (jobs.proto).

queued > running > completed
queued | running > cancelled
queued | running > failed
"""

from __future__ import annotations

from enum import StrEnum


class JobState(StrEnum):
    QUEUED = "queued"
    RUNNING = "running"
    COMPLETED = "completed"
    FAILED = "failed"
    CANCELLED = "cancelled"

    @property
    def finished(self) -> bool:
        return self in (JobState.COMPLETED, JobState.FAILED, JobState.CANCELLED)

    @property
    def proto_name(self) -> str:
        return "JOB_STATE_" + self.name


TRANSITIONS: dict[JobState, frozenset[JobState]] = {
    JobState.QUEUED: frozenset({JobState.RUNNING, JobState.CANCELLED, JobState.FAILED}),
    JobState.RUNNING: frozenset({JobState.COMPLETED, JobState.CANCELLED, JobState.FAILED}),
    JobState.COMPLETED: frozenset(),
    JobState.FAILED: frozenset(),
    JobState.CANCELLED: frozenset(),
}


class StopReason(StrEnum):
    CONVERGED = "converged"  # relative error below noise_threshold after min_spp
    MAX_SPP = "max_spp"  # reached max_spp
    TIME_LIMIT = "time_limit"  # the job's time_limit_s ran out
    CANCELLED = "cancelled"
