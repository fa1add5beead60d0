"""Broadcast (app/broadcast.py): what job watches and stored-state waits rely on."""

import asyncio

import pytest

from renderfarm.app.broadcast import Broadcast


def test_a_notify_wakes_every_waiter_whose_predicate_then_holds():
    async def scenario():
        changes = Broadcast()
        state = {"version": 0}
        woken = []

        async def waiter(name, want):
            await changes.wait_for(lambda: state["version"] >= want, timeout=10)
            woken.append((name, state["version"]))

        tasks = [asyncio.create_task(waiter("a", 1)), asyncio.create_task(waiter("b", 2))]
        await asyncio.sleep(0)  # both are waiting now
        changes.notify()  # nothing changed: both test again and wait on
        await asyncio.sleep(0)
        assert woken == []
        state["version"] = 1
        changes.notify()
        await asyncio.wait_for(tasks[0], 10)
        assert woken == [("a", 1)] and not tasks[1].done()
        state["version"] = 2
        changes.notify()
        await asyncio.wait_for(tasks[1], 10)
        assert woken == [("a", 1), ("b", 2)]
        assert not changes._waiters  # nothing left behind

    asyncio.run(scenario())


def test_a_predicate_that_holds_returns_at_once_and_one_that_never_does_times_out():
    async def scenario():
        changes = Broadcast()
        changes.notify()  # nobody waits: nothing happens
        await changes.wait_for(lambda: True, timeout=0)
        with pytest.raises(TimeoutError):
            await changes.wait_for(lambda: False, timeout=0.01)
        assert not changes._waiters

    asyncio.run(scenario())
