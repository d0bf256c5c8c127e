"""PLC-5 requests: word range read / write and the read-modify-write coil write, byte for byte.

Layouts: 1770-KF2 p. 5-57 (word range), p. 5-48 and 1770-6.5.16 p. 7-20 (read-modify-write);
addresses 1770-6.5.16 p. 13-12 (N7:30 = 07 00 07 1E, T4:2.ACC = 0F 00 04 02 02).
"""

from __future__ import annotations

import pytest

from gateway.protocols.df1.pccc import encode_command
from gateway.protocols.df1.plc5_address import AddressError
from gateway.protocols.df1.plc5_commands import plc5_bit_write, plc5_read, plc5_write


def test_word_range_read_n7_30() -> None:
    packet = encode_command(plc5_read("N7:30"), dst=1, src=0, tns=0x1234)
    assert packet == bytes.fromhex("01 00 0F 00 34 12 01 00 00 01 00 07 00 07 1E 02")


def test_word_range_read_sizes_follow_the_address() -> None:
    assert plc5_read("F8:2").encode_params() == bytes.fromhex("00 00 02 00 07 00 08 02 04")
    assert plc5_read("T4:2").encode_params() == bytes.fromhex("00 00 03 00 07 00 04 02 06")
    assert plc5_read("T4:2.ACC").encode_params() == bytes.fromhex("00 00 01 00 0F 00 04 02 02 02")
    assert plc5_read("N7:0", 10).encode_params() == bytes.fromhex("00 00 0A 00 07 00 07 00 14")


def test_word_range_write_t4_2_acc() -> None:
    assert plc5_write("T4:2.ACC", b"\x07\x00").encode_params() == bytes.fromhex("00 00 01 00 0F 00 04 02 02 07 00")


def test_coil_writes_are_read_modify_write() -> None:
    """Set: AND FFFF OR 1<<b; reset: AND ~(1<<b) OR 0000 (p. 7-20)."""
    assert plc5_bit_write("B3/5", True).encode_params() == bytes.fromhex("07 00 03 00 FF FF 20 00")
    assert plc5_bit_write("B3/21", False).encode_params() == bytes.fromhex("07 00 03 01 DF FF 00 00")
    assert plc5_bit_write("T4:1/DN", True).encode_params() == bytes.fromhex("0F 00 04 01 00 FF FF 00 20")
    packet = encode_command(plc5_bit_write("N7:0/3", True), dst=2, src=0, tns=1)
    assert packet == bytes.fromhex("02 00 0F 00 01 00 26 07 00 07 00 FF FF 08 00")


def test_wrong_address_kinds_are_refused() -> None:
    with pytest.raises(AddressError, match="bit address"):
        plc5_bit_write("N7:0", True)
    with pytest.raises(AddressError, match="plc5_bit_write"):
        plc5_write("B3/5", b"\x01\x00")
    with pytest.raises(AddressError, match="not the bit"):
        plc5_read("B3/5")
