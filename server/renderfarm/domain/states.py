"""Job states, mirrored from renderfarm.v1.JobState (jobs.proto), and the one table of the
transitions between them (TRANSITIONS). Every change of a job's state goes through
check_transition, called by Scheduler._transition (which also records it as a job event).

waiting > queued                      the jobs named in `after` have all completed
queued > running > completed
queued > completed                    restored from a checkpoint whose tiles had all stopped
queued | running > paused > queued | running (resume: back to where it was)
paused > completed                    a result that was in flight when it paused was the last
waiting | queued | running | paused > cancelled | failed
failed > queued | waiting             retry (waiting again when `after` is not all completed)
completed > queued                    continue with more samples or a lower noise threshold
"""

from __future__ import annotations

from enum import StrEnum

from ..errors import TransitionError


class JobState(StrEnum):
    QUEUED = "queued"
    RUNNING = "running"
    COMPLETED = "completed"
    FAILED = "failed"
    CANCELLED = "cancelled"
    PAUSED = "paused"
    WAITING = "waiting"

    @property
    def finished(self) -> bool:
        return self in (JobState.COMPLETED, JobState.FAILED, JobState.CANCELLED)

    @property
    def proto_name(self) -> str:
        return "JOB_STATE_" + self.name


TRANSITIONS: dict[JobState, frozenset[JobState]] = {
    JobState.WAITING: frozenset({JobState.QUEUED, JobState.CANCELLED, JobState.FAILED}),
    JobState.QUEUED: frozenset(
        {
            JobState.RUNNING,
            JobState.COMPLETED,
            JobState.PAUSED,
            JobState.CANCELLED,
            JobState.FAILED,
        }
    ),
    JobState.RUNNING: frozenset(
        {JobState.COMPLETED, JobState.PAUSED, JobState.CANCELLED, JobState.FAILED}
    ),
    JobState.PAUSED: frozenset(
        {
            JobState.QUEUED,
            JobState.RUNNING,
            JobState.COMPLETED,
            JobState.CANCELLED,
            JobState.FAILED,
        }
    ),
    JobState.COMPLETED: frozenset({JobState.QUEUED}),
    JobState.FAILED: frozenset({JobState.QUEUED, JobState.WAITING}),
    JobState.CANCELLED: frozenset(),
}


def check_transition(old: JobState, new: JobState) -> None:
    """Raise TransitionError unless a job in state `old` may go to state `new`."""
    if new not in TRANSITIONS[old]:
        raise TransitionError(old, new)


class StopReason(StrEnum):
    CONVERGED = "converged"  # relative error below noise_threshold after min_spp
    MAX_SPP = "max_spp"  # reached max_spp
    TIME_LIMIT = "time_limit"  # the job's time_limit_s ran out
    CANCELLED = "cancelled"
