"""A half-duplex station's MSG register table served as Modbus registers of its own unit.

``receive_words`` words of ``N<receive_file>`` a station writes to the gateway (report by exception)
are served read-only in ``receive_table`` from ``receive_start``, each word's age (0.1 s, 65535 =
never) right after the words (``gateway.kinds.df1.half.receive``).  Config checks of the range; the
window alone with a fake clock; end to end: a gateway on ``sim://df1line``, two stations sending
MSG writes, SCADA reading the ranges over Modbus TCP.
"""

from __future__ import annotations

import asyncio
from typing import Any

import pytest
from pymodbus.client import AsyncModbusTcpClient

from gateway.app import Gateway
from gateway.config import parse_config
from gateway.errors import ConfigError
from gateway.kinds.df1.config import Df1LinkConfig
from gateway.kinds.df1.half.receive import AGE_NEVER, ReceiveWindow
from gateway.kinds.df1.sim.df1_multidrop import MultidropLine
from gateway.modbus.mapping import Table
from gateway.protocols.df1.half_duplex.slave_messages import RegisterTable, SlaveWrite
from gateway.protocols.df1.pccc import LogicalBinaryAddress, WordRangeWrite, encode_command
from gateway.sim import get_simulator

pytestmark = pytest.mark.usefixtures("forget_simulators")


# --- config ----------------------------------------------------------------------------------


def _text(**keys: Any) -> str:
    keys = {"duplex": "half", **keys}
    lines = "".join(f"{key} = {value!r}\n".replace("'", '"') for key, value in keys.items())
    return (
        '[[link]]\nname = "s2"\nprotocol = "df1"\nport = "/dev/ttyS1"\nunit = 2\nstation = 2\n'
        f'{lines}[[link.map]]\ntable = "input"\nstart = 0\naddress = "N7:0"\ncount = 10\n'
    )


def _link(**keys: Any) -> Df1LinkConfig:
    (link,) = parse_config(_text(**keys)).links
    assert isinstance(link, Df1LinkConfig)
    return link


def test_defaults_and_a_valid_range() -> None:
    plain = _link()
    assert (plain.receive_words, plain.receive_table, plain.receive_start) == (0, "input", 0)
    link = _link(receive_words=8, receive_start=10)
    assert link.receive_last == 25  # 8 words 10-17, ages 18-25
    assert _link(receive_words=8, receive_table="holding").receive_start == 0  # the map is input: no overlap
    assert _link(receive_words=4, receive_start=995, receive_table="holding").receive_last == 1002  # no status


@pytest.mark.parametrize(
    ("keys", "message"),
    [
        ({"receive_words": 4}, "(link[0]).receive_start: the receive range (input 0-7: 4 words, then their ages) "
         "overlaps map[0] (input 0-9): move receive_start"),
        ({"receive_words": 4, "receive_start": 9}, "(link[0]).receive_start: the receive range (input 9-16"),
        ({"receive_words": 4, "receive_start": 65530},
         "(link[0]).receive_start: the receive range (input 65530-65537: 4 words, then their ages) ends past "
         "Modbus address 65535: start 65530 + 2 x receive_words 4 - 1 = 65537"),
        ({"receive_words": 4, "receive_start": 995},
         "(link[0]).receive_start: the receive range (input 995-1002: 4 words, then their ages) overlaps the "
         "unit's status block (input 1000-1011)"),
        ({"receive_words": 4, "receive_start": 20, "duplex": "full"},
         '(link[0]).receive_words: not used by df1 links with duplex = "full" (a half-duplex station key: on a '
         "full-duplex link the gateway takes no messages from the controller)"),
    ],
)
def test_bad_ranges_are_refused(keys: dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError) as info:
        parse_config(_text(**keys))
    assert message in str(info.value)


# --- the window ------------------------------------------------------------------------------


def test_window_serves_words_then_ages() -> None:
    table = RegisterTable(file_number=7, size=3)
    window = ReceiveWindow(Table.INPUT, 100, table)
    assert table.store(SlaveWrite(7, 1, (0xBEEF, 5)), now=10.0)
    registers = window.registers(100, 6, now=12.34)
    assert registers == bytes.fromhex("0000 BEEF 0005 FFFF 0017 0017".replace(" ", ""))  # 2.34 s = 23 tenths
    assert window.registers(104, 1, now=10.0 + 6553.4) == (65534).to_bytes(2, "big")
    assert window.registers(104, 1, now=10.0 + 7000.0) == AGE_NEVER.to_bytes(2, "big")  # over range
    assert window.overlaps(Table.INPUT, 95, 6) and not window.overlaps(Table.INPUT, 95, 5)
    assert not window.overlaps(Table.HOLDING, 100, 1) and not window.overlaps(Table.INPUT, 106, 3)
    assert list(window.split(98, 10)) == [(98, 2, False), (100, 6, True), (106, 2, False)]
    assert list(window.split(101, 2)) == [(101, 2, True)]


# --- end to end ------------------------------------------------------------------------------

URL = "sim://df1line?stations=1,2&checksum=bcc&ladder=0"
UNIT_KEYS = (
    'checksum = "bcc"\npoll_timeout = 0.05\nack_timeout = 0.05\ntimeout = 0.5\npoll_interval = 0.05\n'
    "slow_poll_interval = 2.0\ndemote_after = 5\nreceive_words = 3\n"
)
CONFIG = (
    '[modbus]\nlisten = "127.0.0.1:0"\n'
    f'\n[[link]]\nname = "s1"\nprotocol = "df1"\nport = "{URL}"\nduplex = "half"\nstation = 1\nunit = 1\n'
    f'{UNIT_KEYS}receive_table = "holding"\nreceive_start = 100\n'
    '[[link.map]]\ntable = "holding"\nstart = 0\naddress = "N7:0"\ncount = 2\n'
    f'\n[[link]]\nname = "s2"\nprotocol = "df1"\nport = "{URL}"\nduplex = "half"\nstation = 2\nunit = 2\n'
    f"{UNIT_KEYS}receive_start = 100\n"
    '[[link.map]]\ntable = "holding"\nstart = 0\naddress = "N7:0"\ncount = 2\n'
    '[[link.map]]\ntable = "input"\nstart = 98\naddress = "N7:0"\ncount = 2\n'
)


def _msg(station: int, element: int, words: list[int], tns: int) -> bytes:
    data = b"".join(word.to_bytes(2, "little") for word in words)
    return encode_command(WordRangeWrite(LogicalBinaryAddress.of(0, 7, element), data), dst=0, src=station, tns=tns)


async def _until(modbus: AsyncModbusTcpClient, read: str, unit: int, address: int, count: int,
                 done: Any) -> list[int]:
    registers: list[int] = []
    for _ in range(250):
        reply = await getattr(modbus, read)(address, count=count, device_id=unit)
        if not reply.isError():
            registers = list(reply.registers)
            if done(registers):
                return registers
        await asyncio.sleep(0.02)
    raise AssertionError(f"unit {unit} {read} {address}-{address + count - 1}: last {registers}")


async def test_each_station_serves_its_own_table_over_modbus() -> None:
    config = parse_config(CONFIG)
    line = get_simulator(URL)
    assert isinstance(line, MultidropLine)
    for number, controller in line.controllers.items():
        controller.set_word("N7", 0, 1000 + number)
        controller.set_word("N7", 1, 2000 + number)
    async with Gateway(config) as gw:
        modbus = AsyncModbusTcpClient("127.0.0.1", port=gw.port)
        await modbus.connect()
        try:
            # Before any message: words 0, ages 65535 (never), served at once (no line I/O needed).
            reply = await modbus.read_input_registers(100, count=6, device_id=2)
            assert list(reply.registers) == [0, 0, 0, AGE_NEVER, AGE_NEVER, AGE_NEVER]
            await asyncio.sleep(0.3)  # after the line's link reset (DLE NAK empties slave queues)
            line.slaves[2].initiate(_msg(2, 0, [42, 43], tns=11))
            line.slaves[1].initiate(_msg(1, 2, [7], tns=12))
            two = await _until(modbus, "read_input_registers", 2, 100, 6, lambda r: r[:3] == [42, 43, 0])
            assert two[3] == two[4] and two[3] < 50 and two[5] == AGE_NEVER  # written < 5 s ago; word 2 never
            one = await _until(modbus, "read_holding_registers", 1, 100, 6, lambda r: r[2] == 7)
            assert one[:2] == [0, 0] and one[3:5] == [AGE_NEVER, AGE_NEVER] and one[5] < 50  # its own table
            # The ages grow as time passes, with no new message.
            await asyncio.sleep(0.35)
            later = await modbus.read_input_registers(103, count=1, device_id=2)
            assert later.registers[0] >= two[3] + 3
            # A read spanning the mapped input registers 98-99 and the window: each part from its source.
            span = await _until(modbus, "read_input_registers", 2, 98, 5, lambda r: True)
            assert span == [1002, 2002, 42, 43, 0]
            # The window is read-only: holding 100 of unit 1 refuses a write (0x02); nothing reaches a station.
            refused = await modbus.write_register(100, 5, device_id=1)
            assert refused.isError() and refused.exception_code == 2
            assert (await modbus.read_holding_registers(100, count=1, device_id=1)).registers == [0]
            # The map is served as before, per station.
            assert await _until(modbus, "read_holding_registers", 1, 0, 2, lambda r: True) == [1001, 2001]
            assert await _until(modbus, "read_holding_registers", 2, 0, 2, lambda r: True) == [1002, 2002]
        finally:
            modbus.close()
    assert [len(line.controllers[n].applied_writes) for n in (1, 2)] == [0, 0]
