"""An SLC 100/150 link built from its ``[[link]]`` and the writes its image refuses (``gateway.kinds.slc_ascii.unit``).

Expected values from the manual ("Writing Data Words": "Before the data is written, the most
significant bit of the data word being overwritten must be 0 (the device must not be protected)";
"The Memory Map", 40H-7FH: bit 7 of the MSB of a preset is its protect bit) and the Modbus map
reference (docs/reference/modbus-map.md: "a protected preset answers 0x04").
"""

from __future__ import annotations

from typing import Any

import pytest

from gateway.errors import ModbusExceptionReply
from gateway.kinds.slc_ascii.config import SlcAsciiLinkConfig
from gateway.kinds.slc_ascii.unit import SlcAsciiUnit, build_slc_ascii
from gateway.streams import SerialSettings

from .units import unit_with


def link(name: str, unit: int, **keys: Any) -> SlcAsciiLinkConfig:
    return SlcAsciiLinkConfig.model_validate({"name": name, "protocol": "slc-ascii", "unit": unit, **keys})


def test_each_link_gets_its_own_driver_with_its_settings() -> None:
    links = [
        link("press", 3, port="sim://slc150", baudrate=4800, timeout=0.7, retries=4, write_timeout=2.5,
             down_after_failures=7, stale_after=9.0),
        link("oven", 4, port="sim://slc100"),
    ]
    built = build_slc_ascii(links)
    assert [unit.name for unit in built.units] == ["press", "oven"]
    assert [unit.unit_id for unit in built.units] == [3, 4]
    press, oven = built.units
    assert isinstance(press, SlcAsciiUnit) and isinstance(oven, SlcAsciiUnit)
    assert list(built.runners) == [press.driver, oven.driver]
    assert press.driver is not oven.driver
    driver = press.driver
    assert driver.url == "sim://slc150"
    assert driver.name == "press"
    # 4800 baud as configured; 7 data bits, even parity, 1 stop bit: the manual's fixed framing
    assert driver.settings == SerialSettings(baudrate=4800, bytesize=7, parity="E", stopbits=1)
    assert (driver.timeout, driver.retries, driver.write_budget) == (0.7, 4, 2.5)
    assert driver.down_after_failures == 7
    assert press.stale_after == 9.0
    assert oven.driver.url == "sim://slc100"
    assert oven.driver.settings == SerialSettings(baudrate=9600, bytesize=7, parity="E", stopbits=1)


def test_no_links_build_nothing() -> None:
    built = build_slc_ascii([])
    assert list(built.units) == [] and list(built.runners) == []




async def test_a_protected_preset_is_refused_with_0x04_and_nothing_sent() -> None:
    unit = unit_with({0x40: 0x80, 0x41: 100})  # 901.PRE = 100, protected
    with pytest.raises(ModbusExceptionReply) as refused:
        unit.check_register_write(32, [50])
    assert refused.value.code == 0x04
    assert "holding register 32: protected in the controller (protect bit set); nothing written" in str(
        refused.value)


async def test_an_unprotected_word_is_accepted_whatever_its_other_bits() -> None:
    # 902.PRE = 7FFFH: every bit but the protect bit set; 901.ACC = 0100H
    unit = unit_with({0x42: 0x7F, 0x43: 0xFF, 0x00: 0x01})
    assert [(address, value) for address, _, value in unit.check_register_write(33, [1234])] == [(33, 1234)]
    assert [(address, value) for address, _, value in unit.check_register_write(0, [9999])] == [(0, 9999)]
