"""Wake-ups for readers waiting on the farm's state (job watches, stored final states)."""

from __future__ import annotations

import asyncio
from collections.abc import Callable


class Broadcast:
    """Every waiter is woken at each notify() and tests its own predicate again.

    asyncio.Condition does the same but takes its lock at every notify; the farm notifies
    after every merged result (thousands a second) and usually nobody is waiting, so here a
    notify with no waiter is one test of an empty set."""

    def __init__(self) -> None:
        self._waiters: set[asyncio.Future] = set()

    def notify(self) -> None:
        waiters, self._waiters = self._waiters, set()
        for future in waiters:
            if not future.done():
                future.set_result(None)

    async def wait_for(self, predicate: Callable[[], bool], timeout: float) -> None:
        """Return once predicate() holds (tested now and after each notify); TimeoutError
        after `timeout` seconds."""
        async with asyncio.timeout(timeout):
            while not predicate():
                future = asyncio.get_running_loop().create_future()
                self._waiters.add(future)
                try:
                    await future
                finally:
                    self._waiters.discard(future)
