"""The gateway's Modbus backend: the unit id picks the unit, the function code the table (``FUNCTION_TABLES``)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import pytest

from gateway.errors import ModbusExceptionReply
from gateway.modbus.backend import GatewayBackend
from gateway.modbus.mapping import FUNCTION_TABLES, Table
from gateway.modbus.mbap import BIT_READS, MULTIPLE_WRITES, REGISTER_READS, SINGLE_WRITES, FunctionCode


class RecordingUnit:
    """What the backend calls on a unit, recorded: (method, table or None, address, count or values)."""

    def __init__(self, unit_id: int) -> None:
        self.unit_id = unit_id
        self.calls: list[tuple[str, Table | None, int, Any]] = []

    def read_register_bytes(self, table: Table, address: int, count: int) -> bytes:
        self.calls.append(("read_register_bytes", table, address, count))
        return bytes(2 * count)

    def read_bit_bytes(self, table: Table, address: int, count: int) -> bytes:
        self.calls.append(("read_bit_bytes", table, address, count))
        return bytes((count + 7) // 8)

    def read_registers(self, table: Table, address: int, count: int) -> list[int]:
        self.calls.append(("read_registers", table, address, count))
        return [0] * count

    def read_bits(self, table: Table, address: int, count: int) -> list[bool]:
        self.calls.append(("read_bits", table, address, count))
        return [False] * count

    async def write_registers(self, address: int, values: Sequence[int]) -> None:
        self.calls.append(("write_registers", None, address, list(values)))

    async def write_bits(self, address: int, values: Sequence[bool]) -> None:
        self.calls.append(("write_bits", None, address, list(values)))


def backend(*units: RecordingUnit) -> GatewayBackend:
    return GatewayBackend(units)  # type: ignore[arg-type]  # the unit's methods the backend calls


def test_every_function_code_served_has_its_one_table() -> None:
    assert set(FUNCTION_TABLES) == set(FunctionCode)
    assert {FUNCTION_TABLES[fc] for fc in REGISTER_READS} == {Table.HOLDING, Table.INPUT}
    assert {FUNCTION_TABLES[fc] for fc in BIT_READS} == {Table.COIL, Table.DISCRETE}
    assert all(FUNCTION_TABLES[fc].writable for fc in SINGLE_WRITES | MULTIPLE_WRITES)


@pytest.mark.parametrize("function_code", sorted(REGISTER_READS | BIT_READS))
def test_read_now_reads_the_table_of_the_function_code(function_code: int) -> None:
    unit = RecordingUnit(3)
    data = backend(unit).read_now(3, function_code, 10, 9)
    method = "read_register_bytes" if function_code in REGISTER_READS else "read_bit_bytes"
    assert unit.calls == [(method, FUNCTION_TABLES[function_code], 10, 9)]
    assert len(data) == (18 if function_code in REGISTER_READS else 2)


async def test_the_reads_through_a_task_read_the_same_tables() -> None:
    unit = RecordingUnit(1)
    served = backend(unit)
    await served.read_coils(1, 0, 1)
    await served.read_discrete_inputs(1, 1, 1)
    await served.read_holding_registers(1, 2, 1)
    await served.read_input_registers(1, 3, 1)
    assert unit.calls == [
        ("read_bits", Table.COIL, 0, 1),
        ("read_bits", Table.DISCRETE, 1, 1),
        ("read_registers", Table.HOLDING, 2, 1),
        ("read_registers", Table.INPUT, 3, 1),
    ]


async def test_writes_go_to_the_unit_of_their_unit_id() -> None:
    one, two = RecordingUnit(1), RecordingUnit(2)
    served = backend(one, two)
    await served.write_registers(2, 40, [7, 8])
    await served.write_coils(1, 5, [True])
    assert one.calls == [("write_bits", None, 5, [True])]
    assert two.calls == [("write_registers", None, 40, [7, 8])]


async def test_an_unknown_unit_id_is_answered_0x0A_by_every_call() -> None:
    served = backend(RecordingUnit(1))
    assert served.has_unit(1) and not served.has_unit(2)
    with pytest.raises(ModbusExceptionReply) as caught:
        served.read_now(2, FunctionCode.READ_HOLDING_REGISTERS, 0, 1)
    assert caught.value.code == 0x0A
    for call in (served.read_coils(2, 0, 1), served.read_input_registers(2, 0, 1), served.write_registers(2, 0, [1]),
                 served.write_coils(2, 0, [True])):
        with pytest.raises(ModbusExceptionReply) as caught:
            await call
        assert caught.value.code == 0x0A


def test_units_are_replaced_whole() -> None:
    """A reload gives the backend the new units (``Gateway.apply``): the unit ids are looked up anew."""
    served = backend(RecordingUnit(1))
    new = RecordingUnit(2)
    served.units = {2: new}  # type: ignore[dict-item]
    assert not served.has_unit(1) and served.has_unit(2)
    served.read_now(2, FunctionCode.READ_COILS, 0, 1)
    assert new.calls == [("read_bit_bytes", Table.COIL, 0, 1)]
