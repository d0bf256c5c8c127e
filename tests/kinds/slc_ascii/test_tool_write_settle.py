"""``slc-gateway write`` settles a write whose outcome is unknown by reading the item back."""

from __future__ import annotations

from typing import Any

import pytest

from gateway.errors import WriteOutcomeUnknown
from gateway.kinds.slc_ascii.tool import WRITE_TRIES, _write_and_settle
from gateway.protocols.slc_ascii.memory_map import parse_item


class FakeDriver:
    """Writes answer 'outcome unknown' ``unknown`` times; ``applied`` says whether each one ran."""

    def __init__(self, applied: list[bool]) -> None:
        self.applied = applied
        self.value = 100
        self.writes = 0

    async def execute(self, command: Any) -> None:
        ran = self.applied[self.writes] if self.writes < len(self.applied) else True
        unknown = self.writes < len(self.applied)
        self.writes += 1
        if ran:
            self.value = VALUE  # every write of these tests writes VALUE
        if unknown:
            raise WriteOutcomeUnknown("outcome unknown")

    async def read(self, address: int, count: int) -> bytes:
        return self.value.to_bytes(count, "big")


ITEM = parse_item("905.PRE")
VALUE = 1234


async def test_an_unknown_write_that_ran_is_done_after_the_read_back() -> None:
    driver = FakeDriver([True])
    await _write_and_settle(driver, "905.PRE", ITEM, VALUE)  # type: ignore[arg-type]
    assert driver.writes == 1  # not sent again: the read-back showed it applied


async def test_an_unknown_write_that_did_not_run_is_sent_again() -> None:
    driver = FakeDriver([False])
    await _write_and_settle(driver, "905.PRE", ITEM, VALUE)  # type: ignore[arg-type]
    assert driver.writes == 2 and driver.value == VALUE


async def test_it_gives_up_after_its_tries() -> None:
    driver = FakeDriver([False] * WRITE_TRIES)
    with pytest.raises(WriteOutcomeUnknown):
        await _write_and_settle(driver, "905.PRE", ITEM, VALUE)  # type: ignore[arg-type]
    assert driver.writes == WRITE_TRIES
