"""A worker's credit (how many tasks it wants leased at once) follows its heartbeats: a worker
that serves several servers (renderfarm-worker connect --server A,B) lowers it on one stream
while the others' tasks fill its threads and raises it again after (workers.proto,
Heartbeat.max_in_flight). Lowered, no task is leased until the worker holds fewer; raised, the
service leases the difference at once; 0 (a worker that does not say) leaves it as it was."""

from __future__ import annotations

import asyncio

from test_scheduler import render
from test_service_collaborators import JOB, FakeClock, FakeOwnership, farm, sent


def test_heartbeats_lower_and_raise_what_a_worker_is_leased(tmp_path):
    service, _ = farm(tmp_path, FakeOwnership({"j"}), FakeClock())

    async def main():
        session = await service.worker_hello("w", "host", 2, 4, "test", token="")
        steps = {"hello": sent(session)}
        held = {lease.task_id: lease for _, lease, _ in steps["hello"]}
        await service.worker_heartbeat(session, 0.0, 0.0, 2, 1)  # the other server's tasks came
        steps["lowered"] = sent(session)
        for task_id in list(held)[:3]:  # three results: one task held, the credit is one
            assert await service.worker_result(session, task_id, render(JOB, held[task_id]))
            del held[task_id]
        steps["after results"] = sent(session)
        await service.worker_heartbeat(session, 0.0, 0.0, 1, 0)  # unchanged
        steps["unchanged"] = sent(session)
        await service.worker_heartbeat(session, 0.0, 0.0, 1, 3)  # they are gone again
        steps["raised"] = sent(session)
        steps["leases"] = len(service.scheduler.workers["w"].leases)
        return steps

    steps = asyncio.run(main())
    assert [m[0] for m in steps["hello"]] == ["assign"] * 4
    assert steps["lowered"] == [] and steps["after results"] == [] and steps["unchanged"] == []
    assert [m[0] for m in steps["raised"]] == ["assign"] * 2
    assert steps["leases"] == 3
