"""``slc-gateway export-tags``: every mapped point as a tag, checked against the map and a running gateway."""

from __future__ import annotations

import asyncio
import csv
import dataclasses
import io
import json
from pathlib import Path
from typing import Any

import pytest
from pymodbus.client import AsyncModbusTcpClient

from gateway.app import Gateway
from gateway.config import load_config, parse_config
from gateway.errors import GatewayError
from gateway.kinds import link_kind
from gateway.modbus.mapping import STATUS_BASE, Plan, Table
from gateway.tags import (
    CSV_HEADER,
    KEPWARE_HEADER,
    Tag,
    config_tags,
    kepware_devices,
    kepware_name,
    kepware_rows,
    link_tags,
    reference,
    render,
)
from tests.cli_support import cli, fails, ok
from tests.e2e.modbus_support import connect, exception_code

ROOT = Path(__file__).resolve().parent.parent
DEMO = ROOT / "config" / "demo.toml"

#: every table and data type of both kinds: an SLC 100/150, an SLC 5/04 with both float word
#: orders, int16 / uint16, bit files, structure members and bits, I/O, and a PLC-5
MAPS = """
[modbus]
listen = "127.0.0.1:0"

[[link]]
name = "press-1"
protocol = "slc-ascii"
port = "sim://slc150"
unit = 1
writable = ["holding:32-40", "coil:701-710"]

[[link]]
name = "press-3"
protocol = "df1"
port = "sim://slc504"
unit = 3

[[link.map]]
table = "holding"
start = 0
address = "N7:0"
count = 20

[[link.map]]
table = "holding"
start = 20
address = "N7:20"
count = 4
type = "uint16"

[[link.map]]
table = "holding"
start = 100
address = "T4:0.ACC"
count = 3

[[link.map]]
table = "holding"
start = 200
address = "F8:0"
count = 3
type = "float32"

[[link.map]]
table = "input"
start = 300
address = "F8:3"
count = 2
type = "float32"
word_order = "low-first"

[[link.map]]
table = "input"
start = 0
address = "I:1.0"
count = 2
scan = "slow"

[[link.map]]
table = "coil"
start = 0
address = "B3:0/0"
count = 20

[[link.map]]
table = "discrete"
start = 0
address = "T4:0/DN"
count = 3

[[link]]
name = "line-5"
protocol = "df1"
port = "sim://plc5"
unit = 5
processor = "plc5"
read_only = true

[[link.map]]
table = "holding"
start = 0
address = "N7:0"
count = 4

[[link.map]]
table = "holding"
start = 10
address = "F8:0"
count = 2
type = "float32"
word_order = "low-first"

[[link.map]]
table = "coil"
start = 0
address = "B3/0"
count = 18

[[link.map]]
table = "discrete"
start = 0
address = "T4:0/DN"
count = 2
"""


@pytest.fixture(scope="module")
def config_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("tags") / "maps.toml"
    path.write_text(MAPS, encoding="utf-8")
    return path


def test_every_point_of_every_plan_is_one_tag_of_its_width() -> None:
    """Walk the plans (what check-config prints and the units serve): every mapped address is in
    exactly one tag, a 32-bit tag covers two registers, and nothing else is listed."""
    config = parse_config(MAPS)
    for link in config.link:
        plan = link_kind(link.protocol).plan_of(link)
        tags = link_tags(link)
        covered: dict[tuple[Table, int], str] = {}
        for tag in tags:
            width = tag.width if tag.table in (Table.HOLDING, Table.INPUT) else 1
            for address in range(tag.address, tag.address + width):
                assert (tag.table, address) not in covered, (tag, covered.get((tag.table, address)))
                covered[tag.table, address] = tag.name
        mapped = {(table, a) for table in Table for a, _ in _points(plan, table)}
        status = {(Table.INPUT, a) for a in range(STATUS_BASE, STATUS_BASE + 12)}
        assert set(covered) == mapped | status, link.name
        assert len({tag.name for tag in tags}) == len(tags), "tag names are unique within a link"


def _points(plan: Plan[Any, Any], table: Table) -> list[tuple[int, object]]:
    points = plan.registers(table) if table in (Table.HOLDING, Table.INPUT) else plan.bits(table)
    return sorted(points.items())


def by_name(link_name: str) -> dict[str, tuple[str, str, int, str, str]]:
    config = parse_config(MAPS)
    link = next(link for link in config.link if link.name == link_name)
    return {tag.name: (tag.table.value, tag.type_text, tag.address, tag.access, tag.reference)
            for tag in link_tags(link)}


def test_slc_ascii_tags_name_the_controller_items() -> None:
    tags = by_name("press-1")
    assert tags["press-1/901.ACC"] == ("holding", "uint16", 0, "read", "400001")  # not in writable
    assert tags["press-1/901.PRE"] == ("holding", "uint16", 32, "read-write", "400033")
    assert tags["press-1/910.PRE"] == ("holding", "uint16", 41, "read", "400042")  # past holding:32-40
    assert tags["press-1/932.STEP"] == ("input", "uint16", 31, "read", "300032")
    assert tags["press-1/@0x84"] == ("input", "uint16", 66, "read", "300067")
    assert tags["press-1/@0x102"] == ("input", "uint16", 129, "read", "300130")
    assert tags["press-1/701"] == ("coil", "bool", 701, "read-write", "000702")
    assert tags["press-1/711"] == ("coil", "bool", 711, "read", "000712")  # past coil:701-710
    assert tags["press-1/868"] == ("coil", "bool", 868, "read", "000869")  # a relay the protocol cannot write
    assert tags["press-1/701@discrete"] == ("discrete", "bool", 701, "read", "100702")
    assert tags["press-1/11"] == ("discrete", "bool", 11, "read", "100012")
    assert tags["press-1/951"] == ("discrete", "bool", 951, "read", "100952")
    assert tags["press-1/status.link_up"] == ("input", "uint16", 1000, "read", "301001")
    assert tags["press-1/status.transactions"] == ("input", "uint32 high-first", 1003, "read", "301004")
    assert tags["press-1/status.id_resyncs"] == ("input", "uint32 high-first", 1009, "read", "301010")


def test_df1_tags_carry_type_and_word_order() -> None:
    tags = by_name("press-3")
    assert tags["press-3/N7:0"] == ("holding", "int16", 0, "read-write", "400001")
    assert tags["press-3/N7:20"] == ("holding", "uint16", 20, "read-write", "400021")
    assert tags["press-3/T4:2.ACC"] == ("holding", "int16", 102, "read-write", "400103")
    assert tags["press-3/F8:0"] == ("holding", "float32 high-first", 200, "read-write", "400201")
    assert tags["press-3/F8:2"] == ("holding", "float32 high-first", 204, "read-write", "400205")
    assert tags["press-3/F8:3"] == ("input", "float32 low-first", 300, "read", "300301")
    assert tags["press-3/F8:4"] == ("input", "float32 low-first", 302, "read", "300303")
    assert tags["press-3/I:1.1"] == ("input", "int16", 1, "read", "300002")
    assert tags["press-3/B3:0/15"] == ("coil", "bool", 15, "read-write", "000016")
    assert tags["press-3/B3:1/3"] == ("coil", "bool", 19, "read-write", "000020")
    assert tags["press-3/T4:2/DN"] == ("discrete", "bool", 2, "read", "100003")
    assert not any(name.endswith(("F8:0@holding",)) for name in tags)


def test_plc5_tags_and_read_only() -> None:
    tags = by_name("line-5")
    assert tags["line-5/N7:3"] == ("holding", "int16", 3, "read", "400004")  # read_only = true
    assert tags["line-5/F8:1"] == ("holding", "float32 low-first", 12, "read", "400013")
    assert {name for name in tags if name.startswith("line-5/B3:")} >= {"line-5/B3:0/0", "line-5/B3:1/1"}
    assert len([name for name in tags if name.startswith("line-5/B3:")]) == 18
    assert all(access == "read" for _, _, _, access, _ in tags.values())


def test_reference_notation() -> None:
    assert reference(Table.HOLDING, 0) == "400001"
    assert reference(Table.HOLDING, 65535) == "465536"
    assert reference(Table.INPUT, 1000) == "301001"
    assert reference(Table.COIL, 0) == "000001"
    assert reference(Table.DISCRETE, 9) == "100010"


def test_csv_parses_and_matches_the_tags(config_file: Path) -> None:
    text = ok("export-tags", str(config_file))
    rows = list(csv.reader(io.StringIO(text)))
    assert tuple(rows[0]) == CSV_HEADER == ("name", "unit", "table", "address", "reference", "type", "access",
                                            "description")
    tags = config_tags(load_config(config_file).link)
    assert len(rows) - 1 == len(tags)
    for row, tag in zip(rows[1:], tags, strict=True):
        name, unit, table, address, ref, type_text, access, description = row
        assert (name, int(unit), table, int(address), type_text, access, description) == (
            tag.name, tag.unit, tag.table.value, tag.address, tag.type_text, tag.access, tag.description)
        assert ref == reference(Table(table), int(address))
    assert {row[2] for row in rows[1:]} == {"holding", "input", "coil", "discrete"}
    assert {row[5] for row in rows[1:]} == {"uint16", "int16", "bool", "float32 high-first", "float32 low-first",
                                            "uint32 high-first"}


def test_json_and_kepware_formats(config_file: Path, tmp_path: Path) -> None:
    document = json.loads(ok("export-tags", str(config_file), "--format", "json"))
    floats = [tag for tag in document if tag["type"] == "float32"]
    assert {tag["word_order"] for tag in floats} == {"high-first", "low-first"}
    assert all(tag["registers"] == 2 for tag in floats)
    out = tmp_path / "unit3.csv"
    result = cli("export-tags", str(config_file), "--format", "kepware", "--unit", "3", "-o", str(out))
    assert result.returncode == 0 and result.stdout == "", result.stderr
    assert f"written to {out}" in result.stderr
    rows = list(csv.reader(io.StringIO(out.read_text(encoding="utf-8"))))
    assert tuple(rows[0]) == KEPWARE_HEADER
    kepware = {row[0]: row for row in rows[1:]}
    assert len(kepware) == len(rows) - 1  # unique names
    assert kepware["press_3.N7_0"][1:5] == ["400001", "Short", "1", "RW"]
    assert kepware["press_3.N7_20"][1:3] == ["400021", "Word"]
    assert kepware["press_3.F8_3"][1:5] == ["300301", "Float", "1", "RO"]
    assert "low-first" in kepware["press_3.F8_3"][-1]
    assert kepware["press_3.B3_0_15"][1:3] == ["000016", "Boolean"]
    assert kepware["press_3.status_transactions"][1:3] == ["301004", "DWord"]
    assert all(name.startswith("press_3.") for name in kepware)  # --unit 3 only


def test_config_errors_exit_non_zero_with_one_line(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text('[[link]]\nname = "a"\nprotocol = "slc-ascii"\nport = "sim://slc150"\nunit = 1\ntimout = 1\n')
    line = fails("export-tags", str(bad))
    assert line.startswith("slc-gateway export-tags: ") and "timout" in line and "bad.toml:6" in line
    assert fails("check-config", str(bad)).replace("check-config", "export-tags") == line
    assert "no such file" in fails("export-tags", str(tmp_path / "missing.toml")).lower()
    assert "--unit 9" in fails("export-tags", str(DEMO), "--unit", "9")


async def test_every_reference_resolves_on_the_running_demo() -> None:
    """Every tag of the demo, read with Modbus from the demo gateway: a value, no exception."""
    config = load_config(DEMO)
    config = config.model_copy(update={
        "modbus": config.modbus.model_copy(update={"listen": "127.0.0.1:0"}), "metrics": None})
    rows = list(csv.DictReader(io.StringIO(render(config_tags(config.link), "csv"))))
    async with Gateway(config) as gateway, connect(gateway.port) as client:
        for unit in gateway.units:  # every link's first full scan (the slow class is read first)
            await _wait_fresh(client, unit.unit_id)
        failed = []
        for row in rows:
            unit, table, address = int(row["unit"]), row["table"], int(row["address"])
            count = 2 if row["type"].startswith(("float32", "uint32")) else 1
            read = {"holding": client.read_holding_registers, "input": client.read_input_registers,
                    "coil": client.read_coils, "discrete": client.read_discrete_inputs}[table]
            assert row["reference"] == reference(Table(table), address)
            reply = await read(address, count=count, device_id=unit)
            if exception_code(reply) is not None:
                failed.append((row["name"], exception_code(reply)))
        assert not failed, failed[:20]
    assert len(rows) > 1000


async def _wait_fresh(client: AsyncModbusTcpClient, unit: int) -> None:
    for _ in range(300):  # the paced demo simulators: a few seconds for the first scans
        status = await client.read_input_registers(STATUS_BASE, count=2, device_id=unit)
        # up, and the oldest fast value younger than stale_after (5 s)
        if not status.isError() and status.registers[0] == 1 and status.registers[1] < 50:
            return
        await asyncio.sleep(0.1)
    raise AssertionError(f"unit {unit}: no fresh data after 30 s")


# --- Kepware: one device per unit ---------------------------------------------------------------
#
# Kepware's CSV import ("CSV Import/Export", kepware.com/Products/feature-csvimportexport.htm) takes
# a heading record with the columns below and one record per tag, imported under the one device
# selected; its Modbus Ethernet driver addresses are six digits (000001 coils, 100001 discrete
# inputs, 300001 input registers, 400001 holding registers), its data types Boolean, Word, Short,
# DWord, Long, Float, Respect Data Type 1 / 0, Client Access RO / RW / WO.  A device reads every
# 32-bit value in one word order, its "First word low" setting (on by default).
KEPWARE_COLUMNS = ("Tag Name", "Address", "Data Type", "Respect Data Type", "Client Access", "Scan Rate",
                   "Scaling", "Raw Low", "Raw High", "Scaled Low", "Scaled High", "Scaled Data Type", "Clamp Low",
                   "Clamp High", "Eng Units", "Description")


def kepware_file(path: Path) -> list[dict[str, str]]:
    """The records of a Kepware tag CSV, checked against the documented columns and values."""
    text = path.read_bytes().decode("utf-8")
    rows = list(csv.reader(io.StringIO(text)))
    assert tuple(rows[0]) == KEPWARE_COLUMNS
    records = [dict(zip(KEPWARE_COLUMNS, row, strict=True)) for row in rows[1:]]
    for record in records:
        assert record["Address"][0] in "0134" and len(record["Address"]) == 6 and record["Address"].isdigit()
        assert record["Data Type"] in ("Boolean", "Word", "Short", "DWord", "Long", "Float")
        assert record["Respect Data Type"] in ("0", "1") and record["Client Access"] in ("RO", "RW", "WO")
        assert (record["Data Type"] == "Boolean") == (record["Address"][0] in "01")
    names = [record["Tag Name"] for record in records]
    assert len(set(names)) == len(names)
    return records


def test_kepware_without_unit_refuses_one_mixed_file(tmp_path: Path) -> None:
    line = fails("export-tags", str(DEMO), "--format", "kepware")
    assert "units 1, 2, 3, 4" in line and "--unit N" in line and "-o DIR" in line
    file = tmp_path / "all.csv"
    file.write_text("")
    assert "not the file" in fails("export-tags", str(DEMO), "--format", "kepware", "-o", str(file))


def test_kepware_one_file_per_unit_with_its_word_order(tmp_path: Path) -> None:
    out = tmp_path / "kepware"
    result = cli("export-tags", str(DEMO), "--format", "kepware", "-o", str(out))
    assert result.returncode == 0, result.stderr
    assert sorted(path.name for path in out.iterdir()) == ["unit-1.csv", "unit-2.csv", "unit-3.csv", "unit-4.csv"]
    links = {1: "slc150_sim", 2: "slc100_sim", 3: "slc504_sim", 4: "plc_msg_sim"}
    for unit, link in links.items():
        records = kepware_file(out / f"unit-{unit}.csv")
        addresses = [record["Address"] for record in records]
        assert len(set(addresses)) == len(addresses), f"unit {unit}: an address twice in one device"
        assert {record["Tag Name"].split(".")[0] for record in records} == {link}
        # the demo's floats and the status block are high-first: the device's setting says so
        assert f"unit {unit} ({link.replace('_', '-')}): a Kepware Modbus device with ID {unit} and " \
               "'First word low' off" in result.stderr
        wide = [record for record in records if record["Data Type"] in ("Float", "DWord")]
        assert wide and all("'First word low' off" in record["Description"] for record in wide)
    assert "warning" not in result.stderr


def test_kepware_warns_of_a_unit_whose_32_bit_values_mix_word_orders(config_file: Path, tmp_path: Path) -> None:
    out = tmp_path / "kepware"
    result = cli("export-tags", str(config_file), "--format", "kepware", "-o", str(out))
    assert result.returncode == 0, result.stderr
    warnings = [line for line in result.stderr.splitlines() if "warning" in line]
    # unit 3: three high-first floats (F8:0-2) and the status block against two low-first ones
    (unit3,) = [line for line in warnings if "unit 3:" in line]
    assert "'First word low' off" in unit3 and "press_3.F8_3, press_3.F8_4" in unit3 and "F8_0" not in unit3
    # unit 5: its one float is low-first (the device's order), so the status block's counters read wrong
    (unit5,) = [line for line in warnings if "unit 5:" in line]
    assert "'First word low' on" in unit5
    assert "line_5.status_transactions" in unit5 and "line_5.F8_0" not in unit5
    assert not any("unit 1:" in line for line in warnings)  # no 32-bit value but the status block
    records = {record["Tag Name"]: record for record in kepware_file(out / "unit-3.csv")}
    assert "reads wrong" in records["press_3.F8_3"]["Description"]
    assert "reads wrong" not in records["press_3.F8_0"]["Description"]


# --- the type and access of 32-bit values (issue 42) ------------------------------------------------

TARGET_LONGS = """
[[link]]
name = "plc"
protocol = "df1"
role = "target"
port = "socket://127.0.0.1:9"
station = 1
unit = 7

[[link.file]]
file = 9
type = "L"
elements = 2
start = 60
"""


def test_a_signed_32_bit_value_is_a_kepware_long_and_an_unsigned_one_a_dword() -> None:
    """Kepware's Long is signed, DWord unsigned: an L element as DWord reads -1 as 4294967295."""
    (target,) = parse_config(TARGET_LONGS).link
    tags = link_tags(target)
    rows = {row[0]: row for row in kepware_rows(tags)}
    assert [tag.type for tag in tags if tag.name.startswith("plc/L9:")] == ["int32", "int32"]
    assert rows["plc.L9_0"][1:3] == ("400061", "Long")
    assert rows["plc.L9_1"][1:3] == ("400063", "Long")
    assert rows["plc.status_transactions"][1:3] == ("301004", "DWord")  # a counter: unsigned


FLOATS_WRITABLE = """
[[link]]
name = "oven"
protocol = "df1"
port = "sim://slc504"
unit = 3
writable = ["holding:{first}-{last}"]

[[link.map]]
table = "holding"
start = 200
address = "F8:0"
count = 3
type = "float32"
"""


@pytest.mark.parametrize(("first", "last", "access"), [
    (200, 205, ["read-write", "read-write", "read-write"]),
    (200, 202, ["read-write", "read", "read"]),  # F8:1 is 202-203: its second half is outside
    (201, 205, ["read", "read-write", "read-write"]),  # F8:0 is 200-201: its first half is outside
    (201, 202, ["read", "read", "read"]),  # one half of F8:0 and one of F8:1: neither whole
])
def test_a_32_bit_value_is_read_write_only_when_writable_holds_both_its_registers(
        first: int, last: int, access: list[str]) -> None:
    """A write of one half of a float is refused (one range must hold the whole write), so a tag with
    a half outside ``writable`` is read-only in every format: SCADA must not offer a write that always fails."""
    (oven,) = parse_config(FLOATS_WRITABLE.format(first=first, last=last)).link
    tags = {tag.name: tag for tag in link_tags(oven)}
    assert [tags[f"oven/F8:{n}"].access for n in range(3)] == access
    kepware = {row[0]: row[4] for row in kepware_rows(list(tags.values()))}
    assert [kepware[f"oven.F8_{n}"] for n in range(3)] == ["RW" if a == "read-write" else "RO" for a in access]


# --- the formats, in process (the CLI tests above run them in a subprocess) -------------------------


def _maps_tags() -> list[Tag]:
    return config_tags(parse_config(MAPS).link)


def test_the_csv_format_is_one_row_per_tag_under_its_header() -> None:
    tags = _maps_tags()
    text = render(tags, "csv")
    assert text.endswith("\n") and "\r" not in text  # one line a row, Unix line ends
    rows = list(csv.reader(io.StringIO(text)))
    assert tuple(rows[0]) == ("name", "unit", "table", "address", "reference", "type", "access", "description")
    assert len(rows) == len(tags) + 1
    by_name = {row[0]: row[1:7] for row in rows[1:]}
    assert by_name["press-3/F8:0"] == ["3", "holding", "200", "400201", "float32 high-first", "read-write"]
    assert by_name["press-3/N7:0"] == ["3", "holding", "0", "400001", "int16", "read-write"]
    assert by_name["press-1/701@discrete"] == ["1", "discrete", "701", "100702", "bool", "read"]
    assert by_name["line-5/status.transactions"] == ["5", "input", "1003", "301004", "uint32 high-first", "read"]
    assert rows[1][7] == tags[0].description != ""


def test_the_json_format_is_a_list_of_objects_one_per_tag() -> None:
    tags = _maps_tags()
    text = render(tags, "json")
    assert text.endswith("]\n")
    document = json.loads(text)
    assert len(document) == len(tags)
    by_name = {item["name"]: item for item in document}
    assert by_name["press-3/F8:0"] == {
        "name": "press-3/F8:0", "link": "press-3", "unit": 3, "table": "holding", "address": 200,
        "reference": "400201", "type": "float32", "word_order": "high-first", "registers": 2,
        "access": "read-write", "description": "map entry F8:0 x3, float32, fast scan"}
    n7 = by_name["press-3/N7:0"]
    assert (n7["type"], n7["word_order"], n7["registers"], n7["access"]) == ("int16", None, 1, "read-write")
    bit = by_name["press-3/T4:2/DN"]
    assert (bit["table"], bit["type"], bit["word_order"], bit["registers"], bit["access"]) == (
        "discrete", "bool", None, None, "read")


def test_the_kepware_format_is_one_unit_in_the_documented_columns() -> None:
    unit3 = [tag for tag in _maps_tags() if tag.unit == 3]
    text = render(unit3, "kepware")
    lines = text.split("\r\n")  # CRLF records, as the Windows tool writes them
    assert lines[-1] == "" and len(lines) == len(unit3) + 2
    rows = list(csv.reader(io.StringIO(text)))
    assert tuple(rows[0]) == KEPWARE_COLUMNS
    records = {row[0]: dict(zip(KEPWARE_COLUMNS, row, strict=True)) for row in rows[1:]}
    f80 = records["press_3.F8_0"]
    assert [f80[c] for c in ("Address", "Data Type", "Respect Data Type", "Client Access")] == [
        "400201", "Float", "1", "RW"]
    # every column but these is blank: the server's default
    given = {"Tag Name", "Address", "Data Type", "Respect Data Type", "Client Access", "Description"}
    assert all(value == "" for record in records.values() for column, value in record.items() if column not in given)
    with pytest.raises(GatewayError) as refused:
        render(_maps_tags(), "kepware")
    assert "units 1, 3, 5" in str(refused.value)
    with pytest.raises(GatewayError):  # two units are two devices too
        render([tag for tag in _maps_tags() if tag.unit in (1, 3)], "kepware")


def test_kepware_rows_say_each_32_bit_values_word_order_against_the_devices() -> None:
    """Unit 3 has three high-first floats and two low-first ones: the device is high-first
    ('First word low' off), and the low-first ones say that they read wrong."""
    rows = {row[0]: row for row in kepware_rows([tag for tag in _maps_tags() if tag.unit == 3])}
    assert rows["press_3.F8_0"][-1] == "map entry F8:0 x3, float32, fast scan (high-first words: 'First word low' off)"
    assert rows["press_3.F8_3"][-1] == ("map entry F8:3 x2, float32, fast scan (low-first words: reads wrong "
                                        "with 'First word low' off)")
    assert rows["press_3.N7_0"][-1] == "map entry N7:0 x20, int16, fast scan"  # 16 bits: no word order
    assert rows["press_3.status_transactions"][-1].endswith("(high-first words: 'First word low' off)")
    assert rows["press_3.status_transactions"][2] == "DWord" and rows["press_3.N7_20"][2] == "Word"
    assert rows["press_3.N7_0"][4] == "RW" and rows["press_3.T4_2_DN"][4] == "RO"


def _tag(name: str, address: int, word_order: str = "", *, unit: int = 1, link: str = "a",
         table: Table = Table.HOLDING, type_: str = "float32") -> Tag:
    return Tag(f"{link}/{name}", link, unit, table, address, type_ if word_order else "int16", word_order, False, "d")


def test_a_kepware_name_has_only_letters_digits_and_underscores() -> None:
    assert kepware_name(_tag("N7:10", 0, link="press-1")) == "press_1.N7_10"
    assert kepware_name(_tag("B3:0/15", 0, link="l")) == "l.B3_0_15"
    assert kepware_name(_tag("::x::", 0, link="--")) == "tag.x"  # underscores at the ends dropped
    assert kepware_name(_tag(":", 0, link="a")) == "a.tag"  # nothing left: "tag"
    assert kepware_name(_tag("X1X", 0, link="XaX")) == "XaX.X1X"  # only underscores are stripped


def test_the_same_kepware_name_twice_gets_its_table() -> None:
    """A controller bit served as a coil and as a discrete input: one name each."""
    tags = [_tag("B3:0/1", 1, table=Table.COIL), _tag("B3:0/1", 1, table=Table.DISCRETE)]
    assert [row[0] for row in kepware_rows(tags)] == ["a.B3_0_1", "a.B3_0_1_discrete"]


def test_a_type_kepware_has_no_name_for_is_a_word() -> None:
    (row,) = kepware_rows([_tag("x", 0, "high-first", type_="int64")])
    assert row[2] == "Word"


def test_a_kepware_devices_word_order_is_most_of_its_own_32_bit_values() -> None:
    high = [_tag(f"H{k}", 10 + 2 * k, "high-first") for k in range(3)]
    low = [_tag(f"L{k}", 50 + 2 * k, "low-first") for k in range(2)]
    status = [_tag(f"status.{k}", STATUS_BASE + 3 + 2 * k, "high-first", table=Table.INPUT) for k in range(4)]
    (device,) = kepware_devices(high + low)
    assert (device.word_order, device.setting, device.misread) == ("high-first", "'First word low' off", tuple(low))
    # the status block's counters (high-first) do not count while the unit has 32-bit values of its own
    (device,) = kepware_devices(low + status)
    assert (device.word_order, device.setting) == ("low-first", "'First word low' on")
    assert device.misread == tuple(status)
    (device,) = kepware_devices(high[:2] + low + status)  # a tie: Kepware's default, first word low
    assert device.word_order == "low-first" and device.misread == tuple(high[:2] + status)
    (device,) = kepware_devices([_tag("n", 0), *status])  # none of its own: the status block decides
    assert device.word_order == "high-first" and device.misread == ()
    (device,) = kepware_devices([_tag("n", 0)])  # no 32-bit value at all: the default
    assert device.word_order == "low-first" and device.misread == () and device.warning() == ""


def test_the_status_block_is_the_input_registers_from_1000() -> None:
    own_low = _tag("L", 0, "low-first")
    own_high = _tag("H", 2, "high-first")
    at_base = _tag("status.x", STATUS_BASE, "high-first", table=Table.INPUT)
    below = _tag("I", STATUS_BASE - 2, "high-first", table=Table.INPUT)
    holding = _tag("N", STATUS_BASE, "high-first", table=Table.HOLDING)
    # input 1000 is the status block's: one own value each way is a tie (low-first)
    assert kepware_devices([own_low, own_high, at_base])[0].word_order == "low-first"
    # input 998 and holding 1000 are the unit's own: two high-first against one low-first
    assert kepware_devices([own_low, own_high, below])[0].word_order == "high-first"
    assert kepware_devices([own_low, own_high, holding])[0].word_order == "high-first"


def test_kepware_devices_are_the_units_in_order_with_their_links() -> None:
    tags = [_tag("a", 0, unit=4, link="x"), _tag("b", 0, unit=2, link="y"), _tag("c", 1, unit=4, link="z"),
            _tag("d", 2, unit=4, link="x")]
    devices = kepware_devices(tags)
    assert [(d.unit, d.links, len(d.tags)) for d in devices] == [(4, ("x", "z"), 3), (2, ("y",), 1)]


def test_the_word_order_warning_names_twelve_values_and_counts_the_rest() -> None:
    high = [_tag(f"H{k}", 2 * k, "high-first") for k in range(15)]
    low = [_tag(f"L{k}", 100 + 2 * k, "low-first") for k in range(14)]
    (device,) = kepware_devices(high + low)
    warning = device.warning()
    assert warning.startswith("unit 1: 32-bit values in both word orders")
    assert "this one is high-first ('First word low' off), so these 14 low-first values read wrong: " in warning
    assert ", ".join(f"a.L{k}" for k in range(12)) + " and 2 more;" in warning
    assert "a.L12" not in warning
    (device,) = kepware_devices(high[:13] + low[:12])  # exactly twelve: every one named, no "more"
    assert "and 0 more" not in device.warning() and "a.L11;" in device.warning()
    (device,) = kepware_devices(high[:2] + low[:3])
    warning = device.warning()
    assert ("this one is low-first ('First word low' on), so these 2 high-first values read wrong: a.H0, a.H1;"
            in warning)
    assert "more" not in warning


def test_tags_of_one_unit_are_its_links_only() -> None:
    links = parse_config(MAPS).link
    assert {tag.link for tag in config_tags(links, unit=3)} == {"press-3"}
    assert {tag.link for tag in config_tags(links)} == {"press-1", "press-3", "line-5"}


def test_a_point_its_kind_does_not_label_is_named_by_table_and_address(monkeypatch: pytest.MonkeyPatch) -> None:
    """A kind without labels: a point is ``<table>:<address>``, a bit ``bool``, a 32-bit value ``uint32``,
    a register ``uint16``."""
    (link,) = [link for link in parse_config(MAPS).link if link.name == "press-3"]
    unlabelled = dataclasses.replace(link_kind(link.protocol), point_labels=None)
    monkeypatch.setattr("gateway.tags.link_kind", lambda protocol: unlabelled)
    tags = {tag.name: (tag.type_text, tag.access) for tag in link_tags(link)}
    assert tags["press-3/holding:0"] == ("uint16", "read-write")
    assert tags["press-3/holding:200"] == ("uint32 high-first", "read-write")  # F8:0, a float, unlabelled
    assert tags["press-3/coil:15"] == ("bool", "read-write")
    assert tags["press-3/discrete:2"] == ("bool", "read")
    assert tags["press-3/status.link_up"] == ("uint16", "read")
