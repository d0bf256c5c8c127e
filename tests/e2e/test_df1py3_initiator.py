"""DF1 target mode driven by a DF1 master the project did not write: the public ``df1py3`` package.

``df1py3`` (PyPI, version 1.0a45, the latest; MIT; github.com/reyanvaldes/pydf1, a fork of
metalsartigan/pydf1) is a DF1 full-duplex master for talking to MicroLogix / SLC 500 / PLC-5
controllers.  Here it plays the PLC whose MSG instructions address the gateway (``role =
"target"``), and every value it writes or reads is checked over Modbus TCP (pymodbus), both ways.

What df1py3 1.0a45 can send, read from its source (``df1/commands/commands.py``,
``df1/models/df1_base.py``, ``frame_factory.py``, ``crc16.py``, ``file_type.py``):

* CMD 0F FNC A2, protected typed logical read with three address fields (``Command0FA2``; the
  wrappers ``read_integer`` N, ``read_float`` F, ``read_binary`` B, and ``read_output`` /
  ``read_input`` / ``read_timer`` / ``read_counter`` / ``read_register`` for O, I, T, C, R);
* CMD 0F FNC AA, protected typed logical write with three address fields (``Command0FAA``: file
  types N, B, O and R as 16-bit words 0..65535, F as raw bytes; the wrappers ``write_float``,
  ``write_binary``, ``write_output``, ``write_register``; it has no wrapper for N, which takes
  ``create_command(Command0FAA, file_type=FileType.INTEGER, ...)``);
* CMD 0F FNC AB, protected typed logical masked write (``Command0FAB``: N, B or F, one 16-bit mask
  for every word; ``Command0FABSingleBit``: one bit);
* CMD 0F FNC 04 with the A2 parameters (``Command0F04``, docstring "protected typed logical read",
  not exported by ``df1.commands``): not a command the gateway answers, so it refuses it, STS 10.

What it cannot send or receive:

* file, element and sub-element numbers above 254 (it raises NotImplementedError: no
  FF-expanded address fields); the two-field commands (0F A1 / A9);
* L files: its ``FileType`` has no long-integer type (91 hex);
* the PLC-5 commands (0F 00 / 01 word range, 0F 67 / 68 typed write / read);
* the answer to any command other than CMD 0F: ``frame_factory`` parses only CMD 4F replies, so
  its ``Command0600`` (echo) and ``Command0603`` (diagnostic status, which besides sends the A2
  parameters along) get their reply (CMD 46) dropped unacknowledged in its socket thread;
* BCC: it computes CRC only (so the link here has ``checksum = "crc"``).

Its link layer: a command it sent is answered by DLE ACK and a reply frame, which it ACKs (or
NAKs on a bad CRC); on DLE NAK it sends the command again under a new TNS; it answers DLE ENQ with
its last ACK / NAK.  Its wrappers do not look at STS: ``write_float`` returns True for any reply
and ``read_integer`` returns ``[]`` for a refused read, so these tests check ``reply.sts``.

Transports (both in df1py3): ``Df1TCPClient`` connects to a serial device server in TCP server
mode; ``Df1SerialClient`` opens a serial port with pyserial.  The gateway, too, connects to its
port, so the TCP tests listen for both and relay between them (the serial line between two
device servers).  The serial test joins two pseudo-terminals back to back: the gateway opens one
as a local serial port, df1py3 the other.  df1py3's serial client opens its port with
``write_timeout=0.00001``: pyserial 3.5 raises SerialTimeoutException after any write that took
longer than 10 microseconds (the bytes are already out), which ends df1py3's serial thread; the
serial test lifts that timeout after ``connect()`` (one attribute of its pyserial object).

Without df1py3 these tests are skipped, unless ``SLC_GATEWAY_REQUIRE_DF1PY3=1`` (CI), which makes
them fail instead.
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib.metadata
import os
import pty
import sqlite3
import struct
import tty
import warnings
from collections.abc import AsyncIterator, Callable, Iterator
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from types import SimpleNamespace
from typing import Any, TypeVar

import pytest
from modbus_support import HOST, connect, exception_code
from pymodbus.client import AsyncModbusTcpClient

from gateway.app import Gateway
from gateway.config import parse_config
from gateway.kinds.df1.target.unit import TargetUnit

#: the requirement line of the test extra
DF1PY3 = "df1py3==1.0a45"
UNIT = 1
GATEWAY_NODE, PLC_NODE = 1, 0
#: Modbus addresses of the files (FILES below)
N7, F8, B3_COIL = 0, 200, 0
TARGET_FAILED = 0x0B  # Modbus exception of an element nobody wrote
STS_OK, STS_ILLEGAL_COMMAND, STS_ADDRESS_PROBLEM = 0x00, 0x10, 0x50

FILES = f"""
[[link.file]]
file = 7
type = "N"
elements = 100
table = "holding"
start = {N7}

[[link.file]]
file = 8
type = "F"
elements = 10
table = "holding"
start = {F8}

[[link.file]]
file = 3
type = "B"
elements = 4
table = "coil"
start = {B3_COIL}
"""

T = TypeVar("T")


def df1py3() -> SimpleNamespace:
    """df1py3's classes; skip loudly without it, unless SLC_GATEWAY_REQUIRE_DF1PY3=1 makes that a failure."""
    try:
        version = importlib.metadata.version("df1py3")
        from df1.commands.commands import Command0F04, Command0FA2, Command0FAA, Command0FAB, Command0FABSingleBit
        from df1.file_type import FileType
        from df1.models.df1_serial_client import Df1SerialClient
        from df1.models.df1_tcp_client import Df1TCPClient
    except (importlib.metadata.PackageNotFoundError, ImportError) as exc:
        why = (f"DF1PY3 NOT INSTALLED ({exc}): the DF1 target is not tested against a third-party master; "
               f"pip install '{DF1PY3}' (the test extra)")
        if os.environ.get("SLC_GATEWAY_REQUIRE_DF1PY3") == "1":
            pytest.fail(f"{why}; SLC_GATEWAY_REQUIRE_DF1PY3=1 requires it")
        warnings.warn(why, pytest.PytestWarning, stacklevel=2)
        pytest.skip(f"{why}; set SLC_GATEWAY_REQUIRE_DF1PY3=1 to fail instead")
    return SimpleNamespace(version=version, Command0F04=Command0F04, Command0FA2=Command0FA2,
                           Command0FAA=Command0FAA, Command0FAB=Command0FAB, Command0FABSingleBit=Command0FABSingleBit,
                           FileType=FileType, Df1SerialClient=Df1SerialClient, Df1TCPClient=Df1TCPClient)


def config(port: str, persist: Path | None = None) -> str:
    return f"""
[modbus]
listen = "{HOST}:0"

[[link]]
name = "df1py3"
protocol = "df1"
role = "target"
port = "{port}"
unit = {UNIT}
station = {GATEWAY_NODE}
checksum = "crc"
{f'persist = "{persist}"' if persist else ""}
{FILES}
"""


# --------------------------------------------------------------------------------------------
# the line between df1py3 and the gateway


class TcpRelay:
    """Two TCP listeners joined back to back: what two serial device servers and a cable between
    them do.  Bytes that arrive before the other side has connected wait in the socket."""

    def __init__(self) -> None:
        self.writers: dict[str, asyncio.StreamWriter] = {}
        self.servers: list[asyncio.Server] = []
        self.ports: dict[str, int] = {}
        self._both = asyncio.Event()

    async def start(self) -> None:
        for side in ("gateway", "plc"):
            server = await asyncio.start_server(partial(self._side, side), HOST, 0)
            self.servers.append(server)
            self.ports[side] = server.sockets[0].getsockname()[1]

    async def _side(self, side: str, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if side in self.writers:  # one cable: a second connection on a side is refused
            writer.close()
            return
        self.writers[side] = writer
        if len(self.writers) == 2:
            self._both.set()
        await self._both.wait()
        other = self.writers["plc" if side == "gateway" else "gateway"]
        with contextlib.suppress(ConnectionError):
            while data := await reader.read(4096):
                other.write(data)

    async def close(self) -> None:
        for writer in self.writers.values():
            writer.close()
        for server in self.servers:
            server.close()
            await server.wait_closed()


@contextlib.contextmanager
def pty_cable() -> Iterator[tuple[str, str]]:
    """Two pseudo-terminals whose master sides are joined: (path A, path B), a null-modem cable."""
    loop = asyncio.get_running_loop()
    a_master, a_slave = pty.openpty()
    b_master, b_slave = pty.openpty()
    for fd in (a_slave, b_slave):
        tty.setraw(fd)  # no echo, no line editing before the opener sets its own mode
    for fd in (a_master, b_master):
        os.set_blocking(fd, False)

    def relay(source: int, sink: int) -> None:
        try:
            data = os.read(source, 4096)
        except OSError:  # EIO: nobody has the other side open at this moment
            return
        os.write(sink, data)

    loop.add_reader(a_master, relay, a_master, b_master)
    loop.add_reader(b_master, relay, b_master, a_master)
    try:
        yield os.ttyname(a_slave), os.ttyname(b_slave)
    finally:
        for fd in (a_master, b_master):
            loop.remove_reader(fd)
        for fd in (a_master, b_master, a_slave, b_slave):
            os.close(fd)


async def in_thread(call: Callable[..., T], *args: Any, **kwargs: Any) -> T:
    """df1py3 blocks (it polls its queue every 20 ms): run it beside the gateway's event loop."""
    return await asyncio.wait_for(asyncio.to_thread(call, *args, **kwargs), 20)


# --------------------------------------------------------------------------------------------
# the plant


@dataclass
class Plant:
    df1: SimpleNamespace  # df1py3's classes
    plc: Any  # df1py3's client: the initiating PLC
    gw: Gateway
    modbus: AsyncModbusTcpClient
    db: Path

    def send(self, command: Any, **params: Any) -> Any:
        """One df1py3 command (create_command + send_command); its Reply4f, of the same TNS."""
        request = self.plc.create_command(command, **params)
        reply = self.plc.send_command(request)
        assert reply.tns == request.tns
        return reply

    async def command(self, command: Any, **params: Any) -> tuple[int, list[int]]:
        """(STS, data bytes after the TNS) of one df1py3 command."""
        reply = await in_thread(self.send, command, **params)
        return reply.sts.value, list(reply._get_command_data())

    async def holding(self, address: int, count: int) -> list[int]:
        answer = await self.modbus.read_holding_registers(address, count=count, device_id=UNIT)
        assert not answer.isError(), answer
        return list(answer.registers)

    async def floats(self, address: int, count: int) -> list[float]:
        words = await self.holding(address, 2 * count)
        return [struct.unpack(">f", struct.pack(">HH", *words[i : i + 2]))[0] for i in range(0, 2 * count, 2)]

    def stored(self, file: int) -> dict[int, bytes]:
        """The rows of ``file`` committed to persist, by element (read beside the gateway: WAL)."""
        with contextlib.closing(sqlite3.connect(f"file:{self.db}?mode=ro", uri=True)) as db:
            rows = db.execute("SELECT element, value FROM element WHERE file = ?", (file,)).fetchall()
        return {int(element): bytes(value) for element, value in rows}


@pytest.fixture
async def plant(tmp_path: Path) -> AsyncIterator[Plant]:
    df1 = df1py3()
    relay = TcpRelay()
    await relay.start()
    db = tmp_path / "target.db"
    try:
        async with Gateway(parse_config(config(f"socket://{HOST}:{relay.ports['gateway']}", db))) as gw:
            plc = df1.Df1TCPClient(ip_address=HOST, ip_port=relay.ports["plc"], src=PLC_NODE, dst=GATEWAY_NODE,
                                   timeout=3)
            try:
                assert await in_thread(plc.connect), "df1py3 did not connect to the relay"
                async with connect(gw.port) as modbus:
                    yield Plant(df1, plc, gw, modbus, db)
            finally:
                await in_thread(plc.close)
    finally:
        await relay.close()


def words(values: list[int]) -> bytes:
    return b"".join(v.to_bytes(2, "little") for v in values)


# --------------------------------------------------------------------------------------------
# the tests

#: N7:0-9 as df1py3 writes them: DLE (10 hex) bytes in both halves, the extremes of a word
N7_VALUES = [0, 1, 0x1010, 0x7FFF, 0x8000, 0xFFFF, 1234, 0x0010, 0x1000, 42]
F8_VALUES = [1.5, -2.25, 3.0e6]


async def test_what_df1py3_writes_is_on_modbus_and_on_disk(plant: Plant) -> None:
    df1, file_type = plant.df1, plant.df1.FileType
    # typed logical write, N: 10 words
    sts, _ = await plant.command(df1.Command0FAA, table=7, file_type=file_type.INTEGER, start=0,
                                 data_to_write=N7_VALUES)
    assert sts == STS_OK
    assert await plant.holding(N7, 10) == N7_VALUES
    assert plant.stored(7) == {e: words([v]) for e, v in enumerate(N7_VALUES)}  # committed before the reply

    # typed logical write, F: df1py3's write_float (it returns True for any reply: the value proves it)
    assert await in_thread(plant.plc.write_float, file_table=8, start=0, data=F8_VALUES)
    assert await plant.floats(F8, 3) == F8_VALUES
    assert plant.stored(8)[2] == struct.pack("<f", 3.0e6)

    # masked write: only the mask's bits of N7:3 change; then B3:1 bits 4-7 set, bit 5 cleared alone
    sts, _ = await plant.command(df1.Command0FAB, table=7, file_type=file_type.INTEGER, start=3, bit_mask=0xFF00,
                                 data_to_write=[0x1200])
    assert sts == STS_OK
    assert await plant.holding(N7 + 3, 1) == [0x12FF]
    sts, _ = await plant.command(df1.Command0FAB, table=3, file_type=file_type.BIT, start=1, bit_mask=0x00F0,
                                 data_to_write=[0xFFFF])
    assert sts == STS_OK
    sts, _ = await plant.command(df1.Command0FABSingleBit, table=3, file_type=file_type.BIT, start=1,
                                 bit_position=5, bit_value=0)
    assert sts == STS_OK
    coils = await plant.modbus.read_coils(B3_COIL + 16, count=16, device_id=UNIT)
    assert [k for k, bit in enumerate(coils.bits[:16]) if bit] == [4, 6, 7]
    assert plant.stored(3) == {1: words([0x00D0])}

    # and df1py3 reads all of it back (typed logical read of N, F, B)
    expected = [*N7_VALUES[:3], 0x12FF, *N7_VALUES[4:]]
    assert await in_thread(plant.plc.read_integer, file_table=7, start=0, total_int=10) == expected
    assert await in_thread(plant.plc.read_float, file_table=8, start=0, total_float=3) == F8_VALUES
    assert await in_thread(plant.plc.read_binary, file_table=3, start=1, total_int=1) == [0x00D0]

    (unit,) = plant.gw.units
    assert isinstance(unit, TargetUnit)
    link = unit.driver.metrics()
    assert link["target_bad_frames"] == 0 and link["target_duplicates"] == 0 and link["target_refused"] == 0, link


async def test_what_modbus_writes_is_what_df1py3_reads(plant: Plant) -> None:
    setpoints = [100, 0x1010, 65535, 7, 0]
    assert exception_code(await plant.modbus.read_holding_registers(N7 + 10, count=5, device_id=UNIT)) == TARGET_FAILED
    assert not (await plant.modbus.write_registers(N7 + 10, setpoints, device_id=UNIT)).isError()
    assert await in_thread(plant.plc.read_integer, file_table=7, start=10, total_int=5) == setpoints

    high, low = struct.unpack(">HH", struct.pack(">f", -0.125))
    assert not (await plant.modbus.write_registers(F8 + 10, [high, low], device_id=UNIT)).isError()  # F8:5
    assert await in_thread(plant.plc.read_float, file_table=8, start=5, total_float=1) == [-0.125]

    bits = [k % 3 == 0 for k in range(16)]
    assert not (await plant.modbus.write_coils(B3_COIL + 32, bits, device_id=UNIT)).isError()  # B3:2
    assert await in_thread(plant.plc.read_binary, file_table=3, start=2, total_int=1) == [
        sum(1 << k for k, bit in enumerate(bits) if bit)]

    # an element nobody wrote: the PLC reads 0 (as a new data file does); Modbus still says so
    assert await in_thread(plant.plc.read_integer, file_table=7, start=60, total_int=2) == [0, 0]
    assert exception_code(await plant.modbus.read_holding_registers(N7 + 60, count=1, device_id=UNIT)) == TARGET_FAILED


async def test_df1py3_gets_the_sts_of_what_the_target_refuses(plant: Plant) -> None:
    df1, file_type = plant.df1, plant.df1.FileType
    read = partial(plant.command, df1.Command0FA2, file_type=file_type.INTEGER)
    assert (await read(table=7, start=99, bytes_to_read=4))[0] == STS_ADDRESS_PROBLEM  # runs past N7:99
    assert (await read(table=9, start=0, bytes_to_read=2))[0] == STS_ADDRESS_PROBLEM  # no file 9
    assert (await read(table=7, start=0, bytes_to_read=2, start_sub=1))[0] == STS_ADDRESS_PROBLEM  # sub-element
    assert (await plant.command(df1.Command0FA2, table=7, file_type=file_type.FLOAT, start=0,
                                bytes_to_read=4))[0] == STS_ADDRESS_PROBLEM  # N7 read as F
    sts, _ = await plant.command(df1.Command0FAA, table=7, file_type=file_type.INTEGER, start=98,
                                 data_to_write=[1, 2, 3])
    assert sts == STS_ADDRESS_PROBLEM
    assert exception_code(await plant.modbus.read_holding_registers(N7 + 98, count=1, device_id=UNIT)) == TARGET_FAILED
    assert plant.stored(7) == {}  # a refused write changes nothing, on disk neither
    assert (await plant.command(df1.Command0F04, table=7, file_type=file_type.INTEGER, start=0,
                                bytes_to_read=2))[0] == STS_ILLEGAL_COMMAND
    # the link is as good as before: a write goes through
    sts, _ = await plant.command(df1.Command0FAA, table=7, file_type=file_type.INTEGER, start=98, data_to_write=[5, 6])
    assert sts == STS_OK and await plant.holding(N7 + 98, 2) == [5, 6]
    (unit,) = plant.gw.units
    assert isinstance(unit, TargetUnit)
    assert unit.driver.refused == 6 and unit.driver.last_sts == STS_ILLEGAL_COMMAND


async def test_df1py3_over_a_serial_port(tmp_path: Path) -> None:
    """df1py3's serial client on one pseudo-terminal, the gateway on the other (a local port path)."""
    df1 = df1py3()
    with pty_cable() as (gateway_tty, plc_tty):
        async with Gateway(parse_config(config(gateway_tty))) as gw:
            plc = df1.Df1SerialClient(port=plc_tty, src=PLC_NODE, dst=GATEWAY_NODE, timeout=3)
            try:
                assert await in_thread(plc.connect)
                plc._plc._plc.write_timeout = None  # df1py3's 10-microsecond write timeout (module doc)
                async with connect(gw.port) as modbus:
                    plant = Plant(df1, plc, gw, modbus, tmp_path / "unused.db")
                    sts, _ = await plant.command(df1.Command0FAA, table=7, file_type=df1.FileType.INTEGER, start=0,
                                                 data_to_write=N7_VALUES)
                    assert sts == STS_OK and await plant.holding(N7, 10) == N7_VALUES
                    sts, _ = await plant.command(df1.Command0FABSingleBit, table=3, file_type=df1.FileType.BIT,
                                                 start=0, bit_position=15, bit_value=1)
                    assert sts == STS_OK
                    coils = await modbus.read_coils(B3_COIL, count=16, device_id=UNIT)
                    assert [k for k, bit in enumerate(coils.bits[:16]) if bit] == [15]
                    assert not (await modbus.write_registers(N7 + 20, [4321], device_id=UNIT)).isError()
                    assert await in_thread(plc.read_integer, file_table=7, start=20, total_int=1) == [4321]
            finally:
                await in_thread(plc.close)
                await asyncio.sleep(0.05)  # its thread closes the port on its way out
