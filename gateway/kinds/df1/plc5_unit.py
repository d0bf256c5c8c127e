"""A PLC-5 on DF1 served as a Modbus unit with the PLC-5's own commands.

``processor = "plc5"`` reads and writes with word range commands and PLC-5 addresses, never with the
SLC typed logical commands (``0F A2`` / ``AA`` / ``AB``), which 1770-6.5.16 lists for the SLC 500 and
MicroLogix only (a PLC-5 may answer them STS 10; ``gateway.kinds.df1.sim.plc5`` variant ``typed_logical``):

* blocks: word range read ``0F 01`` (1770-KF2 p. 5-57; 1785-KE p. 5-6), logical binary address of
  the block's first word (``07 00 07 1E`` for N7:30, 1770-6.5.16 p. 13-12);
* holding registers: word range write ``0F 00`` (KF2 p. 5-57; 1785-KE p. 5-5); consecutive words of
  one file in one command, floats as two words low word first;
* coils: read-modify-write ``0F 26`` of the word holding the bit, ``AND ~set_or_reset OR set``
  (1770-6.5.16 p. 7-20): only the written bits change, in the controller, in one command.

Every write is a write by :func:`gateway.protocols.df1.pccc.is_write`: the exactly-once verdict and the read-back of a
write whose reply was lost (``gateway.protocols.df1.full_duplex.transaction.read_back_for``: a word range read of
the same words) apply as for the SLC unit, and so does the one rule for sending again a write the read-back proved
not applied (:meth:`~gateway.kinds.df1.unit.PcccUnit.proves_not_applied`: full duplex, N / B / F files and
presets only).

Addresses are the forms users type (``N7:0``, ``B3/5``, ``B3:0/5``, ``T4:1.ACC``, ``T4:1/DN``,
``F8:2``, ``I:010`` octal), parsed by :mod:`gateway.protocols.df1.plc5_address`; the read plan is
:func:`plan_plc5` (the cost model and block choice of ``mapping_df1``, on PLC-5 word positions).

The unit is the SLC :class:`~gateway.kinds.df1.unit.Df1Unit` with its commands replaced; it only needs a
driver with ``execute(request, name)`` (``Df1Driver`` or a half-duplex ``Df1Station``).
"""

from __future__ import annotations

import functools
import struct
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import replace
from functools import partial
from typing import Final, TypeAlias, Unpack

from gateway.errors import InvalidRequest, ModbusExceptionReply
from gateway.frozen import frozen
from gateway.kinds.df1.plan import (
    F32_HIGH,
    F32_LOW,
    READ_OVERHEAD_BYTES,
    U16_LE,
    MapItem,
    Plc5BitWrite,
    Plc5WordWrite,
    entry_description,
    optimal_blocks,
)
from gateway.kinds.df1.unit import PcccDriver, PcccUnit, _step_bytes, _word_target
from gateway.line_driver import LineLease
from gateway.modbus.mapping import BitPoint, Block, Codec, Plan, PointLabel, RegisterPoint, Scan, Table
from gateway.protocols.df1.pccc import (
    LogicalBinaryAddress,
    ReadModifyWriteRequest,
    WordRangeRead,
    WordRangeWrite,
)
from gateway.protocols.df1.pccc.limits import PLC5_WORD_RANGE
from gateway.protocols.df1.plc5_address import (
    PLC5_STRUCTURES,
    AddressError,
    Plc5Address,
    encode_logical_binary,
    parse_plc5_address,
    plc5_element_words,
)
from gateway.unit import UnitOptions
from gateway.unit_writes import WriteStep

__all__ = [
    "PLC5_MAX_READ_BYTES",
    "PLC5_MAX_WRITE_BYTES",
    "Plc5BitWrite",
    "Plc5Read",
    "Plc5Unit",
    "Plc5WordWrite",
    "plan_plc5",
    "point_labels_plc5",
    "shared_plan_plc5",
]

#: Word range read: reply data bytes, and write: address + data bytes (``pccc/limits.py``).
PLC5_MAX_READ_BYTES: Final = PLC5_WORD_RANGE.max_read_bytes
PLC5_MAX_WRITE_BYTES: Final = PLC5_WORD_RANGE.max_write_bytes


@frozen
class Plc5Read:
    """A block: ``words`` words from ``address`` (a word of a data file)."""

    address: Plc5Address
    words: int


Plc5Plan: TypeAlias = Plan[Plc5WordWrite, Plc5BitWrite]


# --- word positions ------------------------------------------------------------------------

_Key = tuple[str, int]  # file type letter, file number


def _position(address: Plc5Address) -> int:
    """Word position of ``address`` in its file."""
    return address.element * plc5_element_words(address.file_type) + (address.sub_element or 0)


def _word_address(key: _Key, position: int) -> Plc5Address:
    """The address of word ``position`` of a file: element (and sub-element of a structure)."""
    file_type, file_number = key
    size = plc5_element_words(file_type)
    element, sub = divmod(position, size)
    if file_type in PLC5_STRUCTURES:
        return Plc5Address(file_type, file_number, element, sub)
    return Plc5Address(file_type, file_number, element)  # a float's first word is its element


@frozen
class _Plc5Cell:
    table: Table
    modbus: int
    key: _Key
    position: int  # the word (for bits: the word holding the bit)
    codec: Codec | None
    bit: int | None
    scan: Scan


def _plc5_cells(item: MapItem) -> list[_Plc5Cell]:
    try:
        base = parse_plc5_address(item.address)
    except AddressError as exc:
        raise InvalidRequest(f"map address {item.address!r}: {exc}") from exc
    table, scan = Table(item.table), Scan(item.scan)
    key = (base.file_type, base.file_number)
    first = _position(base)
    structure = base.file_type in PLC5_STRUCTURES
    element_words = plc5_element_words(base.file_type)
    cells: list[_Plc5Cell] = []
    if table in (Table.COIL, Table.DISCRETE):
        first_bit = base.bit or 0
        for k in range(item.count):
            if structure:  # T4:0/DN, count 3: the DN bits of T4:0, T4:1, T4:2
                position, bit = first + element_words * k, first_bit
            else:  # B3/5 or B3:0/5, count 20: bits 5..24 of the file
                position, bit = first + (first_bit + k) // 16, (first_bit + k) % 16
            cells.append(_Plc5Cell(table, item.start + k, key, position, None, bit, scan))
        return cells
    if base.bit is not None:
        raise InvalidRequest(f"map address {item.address!r}: a register maps a word, not a bit")
    if item.type == "float32":
        if base.file_type != "F":
            raise InvalidRequest(f"map address {item.address!r}: float32 needs an F file (F8:0)")
        high, low = (0, 1) if item.word_order == "high-first" else (1, 0)
        for k in range(item.count):
            position = first + 2 * k
            cells.append(_Plc5Cell(table, item.start + 2 * k + high, key, position, F32_HIGH, None, scan))
            cells.append(_Plc5Cell(table, item.start + 2 * k + low, key, position, F32_LOW, None, scan))
        return cells
    if base.file_type == "F":
        raise InvalidRequest(f"map address {item.address!r}: an F file holds floats: type = \"float32\"")
    step = element_words if structure and base.sub_element is not None else 1  # T4:0.ACC, count 3: ACC of T4:0-2
    for k in range(item.count):
        cells.append(_Plc5Cell(table, item.start + k, key, first + step * k, U16_LE, None, scan))
    return cells


def plan_plc5(items: Sequence[MapItem], max_read_bytes: int = PLC5_MAX_READ_BYTES) -> Plc5Plan:
    """The read plan and Modbus points of a PLC-5 map (PLC-5 addresses; word range reads)."""
    cells = [cell for item in items for cell in _plc5_cells(item)]
    max_words = min(max_read_bytes, PLC5_MAX_READ_BYTES) // 2
    fast = {(c.key, c.position) for c in cells if c.scan is Scan.FAST}
    needed: dict[tuple[Scan, _Key], set[tuple[int, int]]] = defaultdict(set)
    for cell in cells:
        scan = Scan.FAST if (cell.key, cell.position) in fast else cell.scan
        needed[scan, cell.key].add((cell.position, 2 if cell.codec in (F32_HIGH, F32_LOW) else 1))
    plan: Plc5Plan = Plan()
    where: dict[tuple[Scan, _Key], list[tuple[int, int, int]]] = {}
    for (scan, key), spans in sorted(needed.items(), key=lambda kv: (kv[0][0].value, kv[0][1])):
        entries = []
        for start, words in optimal_blocks(spans, plc5_element_words(key[0]), max_words, READ_OVERHEAD_BYTES):
            address = _word_address(key, start)
            index = len(plan.blocks)
            plan.blocks.append(Block(Plc5Read(address, words), 2 * words, scan, f"{address} ({words} words)"))
            entries.append((start, words, index))
        where[scan, key] = entries
    for cell in cells:
        scan = Scan.FAST if (cell.key, cell.position) in fast else cell.scan
        block, offset = next(
            (index, 2 * (cell.position - start))
            for start, words, index in where[scan, cell.key]
            if start <= cell.position < start + words
        )
        writable = cell.table.writable
        word = _word_address(cell.key, cell.position)
        if cell.bit is not None:
            target = Plc5BitWrite(word, cell.bit) if writable else None
            plan.bits(cell.table)[cell.modbus] = BitPoint(block, offset + cell.bit // 8, cell.bit % 8, target)
        else:
            assert cell.codec is not None
            register_target = Plc5WordWrite(word) if writable else None
            plan.registers(cell.table)[cell.modbus] = RegisterPoint(block, offset, cell.codec, register_target)
    return plan


def point_labels_plc5(items: Sequence[MapItem]) -> dict[tuple[Table, int], PointLabel]:
    """What each point of :func:`plan_plc5` is: its PLC-5 address (``N7:10``, ``B3:0/5``, ``T4:1.ACC``)."""
    labels: dict[tuple[Table, int], PointLabel] = {}
    for item in items:
        description = entry_description(item)
        for cell in _plc5_cells(item):
            word = _word_address(cell.key, cell.position)
            address = word if cell.bit is None else replace(word, bit=cell.bit)
            labels[cell.table, cell.modbus] = PointLabel(str(address), item.type, description)
    return labels


@functools.lru_cache(maxsize=256)
def _shared(items: tuple[MapItem, ...], max_read_bytes: int) -> Plc5Plan:
    return plan_plc5(items, max_read_bytes)


def shared_plan_plc5(items: Sequence[MapItem], max_read_bytes: int = PLC5_MAX_READ_BYTES) -> Plc5Plan:
    """:func:`plan_plc5`, built once per distinct map (as ``shared_plan_df1``); never changed once built."""
    return _shared(tuple(items), max_read_bytes)


def _logical_address(address: Plc5Address) -> LogicalBinaryAddress:
    return LogicalBinaryAddress.of(*address.levels)


# --- the unit ------------------------------------------------------------------------------


class Plc5Unit(PcccUnit[Plc5WordWrite, Plc5BitWrite]):
    """A PLC-5 map served with word range read / write and read-modify-write (module docstring).

    ``driver`` is a ``Df1Driver`` or a half-duplex ``Df1Station`` (the same ``execute`` API).
    """

    def __init__(
        self,
        *,
        driver: PcccDriver,
        items: list[MapItem],
        max_read_bytes: int = 0,
        max_write_bytes: int = 0,
        **common: Unpack[UnitOptions],
    ) -> None:
        plan = shared_plan_plc5(items, max_read_bytes or PLC5_MAX_READ_BYTES)
        limit = min(max_write_bytes or PLC5_MAX_WRITE_BYTES, PLC5_MAX_WRITE_BYTES)
        super().__init__(driver=driver, plan=plan, max_write_bytes=limit, **common)

    async def read_block(self, block: Block) -> bytes:
        read = block.request
        if not isinstance(read, Plc5Read):
            raise TypeError(f"{block.label}: not a PLC-5 read")
        request = WordRangeRead(_logical_address(read.address), 2 * read.words)
        reply = await self.driver.execute(request, f"read {block.label}")
        data: bytes = reply.data
        if len(data) != 2 * read.words:
            raise InvalidRequest(f"read {block.label}: the PLC-5 answered {len(data)} bytes, not {2 * read.words}")
        return data

    async def _write_words(self, address: Plc5Address, data: bytes, line: LineLease) -> None:
        await self._execute(WordRangeWrite(_logical_address(address), data), f"write {address}", line)

    async def _write_register(self, target: Plc5WordWrite, value: int, line: LineLease) -> None:
        await self._write_words(target.address, value.to_bytes(2, "little"), line)

    async def _write_pair(self, target: Plc5WordWrite, raw: int, line: LineLease) -> None:
        await self._write_words(target.address, struct.pack("<I", raw), line)  # low word first, as read

    def _register_steps(self, checked: list[tuple[int, RegisterPoint[Plc5WordWrite], int]]) -> list[WriteStep]:
        """Consecutive words (or floats) of one N / B / F / I / O / S file in one word range write."""
        steps: list[WriteStep] = []
        group: list[tuple[WriteStep, Plc5WordWrite]] = []
        size = 0

        def flush() -> None:
            if len(group) == 1:
                steps.append(group[0][0])
            elif group:
                data = b"".join(_step_bytes(s) for s, _ in group)
                patches = [patch for s, _ in group for patch in s.patches]
                steps.append(WriteStep(group[0][0].first, group[-1][0].last,
                                       partial(self._write_words, group[0][1].address, data), patches))
            group.clear()

        for step in super()._register_steps(checked):
            target = _word_target(step, Plc5Address)
            nbytes = len(_step_bytes(step))
            if group and self._continues(group[0][1], group[-1][1], target.address, size + nbytes):
                group.append((step, target))
                size += nbytes
                continue
            flush()
            group.append((step, target))
            size = nbytes
        flush()
        return steps

    def _continues(self, first: Plc5WordWrite, last: Plc5WordWrite, address: Plc5Address, size: int) -> bool:
        a = last.address
        if a.file_type in PLC5_STRUCTURES or (a.file_type, a.file_number) != (address.file_type, address.file_number):
            return False
        if address.element != a.element + 1:
            return False
        return size <= self.max_write_bytes - len(encode_logical_binary(first.address))

    def _bit_steps(self, checked: list[tuple[int, BitPoint[Plc5BitWrite], bool]]) -> list[WriteStep]:
        """Consecutive coils of one word in one read-modify-write (only their bits change, p. 7-20)."""
        runs: list[list[tuple[int, BitPoint[Plc5BitWrite], bool]]] = []
        for modbus, point, value in checked:
            target = _bit_target(point)
            if runs and runs[-1][-1][0] == modbus - 1 and _bit_target(runs[-1][-1][1]).address == target.address:
                runs[-1].append((modbus, point, value))
            else:
                runs.append([(modbus, point, value)])
        return [
            WriteStep(
                run[0][0], run[-1][0],
                partial(self._write_bits, _bit_target(run[0][1]).address, [(_bit_target(p).bit, v) for _, p, v in run]),
                bit_patches=[(p, v) for _, p, v in run],
            )
            for run in runs
        ]

    async def _write_bits(self, address: Plc5Address, bits: list[tuple[int, bool]], line: LineLease) -> None:
        forced = set_bits = 0
        for bit, on in bits:
            forced |= 1 << bit
            set_bits |= (1 << bit) if on else 0
        request = ReadModifyWriteRequest(((_logical_address(address), 0xFFFF & ~forced | set_bits, set_bits),))
        label = f"write {address}/" + ",".join(str(b) for b, _ in bits)
        await self._execute(request, label, line)

    async def _write_bit(self, target: Plc5BitWrite, value: bool, line: LineLease) -> None:
        await self._write_bits(target.address, [(target.bit, value)], line)


def _bit_target(point: BitPoint[Plc5BitWrite]) -> Plc5BitWrite:
    target = point.write
    if target is None:
        raise ModbusExceptionReply(ModbusExceptionReply.ILLEGAL_DATA_ADDRESS, "coil is not writable")
    return target
