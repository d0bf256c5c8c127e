"""DF1 target mode with ``persist`` when saving fails: a full disk, a read-only database, an I/O
error in the middle of a many-row save (a multi-packet PLC-5 write), a COMMIT that fails.

The promises (``gateway/kinds/df1/target/store.py``, ``target_driver.py``, README "DF1 target
mode"): no write is acknowledged that is not on disk.

* the PLC's MSG gets STS 40 hex, "Host could not complete function due to hardware fault"
  (1770-6.5.16 p. 8-3, Remote STS Error Codes; ../shared/docs/df1-full-duplex-and-pccc-packets.md,
  "Remote STS Error Codes": 40);
* a Modbus client gets exception 04 (server device failure);
* the table (what the PLC's next read and a Modbus read get) holds exactly what is on disk, after
  the failure and after a restart, and the next write once the fault is gone is saved.

The gateway runs whole: the PLC is this test on a TCP port the link connects to
(``socket://``), the Modbus client is pymodbus. The faults are SQLite's own on the gateway's
connection: ``max_page_count`` (SQLITE_FULL, "database or disk is full"), ``query_only``
(SQLITE_READONLY, what a read-only file or directory gives), a temporary trigger that aborts the
save at one row (a failed write in the middle of the rows), an authorizer that refuses COMMIT
(the transaction is left open, as a COMMIT that fails with SQLITE_BUSY or an I/O error may).
"""

from __future__ import annotations

import asyncio
import sqlite3
from collections.abc import AsyncIterator, Callable, Iterator
from contextlib import AbstractContextManager, asynccontextmanager, contextmanager
from pathlib import Path

import pytest
from pymodbus.client import AsyncModbusTcpClient

from gateway.app import Gateway
from gateway.config import parse_config
from gateway.kinds.df1.target.unit import TargetUnit
from gateway.protocols.df1.address import FileType
from gateway.protocols.df1.pccc import (
    LogicalBinaryAddress,
    ProtectedTypedLogicalWrite,
    WordRangeWrite,
)

from .plc_line import STATION, Plc

#: STS of a command the host could not complete due to a hardware fault (1770-6.5.16 p. 8-3)
HOST_HARDWARE_FAULT = 0x40
#: Modbus exception code 04: server device failure (Modbus Application Protocol V1.1b3, 7)
SERVER_DEVICE_FAILURE = 0x04
#: Modbus exception code 0B: gateway target device failed to respond (never-written elements)
NO_RESPONSE = 0x0B
UNIT = 5
ELEMENTS = 800
#: what the failing SLC write writes to N7:1-100
NEW = [-k for k in range(1, 101)]


def config(port: int, db: Path) -> str:
    return f"""
[modbus]
listen = "127.0.0.1:0"

[[link]]
name = "plc"
protocol = "df1"
role = "target"
port = "socket://127.0.0.1:{port}"
station = {STATION}
checksum = "crc"
unit = {UNIT}
persist = "{db}"

[[link.file]]
file = 7
type = "N"
elements = {ELEMENTS}
"""


def slc_write(element: int, values: list[int]) -> ProtectedTypedLogicalWrite:
    data = b"".join(v.to_bytes(2, "little", signed=True) for v in values)
    return ProtectedTypedLogicalWrite(FileType.INTEGER, 7, element, 0, data)


def plc5_packets(element: int, values: list[int], per_packet: int = 100) -> list[WordRangeWrite]:
    """A PLC-5 word range write of ``values`` in packets of ``per_packet`` words (one transaction)."""
    address = LogicalBinaryAddress.for_element(7, element)
    return [
        WordRangeWrite(address, b"".join(v.to_bytes(2, "little", signed=True) for v in values[k : k + per_packet]),
                       packet_offset=k, total=len(values))
        for k in range(0, len(values), per_packet)
    ]


def on_disk(db: Path) -> dict[int, int]:
    """N7's elements in the file, read by a connection of their own (committed rows only)."""
    with sqlite3.connect(db) as reader:
        rows = reader.execute("SELECT element, value FROM element WHERE file = 7").fetchall()
    return {int(element): int.from_bytes(value, "little", signed=True) for element, value in rows}


def in_table(unit: TargetUnit) -> dict[int, int]:
    """N7's written elements in the gateway's table (what the PLC's reads and Modbus reads are served)."""
    n7 = unit.table[7]
    values = {element: n7.value(element) for element in range(n7.count)}
    return {element: int(value) for element, value in values.items() if value is not None}


# --- the faults, on the gateway's own SQLite connection ---------------------------------------


@contextmanager
def disk_full(db: sqlite3.Connection) -> Iterator[None]:
    """No page may be added to the file (SQLITE_FULL, "database or disk is full")."""
    (pages,) = db.execute("PRAGMA page_count").fetchone()
    db.execute(f"PRAGMA max_page_count = {pages}")
    try:
        yield
    finally:
        db.execute("PRAGMA max_page_count = 1073741823")


@contextmanager
def read_only(db: sqlite3.Connection) -> Iterator[None]:
    """SQLITE_READONLY, "attempt to write a readonly database"."""
    db.execute("PRAGMA query_only = ON")
    try:
        yield
    finally:
        db.execute("PRAGMA query_only = OFF")


@contextmanager
def io_error_mid_save(db: sqlite3.Connection) -> Iterator[None]:
    """A save fails at its first row of an element numbered 7k + 3: every failing write of these
    tests has rows before that one, which are in the transaction when it fails."""
    db.execute("CREATE TEMP TRIGGER io_error BEFORE INSERT ON main.element WHEN NEW.element % 7 = 3 "
               "BEGIN SELECT RAISE(ABORT, 'disk I/O error'); END")
    try:
        yield
    finally:
        db.execute("DROP TRIGGER temp.io_error")


@contextmanager
def commit_fails(db: sqlite3.Connection) -> Iterator[None]:
    """COMMIT is refused: the transaction with the rows is left open."""

    def authorize(action: int, arg1: str | None, *_: object) -> int:
        return sqlite3.SQLITE_DENY if action == sqlite3.SQLITE_TRANSACTION and arg1 == "COMMIT" else sqlite3.SQLITE_OK

    db.set_authorizer(authorize)
    try:
        yield
    finally:
        db.set_authorizer(None)


#: what SQLite says for each fault: the logged error names it (and says to check the disk)
MESSAGES = {
    "disk_full": "database or disk is full",
    "read_only": "attempt to write a readonly database",
    "io_error_mid_save": "disk I/O error",
    "commit_fails": "not authorized",
}
FAULTS: dict[str, Callable[[sqlite3.Connection], AbstractContextManager[None]]] = {
    "disk_full": disk_full,
    "read_only": read_only,
    "io_error_mid_save": io_error_mid_save,
    "commit_fails": commit_fails,
}


def small_pages(db: Path) -> None:
    """Create the file with 512-byte pages (the store adds its table): a write of 60 new rows or
    more needs pages the file does not have, so ``disk_full`` refuses it (a write that only
    replaces rows may fit the pages there are: every failing write here adds at least 60)."""
    with sqlite3.connect(db) as conn:
        conn.execute("PRAGMA page_size = 512")
        conn.execute("PRAGMA journal_mode = WAL")


@asynccontextmanager
async def gateway(db: Path) -> AsyncIterator[tuple[Gateway, TargetUnit, Plc, AsyncModbusTcpClient]]:
    plc = Plc()
    server = await asyncio.start_server(plc.connected, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    try:
        async with Gateway(parse_config(config(port, db))) as gw:
            (unit,) = gw.units
            assert isinstance(unit, TargetUnit)
            modbus = AsyncModbusTcpClient("127.0.0.1", port=gw.port)
            await modbus.connect()
            try:
                yield gw, unit, plc, modbus
            finally:
                modbus.close()
    finally:
        server.close()
        await server.wait_closed()


async def served(plc: Plc, modbus: AsyncModbusTcpClient, first: int, count: int) -> tuple[list[int], object]:
    """N7:first.. as the PLC reads them and as a Modbus client reads them (values, or its exception code)."""
    from_plc = await plc.read_n7(first, count)
    answer = await modbus.read_holding_registers(first, count=count, device_id=UNIT)
    from_modbus: object = answer.exception_code if answer.isError() else [r - 0x10000 * (r >> 15)
                                                                          for r in answer.registers]
    return from_plc, from_modbus


def assert_logged(caplog: pytest.LogCaptureFixture, fault: str) -> None:
    errors = [r.getMessage() for r in caplog.records if r.levelname == "ERROR"]
    assert len(errors) == 2 and all(MESSAGES[fault] in e and "check the disk" in e for e in errors), errors


@pytest.mark.parametrize("fault", list(FAULTS))
async def test_a_plc_write_that_cannot_be_saved_is_refused_and_not_kept(
    tmp_path: Path, fault: str, caplog: pytest.LogCaptureFixture
) -> None:
    db = tmp_path / "plc.db"
    small_pages(db)
    expected: dict[int, int] = {}
    async with gateway(db) as (_gw, unit, plc, modbus):
        assert await plc.sts(slc_write(0, [11, 12, 13])) == 0
        for packet in plc5_packets(100, list(range(1000, 1200))):
            assert await plc.sts(packet) == 0
        expected |= {0: 11, 1: 12, 2: 13} | {100 + k: 1000 + k for k in range(200)}
        assert on_disk(db) == in_table(unit) == expected

        store = unit.store_file
        assert store is not None
        with FAULTS[fault](store._db):
            # one SLC MSG over N7:1-2 (written before) and N7:3-100 (never written)
            assert await plc.sts(slc_write(1, NEW)) == HOST_HARDWARE_FAULT
            # a PLC-5 write of 300 words in three packets: the first two are taken (STS 0, nothing
            # applied yet), the last one applies the whole transaction, whose save fails
            *head, last = plc5_packets(120, [-k for k in range(1, 301)])
            for packet in head:
                assert await plc.sts(packet) == 0
            assert await plc.sts(last) == HOST_HARDWARE_FAULT
        assert unit.persist_failures == 2
        assert_logged(caplog, fault)
        assert on_disk(db) == in_table(unit) == expected
        assert await served(plc, modbus, 0, 5) == ([11, 12, 13, 0, 0], NO_RESPONSE)  # N7:3-4 never written
        assert await served(plc, modbus, 120, 100) == ([1000 + k for k in range(20, 120)],) * 2
        assert await served(plc, modbus, 300, 100) == ([0] * 100, NO_RESPONSE)

        # the fault gone, the same MSG is saved (the PLC's ladder sends it again)
        assert await plc.sts(slc_write(1, NEW)) == 0
        expected |= {1 + k: value for k, value in enumerate(NEW)}
        assert on_disk(db) == in_table(unit) == expected
    async with gateway(db) as (_gw, unit, plc, modbus):
        assert on_disk(db) == in_table(unit) == expected
        assert await served(plc, modbus, 0, 5) == ([11, -1, -2, -3, -4],) * 2


@pytest.mark.parametrize("fault", list(FAULTS))
async def test_a_modbus_write_that_cannot_be_saved_is_answered_04_and_not_kept(
    tmp_path: Path, fault: str, caplog: pytest.LogCaptureFixture
) -> None:
    db = tmp_path / "plc.db"
    small_pages(db)
    async with gateway(db) as (_gw, unit, plc, modbus):
        assert not (await modbus.write_registers(140, list(range(1, 121)), device_id=UNIT)).isError()
        expected = {140 + k: 1 + k for k in range(120)}
        assert on_disk(db) == in_table(unit) == expected

        store = unit.store_file
        assert store is not None
        with FAULTS[fault](store._db):
            # 120 registers over N7:200-259 (written before) and N7:260-319 (never written)
            answer = await modbus.write_registers(200, [7] * 120, device_id=UNIT)
            assert answer.isError() and answer.exception_code == SERVER_DEVICE_FAILURE
            answer = await modbus.write_registers(400, [8] * 100, device_id=UNIT)  # never written
            assert answer.isError() and answer.exception_code == SERVER_DEVICE_FAILURE
        assert unit.persist_failures == 2
        assert_logged(caplog, fault)
        assert on_disk(db) == in_table(unit) == expected
        assert await served(plc, modbus, 140, 120) == (list(range(1, 121)),) * 2
        assert await served(plc, modbus, 260, 60) == ([0] * 60, NO_RESPONSE)
        assert await served(plc, modbus, 400, 100) == ([0] * 100, NO_RESPONSE)

        assert not (await modbus.write_register(150, 9, device_id=UNIT)).isError()
        expected[150] = 9
        assert on_disk(db) == in_table(unit) == expected
    async with gateway(db) as (_gw, unit, plc, modbus):
        assert on_disk(db) == in_table(unit) == expected
        assert (await served(plc, modbus, 145, 10))[0] == [6, 7, 8, 9, 10, 9, 12, 13, 14, 15]
