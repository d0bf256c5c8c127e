"""DF1 target mode, the unit alone (``gateway/kinds/df1/target/unit.py``): the target's data files as
Modbus points, Modbus writes applied to the table, and the table loaded at start.

What docs/guide/target-mode.md promises, checked here without a line or a Modbus server (the PLC's
MSG is a PCCC packet handed to the link's target, as the runner hands it; Modbus requests are the
unit's own read and write calls, as the Modbus server makes them):

* a file goes to ``table`` from ``start``; "F and L take two registers per element"; "a B file may
  also go to coil / discrete (16 per element)": bit k of element e is bit ``start + 16 e + k``;
* holding registers and coils are written by Modbus clients, input registers and discrete inputs are
  not (Modbus Application Protocol V1.1b3, 4.3: the input tables are read only);
* "a value a Modbus client writes is what the PLC's next read gets; a write of several registers
  (or coils) is applied whole"; a coil write changes its bit and no other bit of the B element;
* "an element nobody has written since start answers 0x0B ... unless ``initial`` or ``persist``
  gives it a value"; with ``persist``, the table "comes back with its values and write times";
* each Modbus write is committed to ``persist`` before its answer; one that cannot be is answered
  exception 04 (the guide's table of errors) and leaves the table as it was;
* every Modbus write is logged at INFO on ``gateway.audit`` with its unit and addresses
  (docs/guide/reads-and-writes.md), and counted in ``slc_gateway_write_requests_total`` /
  ``..._write_failures_total`` with its duration in ``..._write_duration_seconds``
  (docs/reference/metrics.md).

On the DF1 wire an element is little-endian, an F or L element low-order word first (1770-6.5.16,
SLC typed logical read/write data): N7:0 = 0x1234 is the bytes 34 12.
"""

from __future__ import annotations

import logging
import re
import time
from pathlib import Path

import pytest

import gateway.kinds  # noqa: F401  (registers the link kinds the config is checked against)
from gateway.config import parse_config
from gateway.errors import ModbusExceptionReply
from gateway.kinds.df1.build import df1_plan_lines
from gateway.kinds.df1.config import Df1LinkConfig
from gateway.kinds.df1.target.build import build_target
from gateway.kinds.df1.target.store import StoredElement, TargetStore
from gateway.kinds.df1.target.unit import TargetUnit, load_table, target_plan, target_point_labels
from gateway.modbus.mapping import PointLabel, Table
from gateway.protocols.df1.address import FileType
from gateway.protocols.df1.pccc import PcccHeader, ProtectedTypedLogicalRead, ProtectedTypedLogicalWrite
from gateway.protocols.df1.pccc.commands import encode_command
from gateway.tags import link_tags

UNIT = 4
#: Modbus exception codes (Modbus Application Protocol V1.1b3, 7)
ILLEGAL_DATA_ADDRESS = 0x02
SERVER_DEVICE_FAILURE = 0x04
GATEWAY_TARGET_FAILED = 0x0B

#: B3 on coils 100-147 (3 elements), N7 on holding 0-9, N10 on input 20-24, B12 on discrete 200-231
FILES = """
[[link.file]]
file = 3
type = "B"
elements = 3
table = "coil"
start = 100

[[link.file]]
file = 7
type = "N"
elements = 10

[[link.file]]
file = 10
type = "N"
elements = 5
table = "input"
start = 20

[[link.file]]
file = 12
type = "B"
elements = 2
table = "discrete"
start = 200
"""

#: a float file (two words an element) at holding register 50
FLOAT_FILE = """
[[link.file]]
file = 8
type = "F"
elements = 2
start = 50
"""


def link(files: str = FILES, persist: Path | None = None) -> Df1LinkConfig:
    db = f'persist = "{persist}"' if persist is not None else ""
    config = parse_config(f"""
[[link]]
name = "plc"
protocol = "df1"
role = "target"
port = "socket://127.0.0.1:9"
station = 1
unit = {UNIT}
{db}
{files}
""")
    (target,) = config.link
    assert isinstance(target, Df1LinkConfig)
    return target


class Plc:
    """The PLC's MSGs to the unit's target, handed over as the runner hands a received command."""

    def __init__(self, unit: TargetUnit) -> None:
        self.unit = unit
        self.tns = 0

    def _execute(self, request: ProtectedTypedLogicalRead | ProtectedTypedLogicalWrite) -> bytes:
        self.tns += 1
        result = self.unit.driver.target.execute(encode_command(request, dst=1, src=9, tns=self.tns), 0.0)
        assert result.reply is not None
        if result.written:
            self.unit.driver.on_written(result.written)
        assert PcccHeader.decode(result.reply).sts == 0, result.reply.hex()
        return result.reply[6:]

    def write(self, file_type: FileType, file: int, element: int, data: bytes) -> None:
        self._execute(ProtectedTypedLogicalWrite(file_type, file, element, 0, data))

    def read(self, file_type: FileType, file: int, element: int, size: int) -> bytes:
        return self._execute(ProtectedTypedLogicalRead(file_type, file, element, 0, size))


def words(*values: int) -> bytes:
    return b"".join(v.to_bytes(2, "little") for v in values)


def code_of(excinfo: pytest.ExceptionInfo[ModbusExceptionReply]) -> int:
    return excinfo.value.code


# --- where each file is on Modbus ---------------------------------------------------------------


async def test_bit_k_of_a_coil_b_element_is_coil_start_plus_16_per_element_plus_k() -> None:
    unit = build_target(link())
    plc = Plc(unit)
    plc.write(FileType.BIT, 3, 0, words(0x0001, 0x8000, 0x0120))  # B3:0/0, B3:1/15, B3:2/5 and B3:2/8
    expected = [False] * 48
    expected[0] = expected[16 + 15] = expected[32 + 5] = expected[32 + 8] = True
    assert unit.read_bits(Table.COIL, 100, 48) == expected
    assert unit.read_bits(Table.COIL, 132, 16) == expected[32:]
    for past in (99, 148):  # 16 coils per element, 3 elements: 100-147 and nothing around
        with pytest.raises(ModbusExceptionReply) as excinfo:
            unit.read_bits(Table.COIL, past, 1)
        assert code_of(excinfo) == ILLEGAL_DATA_ADDRESS, past


async def test_a_discrete_b_file_is_read_as_discrete_inputs_and_not_as_coils() -> None:
    unit = build_target(link())
    plc = Plc(unit)
    plc.write(FileType.BIT, 12, 0, words(0x0000, 0x4002))  # B12:1/1 and B12:1/14
    assert unit.read_bits(Table.DISCRETE, 200, 32) == [k in (17, 30) for k in range(32)]
    with pytest.raises(ModbusExceptionReply) as excinfo:
        unit.read_bits(Table.COIL, 200, 1)
    assert code_of(excinfo) == ILLEGAL_DATA_ADDRESS


async def test_an_input_file_is_read_as_input_registers_and_not_written() -> None:
    unit = build_target(link())
    plc = Plc(unit)
    plc.write(FileType.INTEGER, 10, 0, words(1, 2, 3, 4, 0xFFFF))
    assert unit.read_registers(Table.INPUT, 20, 5) == [1, 2, 3, 4, 0xFFFF]
    with pytest.raises(ModbusExceptionReply) as excinfo:
        unit.read_registers(Table.HOLDING, 20, 1)
    assert code_of(excinfo) == ILLEGAL_DATA_ADDRESS
    with pytest.raises(ModbusExceptionReply) as excinfo:
        await unit.write_registers(20, [7])
    assert code_of(excinfo) == ILLEGAL_DATA_ADDRESS


def test_only_holding_registers_and_coils_are_writable_in_the_tag_list() -> None:
    tags = {(tag.table, tag.address): tag for tag in link_tags(link())}
    assert all(tags[(Table.COIL, a)].writable for a in range(100, 148))
    assert all(tags[(Table.HOLDING, a)].writable for a in range(0, 10))
    assert not any(tags[(Table.INPUT, a)].writable for a in range(20, 25))
    assert not any(tags[(Table.DISCRETE, a)].writable for a in range(200, 232))


def test_check_config_names_each_file_with_its_elements() -> None:
    lines = df1_plan_lines(target_plan(link().file))
    # one line per file, its first and last element in the PLC's notation
    assert [re.findall(r"^file ([A-Z]\d+:\d+-\d+):", line) for line in lines] == [
        ["B3:0-2"], ["N7:0-9"], ["N10:0-4"], ["B12:0-1"]
    ]


def test_point_labels_are_the_elements_and_bits_in_the_plcs_notation() -> None:
    files = link(FILES + FLOAT_FILE + """
[[link.file]]
file = 9
type = "L"
elements = 2
start = 60

[[link.file]]
file = 13
type = "B"
elements = 1
start = 70
""").file
    labels = target_point_labels(files)
    by_plc = "written by the PLC's MSG"
    by_either = "written by the PLC's MSG or a Modbus client"
    expected: dict[tuple[Table, int], PointLabel] = {}
    for element in range(3):
        for k in range(16):
            expected[(Table.COIL, 100 + 16 * element + k)] = PointLabel(f"B3:{element}/{k}", "bool", by_either)
    for element in range(10):
        expected[(Table.HOLDING, element)] = PointLabel(f"N7:{element}", "int16", by_either)
    for element in range(5):
        expected[(Table.INPUT, 20 + element)] = PointLabel(f"N10:{element}", "int16", by_plc)
    for element in range(2):
        for k in range(16):
            expected[(Table.DISCRETE, 200 + 16 * element + k)] = PointLabel(f"B12:{element}/{k}", "bool", by_plc)
    for element in range(2):  # "F and L take two registers per element", both with the element's label
        for word in range(2):
            expected[(Table.HOLDING, 50 + 2 * element + word)] = PointLabel(f"F8:{element}", "float32", by_either)
            expected[(Table.HOLDING, 60 + 2 * element + word)] = PointLabel(f"L9:{element}", "int32", by_either)
    expected[(Table.HOLDING, 70)] = PointLabel("B13:0", "uint16", by_either)  # a B file on registers: a word
    assert labels == expected


# --- Modbus writes into the table -----------------------------------------------------------------


async def test_a_coil_write_changes_its_bits_and_keeps_the_others_of_the_element() -> None:
    unit = build_target(link())
    plc = Plc(unit)
    plc.write(FileType.BIT, 3, 0, words(0x0000, 0x8001, 0x0000))
    # B3:1/4 on, B3:1/15 off (one FC15 of coils 116-131), B3:2/3 on (another)
    await unit.write_bits(116 + 4, [True] + [False] * 10 + [False])
    await unit.write_bits(116 + 15, [False])
    await unit.write_bits(132 + 3, [True])
    assert plc.read(FileType.BIT, 3, 0, 6) == words(0x0000, 0x0011, 0x0008)
    assert unit.read_bits(Table.COIL, 116, 32) == [k in (0, 4, 16 + 3) for k in range(32)]


async def test_a_coil_write_over_two_elements_is_applied_whole() -> None:
    unit = build_target(link())
    plc = Plc(unit)
    plc.write(FileType.BIT, 3, 0, words(0xFFFF, 0x0000, 0xFFFF))
    # coils 110-121: B3:0/10-15 off, B3:1/0-5 on
    await unit.write_bits(110, [False] * 6 + [True] * 6)
    assert plc.read(FileType.BIT, 3, 0, 6) == words(0x03FF, 0x003F, 0xFFFF)
    assert unit.read_bits(Table.COIL, 100, 48) == [k < 10 or 16 <= k < 22 or k >= 32 for k in range(48)]


async def test_a_coil_of_a_never_written_element_writes_that_bit_only() -> None:
    unit = build_target(link())
    plc = Plc(unit)
    with pytest.raises(ModbusExceptionReply) as excinfo:
        unit.read_bits(Table.COIL, 132, 16)
    assert code_of(excinfo) == GATEWAY_TARGET_FAILED  # nobody wrote B3:2 yet
    await unit.write_bits(132 + 9, [True])
    assert plc.read(FileType.BIT, 3, 2, 2) == words(0x0200)
    assert unit.read_bits(Table.COIL, 132, 16) == [k == 9 for k in range(16)]


async def test_a_register_write_is_what_the_plcs_next_read_gets() -> None:
    unit = build_target(link())
    plc = Plc(unit)
    await unit.write_registers(3, [0x1234, 0xFFFF])
    assert plc.read(FileType.INTEGER, 7, 3, 4) == bytes.fromhex("3412FFFF")
    assert unit.read_registers(Table.HOLDING, 3, 2) == [0x1234, 0xFFFF]


async def test_each_modbus_write_is_audited_with_its_unit_and_elements(caplog: pytest.LogCaptureFixture) -> None:
    unit = build_target(link())
    with caplog.at_level(logging.INFO, logger="gateway.audit"):
        await unit.write_registers(4, [1, 2])
        await unit.write_bits(100 + 16 + 2, [True])
    messages = [r.getMessage() for r in caplog.records if r.name == "gateway.audit"]
    assert len(messages) == 2, messages
    elements = re.compile(r"\b[NB]\d+:\d+\b")
    assert all(re.search(rf"\bunit {UNIT}\b", m) for m in messages), messages
    # a Modbus client's write, told apart from the PLC's own (which the runner audits by its node)
    assert all(re.search(r"\bModbus\b", m) for m in messages), messages
    assert [elements.findall(m) for m in messages] == [["N7:4", "N7:5"], ["B3:1"]]


async def test_writes_are_counted_and_timed() -> None:
    unit = build_target(link())
    await unit.write_registers(0, [5])
    await unit.write_bits(100, [True])
    assert (unit.write_requests, unit.write_failures) == (2, 0)
    # applied at once (no line to wait for): well within write_timeout, the longest a write may take
    assert unit.write_latency.count == 2
    assert 0 <= unit.write_latency.total <= unit.write_timeout


# --- persist ----------------------------------------------------------------------------------------


async def test_a_modbus_write_that_cannot_be_saved_answers_04_and_is_not_kept(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    unit = build_target(link(persist=tmp_path / "line3.db"))
    plc = Plc(unit)
    plc.write(FileType.INTEGER, 7, 0, words(11, 12))
    plc.write(FileType.BIT, 3, 0, words(0x0101))
    assert unit.store_file is not None

    def disk_full(rows: object) -> None:
        raise OSError("No space left on device")

    monkeypatch.setattr(unit.store_file, "save", disk_full)
    for write in (unit.write_registers(0, [99, 98]), unit.write_bits(100 + 1, [True]), unit.write_bits(100, [False])):
        with pytest.raises(ModbusExceptionReply) as excinfo:
            await write
        assert code_of(excinfo) == SERVER_DEVICE_FAILURE
        assert "No space left on device" in str(excinfo.value) and "check the disk" in str(excinfo.value)
    assert (unit.write_requests, unit.write_failures) == (3, 3)
    assert plc.read(FileType.INTEGER, 7, 0, 4) == words(11, 12)
    assert plc.read(FileType.BIT, 3, 0, 2) == words(0x0101)
    assert unit.read_registers(Table.HOLDING, 0, 2) == [11, 12]
    assert unit.read_bits(Table.COIL, 100, 2) == [True, False]
    monkeypatch.undo()
    await unit.write_bits(100 + 1, [True])
    assert plc.read(FileType.BIT, 3, 0, 2) == words(0x0103)
    assert (unit.write_requests, unit.write_failures) == (4, 3)


def test_the_table_comes_back_with_its_values_and_write_times(tmp_path: Path,
                                                             caplog: pytest.LogCaptureFixture) -> None:
    files = link(FILES + FLOAT_FILE).file
    store = TargetStore(tmp_path / "line3.db")
    wall = time.time()
    store.save([
        StoredElement(7, 2, words(0x1234), wall - 30.0),  # written 30 s ago
        StoredElement(7, 9, words(0x0009), wall + 3600.0),  # the clock went back since: written "now"
        StoredElement(7, 10, words(0x000A), wall),  # past N7:9, the last element: N7 got shorter
        StoredElement(7, 11, words(0x000B), wall),
        StoredElement(8, 0, words(0x0000), wall),  # 2 bytes: not an F element (the file was an N file)
        StoredElement(8, 1, bytes.fromhex("0000C03F"), wall - 5.0),  # F8:1 = 1.5
        StoredElement(11, 0, words(0x0001), wall),  # a file not configured any more
        StoredElement(12, 1, words(0x8000), wall - 1.0),
    ])
    now = 1000.0
    with caplog.at_level(logging.WARNING, logger="gateway.df1.target"):
        table = load_table(files, store, now)
    store.close()
    n7, f8, b12 = table[7], table[8], table[12]
    assert [n7.value(e) for e in range(10)] == [None, None, 0x1234] + [None] * 6 + [9]
    assert [f8.value(e) for e in range(2)] == [None, 1.5]
    assert [b12.value(e) for e in range(2)] == [None, 0x8000]
    assert table.get(11) is None
    stamp = n7.written_at(2)
    assert stamp is not None and abs(stamp - (now - 30.0)) < 1.0
    assert n7.written_at(9) == now
    stamp = f8.written_at(1)
    assert stamp is not None and abs(stamp - (now - 5.0)) < 1.0
    left_out = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(left_out) == 4 and all("left out" in m for m in left_out), left_out
    assert [m for m in left_out if "7:10" in m or "7:11" in m or "8:0" in m or "11:0" in m] == left_out


def test_initial_gives_every_element_its_value_before_anyone_writes() -> None:
    files = link("""
[[link.file]]
file = 7
type = "N"
elements = 3
initial = -5

[[link.file]]
file = 8
type = "F"
elements = 2
start = 10
""").file
    table = load_table(files, None, 20.0)
    assert [table[7].value(e) for e in range(3)] == [-5, -5, -5]
    assert [table[7].written_at(e) for e in range(3)] == [20.0, 20.0, 20.0]
    assert [table[8].value(e) for e in range(2)] == [None, None]
