"""An SLC 500 / PLC-5 on DF1 served as a Modbus unit: the configured map, typed writes.

Holding registers are written with protected typed logical writes (0F AA) of the word (or of
the float); coils with masked writes (0F AB) so that only the written bit changes: no
read-modify-write race with the ladder.  PCCC errors map to Modbus exceptions: an address
problem answers 0x02, another refusal 0x04, no answer 0x0B.

When a write's frame may have reached the controller but its reply never came, the driver's
transaction core (``gateway.protocols.df1.full_duplex.transaction``) reads the target back: if it holds
what was written the write succeeded, otherwise SCADA gets 0x0B.  A write is sent again only where
the read-back proved it was not applied (:meth:`PcccUnit.proves_not_applied`, the one rule for the
SLC 500 and the PLC-5), so it is still applied at most once.
"""

from __future__ import annotations

import math
import struct
from functools import partial
from typing import Any, Final, Protocol, TypeVar, Unpack

from gateway.errors import ControllerRefused, ModbusExceptionReply
from gateway.kinds.df1.config import Processor
from gateway.kinds.df1.full.driver import Df1Driver, check_reply_size
from gateway.kinds.df1.half.receive import ReceiveWindow
from gateway.kinds.df1.plan import Df1BitWrite, Df1Read, Df1WordWrite, MapItem, shared_plan_df1
from gateway.line_driver import LineLease, UnitDriver
from gateway.modbus.mapping import BitPoint, BitWrite, Block, Half, Plan, RegisterPoint, Table, WordWrite
from gateway.protocols.df1.address import FileType, SlcAddress
from gateway.protocols.df1.pccc import (
    PcccError,
    PcccReply,
    ProcessorFamily,
    ProtectedTypedLogicalMaskedWrite,
    ProtectedTypedLogicalRead,
    ProtectedTypedLogicalWrite,
    Sts,
)
from gateway.protocols.df1.plc5_address import Plc5Address
from gateway.unit import Source, Unit, UnitOptions
from gateway.unit_writes import WriteStep

R = TypeVar("R")
B = TypeVar("B")
A = TypeVar("A")

__all__ = ["PROCESSORS", "Df1Unit", "PcccDriver", "PcccUnit", "pccc_exception"]

#: ``processor`` names (every value of the config's ``Processor``) -> families.
PROCESSORS: dict[Processor, ProcessorFamily] = {
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
    address = error.sts == Sts.ADDRESSING_PROBLEM or (error.sts == Sts.EXTENDED and error.ext_sts in _ADDRESS_EXT_STS)
    code = ModbusExceptionReply.ILLEGAL_DATA_ADDRESS if address else ModbusExceptionReply.SERVER_DEVICE_FAILURE
    return ModbusExceptionReply(code, str(error))


class PcccDriver(UnitDriver, Protocol):
    """What a PCCC unit needs of its driver: a full-duplex ``Df1Driver``, or a station's handle on a
    half-duplex line (``gateway.kinds.df1.half.driver.Df1Station``)."""

    last_sts: int

    async def execute(self, request: Any, name: str = "", line: LineLease | None = None) -> PcccReply:
        """The reply to ``request``; ``line``: a write's lease of the unit's write session."""


class PcccUnit(Unit[R, B]):
    """What the SLC 500 and the PLC-5 units share: PCCC commands through a :class:`PcccDriver`,
    PCCC refusals as Modbus exceptions (:func:`pccc_exception`), the last STS as the last fault."""

    driver: PcccDriver

    def __init__(
        self, *, driver: PcccDriver, plan: Plan[R, B], max_write_bytes: int, **common: Unpack[UnitOptions]
    ) -> None:
        super().__init__(driver=driver, plan=plan, **common)
        self.driver = driver
        #: data bytes of one write command
        self.max_write_bytes = max_write_bytes
        #: the station's register table of messages it sent (half duplex, ``receive_words``), set by the builder
        self.receive: ReceiveWindow | None = None

    def read_register_bytes(self, table: Table, address: int, count: int, source: Source = Source.SERVE) -> bytes:
        """As :meth:`Unit.read_register_bytes`; the receive window's part from the table (``receive``)."""
        window = self.receive
        if window is None or not window.overlaps(table, address, count):
            return super().read_register_bytes(table, address, count, source)
        now = self._loop_time()
        return b"".join(
            window.registers(first, n, now) if inside
            else super(PcccUnit, self).read_register_bytes(table, first, n, source)
            for first, n, inside in window.split(address, count)
        )

    async def _execute(self, request: Any, label: str, line: LineLease) -> None:
        """Run a write command on ``line``; a PCCC refusal becomes its Modbus exception."""
        try:
            await self.driver.execute(request, label, line)
        except PcccError as exc:
            raise pccc_exception(exc) from exc

    def refusal_exception(self, error: ControllerRefused) -> ModbusExceptionReply:
        if isinstance(error, PcccError):
            return pccc_exception(error)
        return super().refusal_exception(error)

    @property
    def last_fault_number(self) -> int:
        return self.driver.last_sts

    def proves_not_applied(self, step: WriteStep, shown: bytes) -> bool:
        """Whether ``shown``, what a read-back after the step's write gave (the words the write names:
        ``gateway.protocols.df1.write_verdict.read_back_for``), proves the write was not applied: it shows
        the value the image held before the write (issue 43, item 6b).  The one rule, SLC 500 and PLC-5:

        * full duplex only: the controller runs commands in order, so the read-back ran after the write.
          On half duplex the slave may still hold the write in its queue: never a proof;
        * only points the image has read (it holds a value from before);
        * only in words that only the program and the gateway write (:func:`_program_only`): the N, B and F
          files, and the preset of a timer or counter (``.PRE``) and the length of a control (``.LEN``).
          The processor rewrites a timer's or counter's accumulator and control word, a control's position
          and control word as their instructions run (a TON on a false rung zeroes ``.ACC`` every scan), the
          I/O image at every I/O scan and the status file on its own, so the value from before there proves
          nothing;
        * a float only where every controller keeps it bit for bit (:func:`_kept_exactly`);
        * a word write (typed logical write, PLC-5 word range write, several words in one): the bytes
          read back equal those the image held, and differ from those written;
        * a bit write (masked write, PLC-5 read-modify-write): one command changes all its bits or none,
          so the written bits of the word read back all hold their value from before and one of them
          differs from the value written; the word's other bits are the ladder's and are not compared.
        """
        if not isinstance(self.driver, Df1Driver):
            return False  # half duplex
        stamps = self.cache.stamps
        points: list[RegisterPoint[R] | BitPoint[B]] = [point for point, _ in step.patches]
        points += [bit for bit, _ in step.bit_patches]
        if not points or any(math.isinf(stamps[p.block]) or not _program_only(p.write) for p in points):
            return False
        return self._bits_show_before(step, shown) if step.bit_patches else self._words_show_before(step, shown)

    def _words_show_before(self, step: WriteStep, shown: bytes) -> bool:
        """Whether the words read back are those the image held before the write, not those written."""
        data = self.cache.data
        held: list[tuple[RegisterPoint[R], int]] = []
        for point, _ in step.patches:
            lsb, msb = point.offset + point.codec.lsb, point.codec.msb
            block = data[point.block]
            held.append((point, block[lsb] if msb is None else block[point.offset + msb] << 8 | block[lsb]))
        written = _step_bytes(step)
        if step.patches[0][0].codec.half is not None and not all(
                _kept_exactly(raw) for (raw,) in struct.iter_unpack("<I", written)):
            return False
        before = _step_bytes(WriteStep(step.first, step.last, step.run, held))
        return shown == before and before != written

    def _bits_show_before(self, step: WriteStep, shown: bytes) -> bool:
        """Whether the written bits of the word read back all hold the image's value from before the write,
        and one of them differs from the value written."""
        word, changed = int.from_bytes(shown, "little"), False
        for bit, on in step.bit_patches:
            target = bit.write
            if len(shown) != 2 or not isinstance(target, BitWrite):
                return False
            was = bool(self.cache.data[bit.block][bit.offset] >> bit.bit & 1)
            if bool(word >> target.bit & 1) != was:
                return False
            changed |= was != on
        return changed


class Df1Unit(PcccUnit[Df1WordWrite, Df1BitWrite]):
    """An SLC 500 (or a PLC-5 that accepts SLC commands) with typed logical reads and writes."""

    def __init__(
        self,
        *,
        driver: PcccDriver,
        items: list[MapItem],
        max_read_bytes: int,
        max_write_bytes: int = 0,
        family: ProcessorFamily | None = None,
        **common: Unpack[UnitOptions],
    ) -> None:
        if not max_write_bytes:
            # 3-byte address fields take 2 each off it (``_joins``)
            family = family or (driver.family if isinstance(driver, Df1Driver) else ProcessorFamily.SLC5_04)
            max_write_bytes = family.max_write_bytes
        super().__init__(driver=driver, plan=shared_plan_df1(items, max_read_bytes), max_write_bytes=max_write_bytes,
                         **common)

    async def read_block(self, block: Block) -> bytes:
        read = block.request
        if not isinstance(read, Df1Read):
            raise TypeError(f"{block.label}: not a DF1 read")
        request = ProtectedTypedLogicalRead(read.file_type, read.file_number, read.element, read.sub_element, read.size)
        reply = await self.driver.execute(request, f"read {block.label}")
        return check_reply_size(reply, read.size, f"read {block.label}")

    async def _write(self, request: Any, address: SlcAddress, line: LineLease) -> None:
        await self._execute(request, f"write {address}", line)

    async def _write_register(self, target: Df1WordWrite, value: int, line: LineLease) -> None:
        a = target.address
        data = value.to_bytes(2, "little")
        request = ProtectedTypedLogicalWrite(a.file_type, a.file_number, a.element, a.sub_element, data)
        await self._write(request, a, line)

    async def _write_pair(self, target: Df1WordWrite, raw: int, line: LineLease) -> None:
        a = target.address
        data = struct.pack("<I", raw)
        request = ProtectedTypedLogicalWrite(a.file_type, a.file_number, a.element, a.sub_element, data)
        await self._write(request, a, line)

    def _register_steps(self, checked: list[tuple[int, RegisterPoint[Df1WordWrite], int]]) -> list[WriteStep]:
        """Consecutive words (or floats) of one file in one typed logical write, up to the size limit.

        The protected typed logical write (CMD 0F, FNC AA) writes ``size`` bytes from its address
        (notes §4.36): N7:23-26 go in one command of 8 bytes, F8:0-1 in one of 8.
        """
        groups: list[list[WriteStep]] = []
        for step in super()._register_steps(checked):
            target = _word_target(step, SlcAddress)
            if groups and self._joins(groups[-1], target.address, len(_step_bytes(step))):
                groups[-1].append(step)
            else:
                groups.append([step])
        steps: list[WriteStep] = []
        for group in groups:
            if len(group) == 1:
                steps.append(group[0])
                continue
            first = _word_target(group[0], SlcAddress)
            patches = [patch for step in group for patch in step.patches]
            data = b"".join(_step_bytes(step) for step in group)
            steps.append(WriteStep(group[0].first, group[-1].last, partial(self._write_words, first.address, data),
                                   patches))
        return steps

    def _joins(self, group: list[WriteStep], address: SlcAddress, size: int) -> bool:
        """Whether a write of ``size`` bytes at ``address`` continues ``group`` in one command."""
        last = _word_target(group[-1], SlcAddress)
        first = _word_target(group[0], SlcAddress)
        a, b = last.address, address
        if a.file_type not in _PLAIN_FILES or a.sub_element or b.sub_element or a.bit is not None:
            return False
        if (a.file_type, a.file_number) != (b.file_type, b.file_number) or b.element != a.element + 1:
            return False
        limit = self.max_write_bytes - 2 * _expanded_fields(first.address)
        return sum(len(_step_bytes(step)) for step in group) + size <= limit

    async def _write_words(self, address: SlcAddress, data: bytes, line: LineLease) -> None:
        request = ProtectedTypedLogicalWrite(
            address.file_type, address.file_number, address.element, address.sub_element, data
        )
        await self._write(request, address, line)

    def _bit_steps(self, checked: list[tuple[int, BitPoint[Df1BitWrite], bool]]) -> list[WriteStep]:
        """Consecutive coils of one word in one masked write (CMD 0F, FNC AB: only the bits of the
        mask change, notes §4.36, §7.3), so an FC15 over B3:0/0-15 is one command."""
        steps: list[WriteStep] = []
        word: SlcAddress | None = None
        targets: list[list[Df1BitWrite]] = []
        for address, bit, value in checked:
            target = bit.write
            if target is None:
                raise ModbusExceptionReply(ModbusExceptionReply.ILLEGAL_DATA_ADDRESS, f"coil {address} is not writable")
            if steps and target.address == word and steps[-1].last == address - 1:
                steps[-1].last = address
                steps[-1].bit_patches.append((bit, value))
                targets[-1].append(target)
            else:
                word = target.address
                write = partial(self._write_bit, target, value)
                steps.append(WriteStep(address, address, write, bit_patches=[(bit, value)]))
                targets.append([target])
        for step, bit_targets in zip(steps, targets, strict=True):
            if len(bit_targets) > 1:
                bits = [(t.bit, v) for t, (_, v) in zip(bit_targets, step.bit_patches, strict=True)]
                step.run = partial(self._write_bits, bit_targets[0].address, bits)
        return steps

    async def _write_bits(self, a: SlcAddress, bits: list[tuple[int, bool]], line: LineLease) -> None:
        mask = 0
        value = 0
        for bit, on in bits:
            mask |= 1 << bit
            value |= (1 << bit) if on else 0
        data = value.to_bytes(2, "little")
        request = ProtectedTypedLogicalMaskedWrite(a.file_type, a.file_number, a.element, a.sub_element, mask, data)
        await self._write(request, a, line)

    async def _write_bit(self, target: Df1BitWrite, value: bool, line: LineLease) -> None:
        a = target.address
        mask = 1 << target.bit
        data = (mask if value else 0).to_bytes(2, "little")
        request = ProtectedTypedLogicalMaskedWrite(a.file_type, a.file_number, a.element, a.sub_element, mask, data)
        await self._write(request, a, line)

#: Files whose elements are one word or one float, packed: consecutive elements are consecutive bytes.
_PLAIN_FILES = frozenset({FileType.INTEGER, FileType.BIT, FileType.FLOAT})


#: The data files only the program and the gateway write (integer, bit, float), and the structure files
#: whose word 1 (a timer's or counter's ``.PRE``, a control's ``.LEN``: 1747-6.15 / 1770-6.5.16 p. 13-13) is
#: only the program's and the gateway's: the words where a read-back showing the value from before a write
#: proves it was not applied (``PcccUnit.proves_not_applied``).
_PROGRAM_FILES: Final = frozenset({"N", "B", "F"})
_PRESET_FILES: Final = frozenset({"T", "C", "R"})
_PRESET_WORD: Final = 1


def _program_only(target: object) -> bool:
    """Whether a point's write target (SLC 500 or PLC-5) is a word, or a bit of a word, that only the program and
    the gateway write: one of :data:`_PROGRAM_FILES`, or word :data:`_PRESET_WORD` of :data:`_PRESET_FILES`."""
    address = target.address if isinstance(target, WordWrite | BitWrite) else None
    word: int | None
    if isinstance(address, SlcAddress):
        letter, word = address.file_type.letter, address.sub_element
    elif isinstance(address, Plc5Address):
        letter, word = address.file_type, address.sub_element
    else:
        return False
    return letter in _PROGRAM_FILES or (letter in _PRESET_FILES and word == _PRESET_WORD)


def _kept_exactly(raw: int) -> bool:
    """Whether an IEEE 754 single (its 32 bits) is kept bit for bit by any controller: +0.0 or a normal
    finite number.  A subnormal, -0.0, an infinity or a NaN may be stored as another pattern (flushed to
    zero, made canonical), which could equal the value from before the write and fake a proof."""
    exponent = raw >> 23 & 0xFF
    return raw == 0 or 0 < exponent < 0xFF


def _expanded_fields(address: SlcAddress) -> int:
    return sum(v >= 0xFF for v in (address.file_number, address.element, address.sub_element))


def _step_bytes(step: WriteStep) -> bytes:
    """The bytes a step writes, in address order: words little-endian, floats as 4 bytes."""
    out = bytearray()
    patches = step.patches
    i = 0
    while i < len(patches):
        point, value = patches[i]
        if point.codec.half is not None:
            halves = {p.codec.half: v for p, v in patches[i : i + 2]}
            out += struct.pack("<I", halves[Half.HIGH] << 16 | halves[Half.LOW])
            i += 2
        else:
            out += value.to_bytes(2, "little")
            i += 1
    return bytes(out)


def _word_target(step: WriteStep, address_type: type[A]) -> WordWrite[A]:
    """The word a register write step starts at, at an ``address_type`` address (SLC or PLC-5;
    steps are made from writable points only)."""
    target = step.patches[0][0].write
    if not (isinstance(target, WordWrite) and isinstance(target.address, address_type)):
        raise TypeError(f"register {step.first}: not a write of a word at a {address_type.__name__}")
    return target
