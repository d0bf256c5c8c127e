"""Modbus side of the gateway.

``gateway.modbus.server`` is the Modbus TCP server (its parts: ``mbap``, ``handler``, the only
module that imports pymodbus, ``connection`` and ``admission``); ``gateway.modbus.backend`` is the
gateway's backend of it (a unit id to its unit, a function code to its table);
``gateway.modbus.mapping`` maps Modbus addresses to controller addresses. Import them directly:
this package re-exports nothing, so that the pure mapping does not pull in pymodbus.
"""
