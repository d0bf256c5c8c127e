"""DF1 target mode end to end: a PLC's MSG instructions (``sim://plc-msg``) against the gateway,
the values checked over Modbus and back, under frame corruption, lost ACKs and NAKed replies."""

from __future__ import annotations

import struct
from collections import Counter
from collections.abc import AsyncIterator, Callable
from pathlib import Path

import pytest
from pymodbus.client import AsyncModbusTcpClient

from gateway.app import Gateway, describe_map
from gateway.config import parse_config
from gateway.errors import ConfigError
from gateway.kinds.df1.config import Df1LinkConfig
from gateway.kinds.df1.sim.plc_msg import PlcMsgSimulator
from gateway.kinds.df1.target.build import build_target
from gateway.kinds.df1.target.unit import TargetUnit
from gateway.sim import get_simulator, reset_simulators
from tests.waiting import until

FILES = """
[[link.file]]
file = 7
type = "N"
elements = 100

[[link.file]]
file = 8
type = "F"
elements = 10
start = 200

[[link.file]]
file = 3
type = "B"
elements = 4
table = "coil"
"""


def config(port: str, extra: str = "") -> str:
    return f"""
[modbus]
listen = "127.0.0.1:0"

[[link]]
name = "plc-msg"
protocol = "df1"
role = "target"
port = "{port}"
unit = 5
{extra}
{FILES}
"""


FAULTS = "sim://plc-msg?corrupt=4&lose_ack=4&nak_reply=4&duplicate=4&seed=3&every=0.005&cycle=0.01"


@pytest.fixture
async def target() -> AsyncIterator[tuple[Gateway, AsyncModbusTcpClient, PlcMsgSimulator, Counter[int]]]:
    reset_simulators()
    async with Gateway(parse_config(config(FAULTS))) as gw:
        (unit,) = gw.units
        assert isinstance(unit, TargetUnit)
        runs: Counter[int] = Counter()  # executions per (SRC, TNS): a duplicate must not run again
        execute: Callable[..., object] = unit.driver.target.execute

        def counting(packet: bytes, now: float) -> object:
            runs[int.from_bytes(packet[4:6], "little")] += 1
            return execute(packet, now)

        unit.driver.target.execute = counting  # type: ignore[method-assign]
        modbus = AsyncModbusTcpClient("127.0.0.1", port=gw.port)
        await modbus.connect()
        try:
            yield gw, modbus, get_simulator(FAULTS), runs
        finally:
            modbus.close()
        reset_simulators()


async def test_msgs_complete_under_faults_and_none_runs_twice(
    target: tuple[Gateway, AsyncModbusTcpClient, PlcMsgSimulator, Counter[int]],
) -> None:
    gw, modbus, plc, runs = target
    await until(lambda: plc.counters.done >= 150, 20.0, step=0.01, what="150 MSGs")
    faults = plc.counters.faults
    assert faults["corrupt"] and faults["lose_ack"] and faults["nak_reply"] and faults["duplicate"], faults
    assert plc.counters.failed == 0 and plc.counters.refused == 0, list(plc.log)[-5:]
    assert runs and max(runs.values()) == 1, [tns for tns, n in runs.items() if n > 1]
    (unit,) = gw.units
    assert unit.driver.duplicates > 0  # frames the PLC sent again: ACKed, not run

    # what the PLC wrote is on Modbus: N7:0-9 a counter run, F8:0-3 floats, B3:0 one bit
    words = await modbus.read_holding_registers(0, count=10, device_id=5)
    assert not words.isError()
    assert [w - words.registers[0] for w in words.registers] == list(range(10))
    floats = await modbus.read_holding_registers(200, count=8, device_id=5)
    values = [struct.unpack(">f", struct.pack(">HH", *floats.registers[i : i + 2]))[0] for i in range(0, 8, 2)]
    assert all(-1.0 <= v <= 1.0 for v in values)
    bits = await modbus.read_coils(0, count=16, device_id=5)
    assert sum(bits.bits[:16]) == 1


async def test_a_modbus_write_is_what_the_plcs_next_read_gets(
    target: tuple[Gateway, AsyncModbusTcpClient, PlcMsgSimulator, Counter[int]],
) -> None:
    _gw, modbus, plc, _runs = target
    never = await modbus.read_holding_registers(10, count=10, device_id=5)
    assert never.isError() and never.exception_code == 0x0B  # nobody wrote N7:10-19 yet
    setpoints = list(range(1000, 1010))
    assert not (await modbus.write_registers(10, setpoints, device_id=5)).isError()
    assert list((await modbus.read_holding_registers(10, count=10, device_id=5)).registers) == setpoints
    expected = b"".join(v.to_bytes(2, "little") for v in setpoints)
    plc.replies.clear()
    await until(lambda: plc.replies.get("SLC typed logical read N7:10-19") == expected, 20.0, step=0.01,
                what="the PLC's read")
    await until(lambda: plc.replies.get("PLC-5 word range read N7:10-14") == expected[:10], 20.0, step=0.01,
                what="the PLC-5 read")


async def test_status_block_shows_the_plc_side(
    target: tuple[Gateway, AsyncModbusTcpClient, PlcMsgSimulator, Counter[int]],
) -> None:
    gw, modbus, plc, _runs = target
    await until(lambda: plc.counters.done >= 20, 20.0, step=0.01, what="20 MSGs")
    status = await modbus.read_input_registers(1000, count=11, device_id=5)
    link_up, age, last_sts = status.registers[0:3]
    messages = status.registers[3] << 16 | status.registers[4]
    duplicates = status.registers[9] << 16 | status.registers[10]
    (unit,) = gw.units
    assert link_up == 1 and age < 20 and last_sts == 0
    assert messages >= 20 and duplicates == unit.driver.duplicates


ONE_MAP_ENTRY = '[[link.map]]\ntable = "holding"\nstart = 500\naddress = "N7:0"\ncount = 1\n'


def test_check_config_refuses_what_a_target_cannot_serve() -> None:
    text = config("sim://plc-msg")
    assert "not polled" in describe_map(parse_config(text))
    with pytest.raises(ConfigError, match=r'"T" is not a file type a target serves'):
        parse_config(text.replace('type = "B"', 'type = "T"'))
    with pytest.raises(ConfigError, match=r"file\[1\].start: F8 \(holding 20-39\) overlaps N7 \(holding 0-99\)"):
        parse_config(text.replace("start = 200", "start = 20"))
    with pytest.raises(ConfigError, match=r"only a B file maps to coil bits"):
        parse_config(text.replace('type = "B"', 'type = "N"'))
    with pytest.raises(ConfigError, match=r"map: not used by df1 links with role = \"target\""):
        parse_config(text.replace("unit = 5", "unit = 5\n" + ONE_MAP_ENTRY))
    # an initial value the table cannot hold is a config error, not a failure at start
    with pytest.raises(ConfigError, match=r"file\[0\].initial: N7: initial 40000: 40000 does not fit an N element"):
        parse_config(text.replace('elements = 100\n', 'elements = 100\ninitial = 40000\n', 1))
    assert parse_config(text.replace('elements = 100\n', 'elements = 100\ninitial = -32768\n', 1))
    with pytest.raises(ConfigError, match=r"overlaps the status block"):
        parse_config(text.replace("start = 200", 'start = 995\ntable = "input"'))
    refused = r'persist: not used by df1 links with duplex = "full" \(a key of a link with role = "target"'
    with pytest.raises(ConfigError, match=refused):
        parse_config(text.replace('role = "target"', 'persist = "x.db"').replace(FILES, ONE_MAP_ENTRY))


async def test_persist_brings_the_table_back_with_its_write_times(tmp_path: Path) -> None:
    reset_simulators()
    text = config("sim://plc-msg?every=0.005&cycle=0.01", f'persist = "{tmp_path / "plc.db"}"')
    async with Gateway(parse_config(text)) as gw:
        plc = get_simulator("sim://plc-msg?every=0.005&cycle=0.01")
        await until(lambda: plc.counters.done >= 30, 20.0, step=0.01, what="30 MSGs")
        modbus = AsyncModbusTcpClient("127.0.0.1", port=gw.port)
        await modbus.connect()
        assert not (await modbus.write_registers(50, [4242, 4343], device_id=5)).isError()
        modbus.close()
    reset_simulators()
    quiet = config("tcp-closed", f'persist = "{tmp_path / "plc.db"}"').replace('"tcp-closed"', '"socket://127.0.0.1:9"')
    async with Gateway(parse_config(quiet)) as gw:
        (_unit,) = gw.units
        modbus = AsyncModbusTcpClient("127.0.0.1", port=gw.port)
        await modbus.connect()
        assert list((await modbus.read_holding_registers(50, count=2, device_id=5)).registers) == [4242, 4343]
        assert not (await modbus.read_holding_registers(0, count=10, device_id=5)).isError()  # the PLC's, kept
        assert (await modbus.read_holding_registers(60, count=1, device_id=5)).isError()  # never written
        modbus.close()


def test_a_targets_ack_timeout_is_the_slc_channels_by_default() -> None:
    """The wait for the PLC's DLE ACK of a reply: an SLC 500 channel 0's "ACK Timeout 50" x 20 ms
    (1747-RM001G p. 13-52, Table 13.15), not the 0.5 s default of the half-duplex line key."""
    (link,) = parse_config(config("sim://plc-msg")).links
    assert isinstance(link, Df1LinkConfig)
    assert build_target(link).driver.responder.ack_timeout == 1.0
    (link,) = parse_config(config("sim://plc-msg", "ack_timeout = 0.3")).links
    assert isinstance(link, Df1LinkConfig)
    assert build_target(link).driver.responder.ack_timeout == 0.3
