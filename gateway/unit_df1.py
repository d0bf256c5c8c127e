"""An SLC 500 / PLC-5 on DF1 served as a Modbus unit: the configured map, typed writes.

Holding registers are written with protected typed logical writes (0F AA) of the word (or of
the float); coils with masked writes (0F AB) so that only the written bit changes: no
read-modify-write race with the ladder.  PCCC errors map to Modbus exceptions: an address
problem answers 0x02, another refusal 0x04, no answer 0x0B.

When a write's frame may have reached the controller but its reply never came, the driver's
transaction core (``gateway.protocols.df1.transaction``) reads the target back: if it holds
what was written the write succeeded, otherwise SCADA gets 0x0B.  A write is never sent twice.
"""

from __future__ import annotations

import struct
from typing import Any, cast

from gateway.config import LinkConfig
from gateway.drivers.df1 import Df1Driver, check_reply_size
from gateway.errors import ControllerRefused, ModbusExceptionReply
from gateway.modbus.mapping import Block
from gateway.modbus.mapping_df1 import Df1BitWrite, Df1Read, Df1WordWrite, MapItem, plan_df1
from gateway.protocols.df1.address import SlcAddress
from gateway.protocols.df1.framing import Checksum
from gateway.protocols.df1.pccc import (
    PcccError,
    ProcessorFamily,
    ProtectedTypedLogicalMaskedWrite,
    ProtectedTypedLogicalRead,
    ProtectedTypedLogicalWrite,
)
from gateway.transport import SerialSettings
from gateway.unit import Unit

__all__ = ["PROCESSORS", "Df1Unit", "build_df1_unit", "pccc_exception"]

PROCESSORS = {
    "slc500": ProcessorFamily.SLC500_FIXED,
    "slc5/01": ProcessorFamily.SLC5_01,
    "slc5/02": ProcessorFamily.SLC5_02,
    "slc5/03": ProcessorFamily.SLC5_03,
    "slc5/04": ProcessorFamily.SLC5_04,
    "slc5/05": ProcessorFamily.SLC5_05,
    "plc5": ProcessorFamily.PLC5,
}
#: EXT STS codes (CMD 0F) that say the address is wrong: answered as Modbus 0x02.
_ADDRESS_EXT_STS = frozenset({0x02, 0x03, 0x06, 0x07, 0x0A, 0x13})


def pccc_exception(error: PcccError) -> ModbusExceptionReply:
    """A PCCC refusal as a Modbus exception: address problems 0x02, other refusals 0x04."""
    address = error.sts == 0x50 or (error.sts == 0xF0 and error.ext_sts in _ADDRESS_EXT_STS)
    code = ModbusExceptionReply.ILLEGAL_DATA_ADDRESS if address else ModbusExceptionReply.SERVER_DEVICE_FAILURE
    return ModbusExceptionReply(code, str(error))


class Df1Unit(Unit):
    driver: Df1Driver

    def __init__(self, *, driver: Df1Driver, items: list[MapItem], max_read_bytes: int, **common: Any) -> None:
        super().__init__(driver=driver, plan=plan_df1(items, max_read_bytes), **common)

    async def read_block(self, block: Block) -> bytes:
        read = cast(Df1Read, block.request)
        request = ProtectedTypedLogicalRead(read.file_type, read.file_number, read.element, read.sub_element, read.size)
        reply = await self.driver.execute(request, f"read {block.label}")
        return check_reply_size(reply, read.size, f"read {block.label}")

    async def _write(self, request: Any, address: SlcAddress) -> None:
        try:
            await self.driver.execute(request, f"write {address}")
        except PcccError as exc:
            raise pccc_exception(exc) from exc

    async def _write_register(self, target: object, value: int) -> None:
        assert isinstance(target, Df1WordWrite)
        a = target.address
        data = value.to_bytes(2, "little")
        request = ProtectedTypedLogicalWrite(a.file_type, a.file_number, a.element, a.sub_element, data)
        await self._write(request, a)

    async def _write_float(self, target: object, raw: int) -> None:
        assert isinstance(target, Df1WordWrite)
        a = target.address
        data = struct.pack("<I", raw)
        request = ProtectedTypedLogicalWrite(a.file_type, a.file_number, a.element, a.sub_element, data)
        await self._write(request, a)

    async def _write_bit(self, target: object, value: bool) -> None:
        assert isinstance(target, Df1BitWrite)
        a = target.address
        mask = 1 << target.bit
        data = (mask if value else 0).to_bytes(2, "little")
        request = ProtectedTypedLogicalMaskedWrite(a.file_type, a.file_number, a.element, a.sub_element, mask, data)
        await self._write(request, a)

    def refusal_exception(self, error: ControllerRefused) -> ModbusExceptionReply:
        if isinstance(error, PcccError):
            return pccc_exception(error)
        return super().refusal_exception(error)

    @property
    def last_fault_number(self) -> int:
        return self.driver.last_sts

    @property
    def id_resyncs(self) -> int:
        return 0


def build_df1_unit(link: LinkConfig, common: dict[str, Any]) -> Df1Unit:
    family = PROCESSORS[link.processor]
    max_read = link.max_read_bytes or family.max_read_bytes
    settings = SerialSettings(link.baudrate, link.bytesize, link.parity, link.stopbits)
    driver = Df1Driver(
        link.port,
        name=link.name,
        settings=settings,
        checksum=Checksum.CRC if link.checksum == "crc" else Checksum.BCC,
        station=link.station,
        source=link.source,
        family=family,
        timeout=link.timeout,
        retries=link.retries,
        trace=link.trace,
    )
    items = [
        MapItem(e.table, e.start, e.address, e.count, e.type, e.word_order, e.scan) for e in link.map
    ]
    return Df1Unit(driver=driver, items=items, max_read_bytes=max_read, **common)

