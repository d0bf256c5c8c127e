"""An SLC 100/150 served as a Modbus unit: the fixed default map, word and relay-bit writes."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Unpack

from gateway.kinds.contract import Built, line_options, unit_options
from gateway.kinds.slc_ascii.config import SlcAsciiLinkConfig
from gateway.kinds.slc_ascii.driver import ID_RESYNC, SlcAsciiDriver
from gateway.kinds.slc_ascii.plan import U16_BE_MASKED, SlcBitWrite, SlcWordWrite, byte_read, slc_ascii_plan
from gateway.line_driver import LineLease
from gateway.modbus.mapping import Block, RegisterPoint
from gateway.unit import Unit, UnitOptions

__all__ = ["SlcAsciiUnit", "build_slc_ascii"]


class SlcAsciiUnit(Unit[SlcWordWrite, SlcBitWrite]):
    """An SLC 100/150 with the default map."""

    driver: SlcAsciiDriver

    def __init__(self, *, driver: SlcAsciiDriver, **common: Unpack[UnitOptions]) -> None:
        super().__init__(driver=driver, plan=slc_ascii_plan(), **common)

    async def read_block(self, block: Block) -> bytes:
        address, count = byte_read(block)
        return await self.driver.read(address, count)

    def _refused_by_image(self, point: RegisterPoint[SlcWordWrite]) -> str | None:
        # A preset word with its protect bit set is refused by the controller (``;E``; "The
        # Memory Map", 40H-7FH): known from the last read of it, so nothing of the request is sent.
        if point.codec is U16_BE_MASKED and self.cache.data[point.block][point.offset] & 0x80:
            return "protected in the controller (protect bit set)"
        return None

    async def _write_register(self, target: SlcWordWrite, value: int, line: LineLease) -> None:
        await self.driver.write_word(target.address, value, line)

    async def _write_bit(self, target: SlcBitWrite, value: bool, line: LineLease) -> None:
        await self.driver.update_byte(target.address, target.bit, value, line)

    @property
    def kind_counter(self) -> int:
        """Message-ID resyncs that recovered the numbering (status registers 1009-1010)."""
        return self.driver.counters.retries_by_kind.get(ID_RESYNC, 0)

    @property
    def last_fault_number(self) -> int:
        fault = self.driver.last_fault
        return fault.errors[0] if fault is not None and fault.errors else 0


def build_slc_ascii(links: Sequence[SlcAsciiLinkConfig]) -> Built:
    """One unit per link, each with its own driver (one controller per port): the driver is the runner."""
    units: list[SlcAsciiUnit] = []
    for link in links:
        driver = SlcAsciiDriver(
            link.port,
            settings=link.line_settings,
            timeout=link.timeout,
            retries=link.retries,
            # a served write asks again (;Z, copies) while its Modbus answer is still owed
            write_budget=link.write_timeout,
            **line_options(link),
        )
        units.append(SlcAsciiUnit(driver=driver, **unit_options(link)))
    return Built(units, [unit.driver for unit in units])
