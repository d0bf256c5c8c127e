"""Waiting in a test until the state under test shows a condition: polled, with a bound.

The one place for it: ``until`` in a test on the event loop (its ``step`` is loop time, so under
the virtual clock, ``@pytest.mark.looptime``, it costs no real time), ``until_sync`` in a test that
drives a process or a thread and waits in real time.
"""

from __future__ import annotations

import asyncio
import inspect
import time
from collections.abc import Awaitable, Callable
from typing import TypeVar

T = TypeVar("T")


async def until(condition: Callable[[], object | Awaitable[object]], seconds: float = 5.0, *, step: float = 0.002,
                what: str = "condition") -> None:
    """Poll ``condition`` every ``step`` seconds until it holds; AssertionError after ``seconds``.

    ``condition`` may be a coroutine function (it is awaited each time)."""
    for _ in range(max(1, int(seconds / step))):
        result = condition()
        if inspect.isawaitable(result):
            result = await result
        if result:
            return
        await asyncio.sleep(step)
    raise AssertionError(f"{what} not met within {seconds:g} s")


def until_sync(check: Callable[[], T | None], seconds: float, *, step: float = 0.05, what: str = "condition") -> T:
    """Poll ``check`` every ``step`` seconds of real time until it returns something true; return it.

    AssertionError naming ``what`` after ``seconds``."""
    deadline = time.monotonic() + seconds
    while True:
        result = check()
        if result is not None and result is not False:
            return result
        assert time.monotonic() < deadline, f"{what} not met within {seconds:g} s"
        time.sleep(step)
