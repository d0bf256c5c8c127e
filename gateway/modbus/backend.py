"""The gateway's Modbus backend: a request's unit id picks the unit, its function code the table.

The request side of the server (:mod:`gateway.modbus.handler`) checks a request and calls a
:class:`~gateway.modbus.handler.ModbusBackend`; :class:`GatewayBackend` is the gateway's, over its
units (``gateway.unit``).  Reads are slices of the unit's images: ``read_now`` serves FC1-FC4 at
once, inside the connection's ``data_received`` (the fast path).  Writes go to the unit's write side
(``gateway.unit_writes``), which answers once the controller has confirmed them.  The table of each
function code is :data:`~gateway.modbus.mapping.FUNCTION_TABLES`, stated there once.  An unknown unit
id is answered 0x0A (gateway path unavailable).

``app.py`` builds one backend for its Modbus listeners and gives it the units of every line
(``units``, replaced whole on a reload).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from gateway.errors import ModbusExceptionReply
from gateway.modbus.mapping import FUNCTION_TABLES
from gateway.modbus.mbap import GATEWAY_PATH_UNAVAILABLE, REGISTER_READS, FunctionCode
from gateway.unit import Unit

__all__ = ["GatewayBackend"]


class GatewayBackend:
    """The Modbus server's backend: dispatch by unit id (module docstring)."""

    def __init__(self, units: Sequence[Unit[Any, Any]]) -> None:
        self.units = {unit.unit_id: unit for unit in units}

    def has_unit(self, unit: int) -> bool:
        return unit in self.units

    def _unit(self, unit: int) -> Unit[Any, Any]:
        try:
            return self.units[unit]
        except KeyError:
            raise ModbusExceptionReply(GATEWAY_PATH_UNAVAILABLE) from None

    def read_now(self, unit: int, function_code: int, address: int, count: int) -> bytes:
        """FC1-FC4 from the unit's images: the reply's data bytes (the server's fast path)."""
        target = self.units.get(unit)
        if target is None:
            raise ModbusExceptionReply(GATEWAY_PATH_UNAVAILABLE)
        if function_code in REGISTER_READS:
            return target.read_register_bytes(FUNCTION_TABLES[function_code], address, count)
        return target.read_bit_bytes(FUNCTION_TABLES[function_code], address, count)

    async def read_coils(self, unit: int, address: int, count: int) -> Sequence[bool]:
        return self._unit(unit).read_bits(FUNCTION_TABLES[FunctionCode.READ_COILS], address, count)

    async def read_discrete_inputs(self, unit: int, address: int, count: int) -> Sequence[bool]:
        return self._unit(unit).read_bits(FUNCTION_TABLES[FunctionCode.READ_DISCRETE_INPUTS], address, count)

    async def read_holding_registers(self, unit: int, address: int, count: int) -> Sequence[int]:
        return self._unit(unit).read_registers(FUNCTION_TABLES[FunctionCode.READ_HOLDING_REGISTERS], address, count)

    async def read_input_registers(self, unit: int, address: int, count: int) -> Sequence[int]:
        return self._unit(unit).read_registers(FUNCTION_TABLES[FunctionCode.READ_INPUT_REGISTERS], address, count)

    async def write_coils(self, unit: int, address: int, values: Sequence[bool]) -> None:
        """FC5 and FC15: coils (``FUNCTION_TABLES``), the unit's ``write_bits``."""
        await self._unit(unit).write_bits(address, values)

    async def write_registers(self, unit: int, address: int, values: Sequence[int]) -> None:
        """FC6 and FC16: holding registers (``FUNCTION_TABLES``), the unit's ``write_registers``."""
        await self._unit(unit).write_registers(address, values)
