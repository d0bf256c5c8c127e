"""Waiting in a test until the state under test shows a condition: polled, with a bound."""

from __future__ import annotations

import asyncio
from collections.abc import Callable


async def until(condition: Callable[[], bool], seconds: float = 5.0, *, step: float = 0.002,
                what: str = "condition") -> None:
    """Poll ``condition`` every ``step`` seconds until it holds; AssertionError after ``seconds``."""
    for _ in range(int(seconds / step)):
        if condition():
            return
        await asyncio.sleep(step)
    raise AssertionError(f"{what} not met within {seconds} s")
