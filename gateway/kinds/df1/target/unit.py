"""A DF1 target link served as a Modbus unit: the data files a PLC's MSG instructions read and write.

The unit is not polled (:attr:`gateway.unit.Unit.POLLED` False): the runner
(:mod:`gateway.kinds.df1.target.driver`) answers the PLC and stores what it wrote; Modbus clients
read the same values from the image and write into the same table, which the PLC's next read
returns.  One block per element, so each element has its own time of last write: an element
nobody wrote since start (and not loaded from ``persist`` or set by ``initial``) answers 0x0B.

**Atomic for readers.**  Everything here runs on the event loop thread, and a write (a PLC's MSG,
a Modbus FC16 or FC15) is applied to the table, committed to ``persist``, and stored in the image
without an ``await`` in between: no reader, on either side, sees part of it.  A write whose commit
fails is taken back out of the table (the image, refreshed only after a commit, holds what was
there), so the table holds what ``persist`` holds.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Hashable, Iterable, Sequence
from typing import Unpack

from gateway.errors import GatewayError, ModbusExceptionReply
from gateway.frozen import frozen
from gateway.kinds.df1.plan import F32_HIGH, F32_LOW, U16_LE
from gateway.kinds.df1.target.config import TargetFile
from gateway.kinds.df1.target.driver import TargetRunner
from gateway.kinds.df1.target.store import StoredElement, TargetStore
from gateway.line_driver import LineLease
from gateway.modbus.mapping import BitPoint, Block, Plan, PointLabel, RegisterPoint, Scan, Table
from gateway.protocols.df1.pccc.target_table import DataTable, ElementRef, TableFile
from gateway.schedule import NEVER
from gateway.unit import Unit, UnitOptions
from gateway.unit_writes import WriteStep

__all__ = ["TargetBit", "TargetElement", "TargetUnit", "load_table", "target_plan", "target_point_labels"]

log = logging.getLogger("gateway.df1.target")
audit = logging.getLogger("gateway.audit")


@frozen
class TargetElement:
    """The write target of a register: one element of one file (both registers of an F or L)."""

    file: int
    element: int

    @property
    def address(self) -> Hashable:
        return (self.file, self.element)


@frozen
class TargetBit:
    """The write target of a coil: bit ``bit`` of element ``element`` of B file ``file``."""

    file: int
    element: int
    bit: int

    @property
    def address(self) -> Hashable:
        return (self.file, self.element)


def target_plan(files: Sequence[TargetFile]) -> Plan[TargetElement, TargetBit]:
    """One block per element (its little-endian bytes), and the points of each file's Modbus range."""
    plan: Plan[TargetElement, TargetBit] = Plan()
    for entry in files:
        writable = entry.table in ("holding", "coil")
        for element in range(entry.elements):
            index = len(plan.blocks)
            plan.blocks.append(Block(ElementRef(entry.file, element), entry.kind.element_bytes, Scan.FAST,
                                     f"{entry.name}:{element}"))
            if entry.is_bits:
                bits = plan.coils if entry.table == "coil" else plan.discrete
                for k in range(16):
                    target = TargetBit(entry.file, element, k) if writable else None
                    bits[entry.start + 16 * element + k] = BitPoint(index, k // 8, k % 8, target)
                continue
            registers = plan.holding if entry.table == "holding" else plan.input
            target_word = TargetElement(entry.file, element) if writable else None
            address = entry.start + entry.words * element
            if entry.words == 1:
                registers[address] = RegisterPoint(index, 0, U16_LE, target_word)
                continue
            low_first = entry.word_order == "low-first"
            first, second = (F32_LOW, F32_HIGH) if low_first else (F32_HIGH, F32_LOW)
            registers[address] = RegisterPoint(index, 0, first, target_word, word_order_low_first=low_first)
            registers[address + 1] = RegisterPoint(index, 0, second, target_word, word_order_low_first=low_first)
    return plan


def target_point_labels(files: Sequence[TargetFile]) -> dict[tuple[Table, int], PointLabel]:
    """Each point's file address and type (``export-tags``)."""
    types = {"N": "int16", "B": "uint16", "F": "float32", "L": "int32"}
    labels: dict[tuple[Table, int], PointLabel] = {}
    for entry in files:
        table = Table(entry.table)
        writers = "written by the PLC's MSG or a Modbus client" if table.writable else "written by the PLC's MSG"
        for element in range(entry.elements):
            if entry.is_bits:
                for k in range(16):
                    labels[(table, entry.start + 16 * element + k)] = PointLabel(f"{entry.name}:{element}/{k}", "bool",
                                                                                 writers)
                continue
            for word in range(entry.words):
                labels[(table, entry.start + entry.words * element + word)] = PointLabel(
                    f"{entry.name}:{element}", types[entry.type], writers)
    return labels


def load_table(files: Sequence[TargetFile], store: TargetStore | None, now: float) -> DataTable:
    """The data table at start: ``initial`` values, then what ``persist`` holds (with its write times)."""
    table = DataTable()
    for entry in files:
        table_file = table.add(entry.kind, entry.file, entry.elements)
        if entry.initial is not None:
            for element in range(entry.elements):
                table_file.set_value(element, entry.initial, now)
    if store is not None:
        wall = time.time()
        for row in store.load():
            table_file_or_none = table.get(row.file)
            size = table_file_or_none.kind.element_bytes if table_file_or_none is not None else 0
            if table_file_or_none is None or row.element >= table_file_or_none.count or len(row.value) != size:
                log.warning("persist %s: %s:%d is not in the configured files any more: left out", store.path,
                            row.file, row.element)
                continue
            table_file_or_none.write_bytes(row.element * size, row.value, now - max(0.0, wall - row.written_at))
    return table


def stored_elements(table: DataTable, refs: Iterable[ElementRef]) -> list[StoredElement]:
    """Rows for ``persist``: each element's bytes, stamped with the wall-clock time now."""
    wall = time.time()
    rows = []
    for ref in refs:
        table_file = table[ref.file]
        size = table_file.kind.element_bytes
        data, _ = table_file.read_bytes(ref.element * size, size)
        rows.append(StoredElement(ref.file, ref.element, data, wall))
    return rows


class TargetUnit(Unit[TargetElement, TargetBit]):
    """A target link's data files as a Modbus unit (module doc)."""

    POLLED = False
    driver: TargetRunner

    def __init__(self, *, driver: TargetRunner, files: Sequence[TargetFile], store: TargetStore | None,
                 **common: Unpack[UnitOptions]) -> None:
        super().__init__(driver=driver, plan=target_plan(files), **common)
        self.files = tuple(files)
        table = driver.target.table
        self.table = table
        self.store_file = store
        self._blocks = {block.request: index for index, block in enumerate(self.plan.blocks)}
        #: persist commits that failed (the write was not acknowledged)
        self.persist_failures = 0
        driver.on_written = self._plc_wrote
        driver.on_heard = self.heard
        self.refresh_all()

    def _plc_wrote(self, refs: Sequence[ElementRef]) -> None:
        """The PLC's command wrote ``refs`` into the table: commit them, or take them back (GatewayError)."""
        try:
            self.persist(refs)
        except GatewayError:
            self._take_back(refs)
            raise
        self.refresh(refs)

    # --- the image, from the table -----------------------------------------------------------

    def refresh(self, refs: Iterable[ElementRef]) -> None:
        """Put the table's elements ``refs`` in the image with their write times (a PLC write, a load)."""
        for ref in refs:
            table_file = self.table[ref.file]
            stamp = table_file.written_at(ref.element)
            index = self._blocks.get(ref)
            if stamp is None or index is None:
                continue
            size = table_file.kind.element_bytes
            data, _ = table_file.read_bytes(ref.element * size, size)
            self.cache.store(index, data, stamp)

    def _take_back(self, refs: Iterable[ElementRef]) -> None:
        """Put the table's elements ``refs`` back as the image holds them: their last committed values
        (the image is refreshed only after a commit), never-written where the image has none."""
        for ref in refs:
            table_file = self.table[ref.file]
            index = self._blocks[ref]
            stamp = self.cache.stamps[index]
            size = table_file.kind.element_bytes
            if stamp == NEVER:
                table_file.forget(ref.element)
            else:
                table_file.write_bytes(ref.element * size, bytes(self.cache.data[index]), stamp)

    def refresh_all(self) -> None:
        self.refresh(ElementRef(f.number, e) for f in self.table for e in range(f.count))

    def persist(self, refs: Sequence[ElementRef]) -> None:
        """Commit ``refs`` to ``persist`` (if set); raises GatewayError when the commit failed."""
        if self.store_file is None or not refs:
            return
        try:
            self.store_file.save(stored_elements(self.table, refs))
        except Exception as exc:
            self.persist_failures += 1
            raise GatewayError(f"link {self.name}: persist {self.store_file.path}: {exc}: the write is not "
                               "acknowledged; check the disk") from exc

    # --- Modbus writes: into the table, whole ---------------------------------------------------

    def _footprint(self, target: TargetElement | TargetBit) -> Hashable:
        return target.address

    async def _queue_write(self, table: Table, steps: list[WriteStep], footprint: frozenset[Hashable]) -> None:
        """Apply the whole request at once (module doc): no line to wait for, no queue (the steps'
        lease holds nothing)."""
        self.write_requests += 1
        started = self._loop_time()
        line = LineLease()
        try:
            for step in steps:
                await step.run(line)
        except ModbusExceptionReply:
            self.write_failures += 1
            raise
        finally:
            self.write_latency.observe(self._loop_time() - started)

    def _register_steps(self, checked: list[tuple[int, RegisterPoint[TargetElement], int]]) -> list[WriteStep]:
        values: dict[TargetElement, dict[int, int]] = {}
        for _, point, value in checked:
            target = point.write
            assert target is not None  # checked writable
            half = 0 if point.codec.half is None else (1 if point.codec is F32_HIGH else 0)
            values.setdefault(target, {})[half] = value
        first, last = checked[0][0], checked[-1][0]

        async def run(line: LineLease) -> None:
            self._apply_words(values)

        return [WriteStep(first, last, run)]

    def _bit_steps(self, checked: list[tuple[int, BitPoint[TargetBit], bool]]) -> list[WriteStep]:
        changes: dict[tuple[int, int], tuple[int, int]] = {}
        for _, point, on in checked:
            target = point.write
            assert target is not None
            mask, value = changes.get((target.file, target.element), (0, 0))
            changes[(target.file, target.element)] = (mask | 1 << target.bit, value | (on << target.bit))
        first, last = checked[0][0], checked[-1][0]

        async def run(line: LineLease) -> None:
            self._apply_bits(changes)

        return [WriteStep(first, last, run)]

    def _apply_words(self, values: dict[TargetElement, dict[int, int]]) -> None:
        now = self._loop_time()
        staged: list[tuple[TableFile, int, bytes]] = []
        for target, words in values.items():
            table_file = self.table[target.file]
            size = table_file.kind.element_bytes
            if size == 2:
                data = words[0].to_bytes(2, "little")
            else:
                data = (words[1] << 16 | words[0]).to_bytes(4, "little")  # low-order word first on the wire
            staged.append((table_file, target.element * size, data))
        self._commit(staged, now)

    def _apply_bits(self, changes: dict[tuple[int, int], tuple[int, int]]) -> None:
        now = self._loop_time()
        staged: list[tuple[TableFile, int, bytes]] = []
        for (file, element), (mask, value) in changes.items():
            table_file = self.table[file]
            current, _ = table_file.read_bytes(element * 2, 2)
            word = (int.from_bytes(current, "little") & ~mask) | value
            staged.append((table_file, element * 2, (word & 0xFFFF).to_bytes(2, "little")))
        self._commit(staged, now)

    def _commit(self, staged: list[tuple[TableFile, int, bytes]], now: float) -> None:
        """Write the staged elements to the table, persist them, put them in the image; on a failed
        commit the table is put back and the Modbus client gets 0x04 (nothing acknowledged)."""
        refs = []
        for table_file, offset, data in staged:
            table_file.write_bytes(offset, data, now)
            refs.append(ElementRef(table_file.number, offset // table_file.kind.element_bytes))
        try:
            self.persist(refs)
        except GatewayError as exc:
            self._take_back(refs)
            log.error("%s", exc)
            raise ModbusExceptionReply(ModbusExceptionReply.SERVER_DEVICE_FAILURE, str(exc)) from exc
        self.refresh(refs)
        audit.info("unit %d: Modbus client wrote %s", self.unit_id,
                   ", ".join(f"{self.table[r.file].name}:{r.element}" for r in refs))

    # --- the hooks of a polled unit, which this one is not --------------------------------------

    async def read_block(self, block: Block) -> bytes:
        raise GatewayError(f"link {self.name}: a target link is not polled")

    async def _write_register(self, target: TargetElement, value: int, line: LineLease) -> None:
        raise GatewayError("target writes go through _register_steps")

    async def _write_bit(self, target: TargetBit, value: bool, line: LineLease) -> None:
        raise GatewayError("target writes go through _bit_steps")

    @property
    def last_fault_number(self) -> int:
        """The last STS the gateway sent the PLC other than 0 (0: none refused yet)."""
        return self.driver.last_sts

    @property
    def kind_counter(self) -> int:
        """Duplicate messages received (status registers 1009-1010): ACKed and answered, not run again."""
        return self.driver.duplicates

