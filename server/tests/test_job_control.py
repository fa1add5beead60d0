"""Job control in the scheduler: the state machine, pause and resume, and continue, whose
result must equal a job submitted with the final settings from the start, bit for bit."""

from __future__ import annotations

import itertools
import random
import re
from pathlib import Path

import numpy as np
import pytest
from test_scheduler import FakeClock, render, run_farm

from renderfarm.domain.continuation import continue_plan
from renderfarm.domain.jobspec import JobSettings
from renderfarm.domain.scheduler import Scheduler
from renderfarm.domain.states import JobState, check_transition
from renderfarm.errors import TransitionError

Q, R, C, F, X, P, W = (
    JobState.QUEUED,
    JobState.RUNNING,
    JobState.COMPLETED,
    JobState.FAILED,
    JobState.CANCELLED,
    JobState.PAUSED,
    JobState.WAITING,
)
# Written out from the design (docs/operators.md), not read from states.TRANSITIONS.
ALLOWED = {
    (W, Q), (W, X), (W, F),
    (Q, R), (Q, C), (Q, P), (Q, X), (Q, F),
    (R, C), (R, P), (R, X), (R, F),
    (P, Q), (P, R), (P, C), (P, X), (P, F),
    (C, Q),
    (F, Q), (F, W),
}  # fmt: skip


@pytest.mark.parametrize("old,new", list(itertools.product(JobState, repeat=2)))
def test_every_transition_is_allowed_or_refused_as_designed(old, new):
    if (old, new) in ALLOWED:
        check_transition(old, new)
    else:
        with pytest.raises(TransitionError, match=f"a {old.value} job cannot become {new.value}"):
            check_transition(old, new)


def test_the_proto_enum_comment_lists_the_same_transitions():
    """jobs.proto's JobState comment (what a gRPC client reads) says what the table allows."""
    proto = (Path(__file__).resolve().parents[2] / "proto/renderfarm/v1/jobs.proto").read_text()
    stated = set()
    for old, targets in re.findall(r"^//   (\w+) > (.+)$", proto, re.M):
        for new in re.findall(r"\b(\w+)\b", targets.split("(")[0]):
            stated.add((JobState(old), JobState(new)))
    assert stated == ALLOWED


def test_the_scheduler_refuses_a_transition_the_table_refuses():
    sched = Scheduler(clock=FakeClock())
    sched.add_job("j", JobSettings(width=16, height=16, tile_size=8), "scene")
    sched.cancel_job("j")
    with pytest.raises(TransitionError):
        sched.pause_job("j")
    with pytest.raises(TransitionError):
        sched.resume_job("j")
    assert sched.jobs["j"].state == JobState.CANCELLED


def test_pause_returns_the_leases_and_resume_ends_with_the_same_image():
    s = JobSettings(width=32, height=16, tile_size=8, noise_threshold=0.01, min_spp=4, max_spp=64)
    reference = run_farm(s, workers=1, seed=0).jobs["j"]
    clock = FakeClock()
    sched = Scheduler(clock=clock)
    sched.add_job("j", s, "scene")
    sched.add_worker("w", 4)
    leases = sched.assign("w")
    for lease in leases[:2]:
        sched.complete(lease.task_id, render(s, lease))
    in_hand = [lease.task_id for lease in leases[2:]]
    sched.take_events()
    sched.pause_job("j")
    job = sched.jobs["j"]
    assert job.state == JobState.PAUSED
    assert sorted(sched.take_cancellations("w")) == sorted(in_hand)
    assert sched.assign("w") == []  # a paused job leases nothing
    events = sched.take_events()
    assert [(e.kind, e.data) for e in events] == [
        ("job_paused", {"from": "running", "to": "paused"})
    ]
    clock.now += 100.0  # paused time is not elapsed time
    elapsed = sched.progress(job).elapsed_s
    sched.resume_job("j")
    assert job.state == JobState.RUNNING
    assert sched.progress(job).elapsed_s == pytest.approx(elapsed)
    while not job.state.finished:
        for lease in sched.assign("w"):
            sched.complete(lease.task_id, render(s, lease))
    assert job.state == JobState.COMPLETED
    for a, b in zip(reference.tiles, job.tiles, strict=True):
        np.testing.assert_array_equal(a.acc.rgb_sum, b.acc.rgb_sum)
        np.testing.assert_array_equal(a.acc.m2_between, b.acc.m2_between)
        assert a.stop == b.stop


def _continued(old: JobSettings, new: JobSettings, seed: int):
    """Render `old` to completion, continue it to `new` as the service does (continue_plan on
    each tile, then a scheduler restored from the kept tiles), render that to completion."""
    first = run_farm(old, workers=3, seed=seed).jobs["j"]
    assert first.state == JobState.COMPLETED
    checkpoint, plans, bases, again = {}, {}, {}, []
    for t in first.tiles:
        kept = continue_plan(old, new, t.merged, dict(t.basis))
        if kept is None:
            again.append(t.index)
            continue
        checkpoint[t.index] = t.acc
        plans[t.index] = kept[0]
        bases[t.index] = [[b, *kept[1][b]] for b in sorted(kept[1])]
    sched = Scheduler(clock=FakeClock())
    sched.add_job(
        "j", new, "scene", checkpoint=checkpoint, plans=plans, bases=bases,
        state=JobState.QUEUED, transition=(JobState.COMPLETED, "job_continued", {}),
    )  # fmt: skip
    events = sched.take_events()
    assert events[0].kind == "job_continued"
    assert events[0].data == {"from": "completed", "to": "queued"}
    rng = random.Random(seed)
    for w in range(2):
        sched.add_worker(f"w{w}", 2)
    job = sched.jobs["j"]
    outstanding = []
    for _ in range(100000):
        for w in range(2):
            outstanding += sched.assign(f"w{w}")
        cancelled = {t for w in range(2) for t in sched.take_cancellations(f"w{w}")}
        outstanding = [lease for lease in outstanding if lease.task_id not in cancelled]
        if job.state.finished:
            break
        lease = outstanding.pop(rng.randrange(len(outstanding)))
        sched.complete(lease.task_id, render(new, lease))
    return job, again


CASES = [
    # No noise threshold, max_spp on a batch boundary (64 = 1+1+2+4+8+16+32): every tile
    # carries on.
    (dict(noise_threshold=0, max_spp=64), dict(noise_threshold=0, max_spp=200), 0),
    # Not on a boundary: the last batch of every tile was cut at 100; all render again.
    (dict(noise_threshold=0, max_spp=100), dict(noise_threshold=0, max_spp=300), 6),
    # With a noise threshold: a higher max_spp, then a lower threshold, then both.
    (dict(noise_threshold=0.01, max_spp=128), dict(noise_threshold=0.01, max_spp=512), None),
    (dict(noise_threshold=0.02, max_spp=512), dict(noise_threshold=0.005, max_spp=512), None),
    (dict(noise_threshold=0.02, max_spp=96), dict(noise_threshold=0.004, max_spp=1024), None),
    # A threshold turned off (0 is lower): a tile carries on only if no batch was cut.
    (dict(noise_threshold=0.01, max_spp=256), dict(noise_threshold=0, max_spp=256), None),
]


@pytest.mark.parametrize("old,new,rendered_again", CASES)
def test_continue_equals_a_job_submitted_with_the_final_settings(old, new, rendered_again):
    base = dict(width=48, height=32, tile_size=16, min_spp=4)
    old_s, new_s = JobSettings(**base, **old), JobSettings(**base, **new)
    fresh = run_farm(new_s, workers=2, seed=9).jobs["j"]
    job, again = _continued(old_s, new_s, seed=4)
    assert job.state == JobState.COMPLETED
    if rendered_again is not None:
        assert len(again) == rendered_again
    for a, b in zip(fresh.tiles, job.tiles, strict=True):
        assert (a.acc.samples, a.acc.batches) == (b.acc.samples, b.acc.batches)
        for name in ("rgb_sum", "lum_mean", "m2_within", "m2_between"):
            assert getattr(a.acc, name).tobytes() == getattr(b.acc, name).tobytes(), name
        assert a.stop == b.stop
        assert a.error == b.error or (np.isnan(a.error) and np.isnan(b.error))
    assert job.samples_merged == fresh.samples_merged


def test_a_continue_with_a_higher_max_spp_keeps_tiles_with_a_noise_threshold():
    """Not only exact but useful: raising max_spp keeps the tiles whose batches it would not
    have cut otherwise (here every tile that stopped on noise below the old max_spp)."""
    base = dict(width=48, height=32, tile_size=16, min_spp=4, noise_threshold=0.01)
    old, new = JobSettings(**base, max_spp=128), JobSettings(**base, max_spp=512)
    first = run_farm(old, workers=2, seed=3).jobs["j"]
    converged = [t for t in first.tiles if t.stop.reason.value == "converged"]
    assert converged, "the easy half should converge below 128 spp"
    for t in converged:
        assert continue_plan(old, new, t.merged, dict(t.basis)) is not None


def test_a_job_paused_before_it_started_can_be_cancelled_or_resumed_to_queued():
    sched = Scheduler(clock=FakeClock())
    for job_id in ("a", "b"):
        sched.add_job(job_id, JobSettings(width=16, height=16, tile_size=8), "scene")
        sched.pause_job(job_id)
    sched.cancel_job("a")
    assert sched.jobs["a"].state == JobState.CANCELLED
    sched.resume_job("b")
    assert sched.jobs["b"].state == JobState.QUEUED
    sched.add_worker("w", 1)
    assert [lease.job_id for lease in sched.assign("w")] == ["b"]
