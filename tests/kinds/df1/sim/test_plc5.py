"""The simulated PLC-5: word range read / write and read-modify-write, byte for byte, both variants.

Formats: 1770-KF2 user manual p. 5-57 (word range read FNC 01 / write FNC 00), p. 5-48 and
1770-6.5.16 p. 7-20 (read-modify-write FNC 26); addresses 1770-6.5.16 p. 13-11 .. 13-15.
"""

from __future__ import annotations

import struct

import pytest

from gateway.kinds.df1.sim.plc5 import Plc5Simulator
from gateway.kinds.df1.sim.slc500 import Slc500Options
from gateway.protocols.df1.framing import ACK_SYMBOL, Checksum, encode_frame
from gateway.protocols.df1.pccc.plc5 import ReadModifyWrite
from gateway.protocols.df1.pccc.plc5 import WordRangeReadParams as WordRangeRead
from gateway.protocols.df1.pccc.plc5 import WordRangeWriteParams as WordRangeWrite
from gateway.protocols.df1.plc5_address import (
    encode_logical_ascii,
    encode_logical_binary,
    parse_plc5_address,
)
from gateway.sim.variants import variant_matrix

VARIANTS = ("refuse", "accept")
TNS = bytes.fromhex("34 12")


def make(typed_logical: str = "refuse") -> Plc5Simulator:
    return Plc5Simulator(Slc500Options(checksum=Checksum.BCC), ladder=False, variants={"typed_logical": typed_logical})


def cmd(fnc: int, params: bytes) -> bytes:
    """DST 01 SRC 00 CMD 0F STS 00 TNS 1234 FNC params."""
    return bytes.fromhex("01 00 0F 00") + TNS + bytes((fnc,)) + params


def ok_reply(data: bytes = b"") -> bytes:
    return bytes.fromhex("00 01 4F 00") + TNS + data


def read(address: str, size: int, *, compact: bool = False) -> bytes:
    encoded = encode_logical_binary(parse_plc5_address(address), compact=compact)
    return cmd(0x01, WordRangeRead(encoded, size).encode())


def write(address: str, data: bytes) -> bytes:
    return cmd(0x00, WordRangeWrite(encode_logical_binary(parse_plc5_address(address)), data).encode())


@pytest.mark.parametrize("variant", VARIANTS)
def test_word_range_read_n7_30_byte_exact(variant: str) -> None:
    """N7:30 = 30 (the model's initial table); mask 07 00 07 1E is the p. 13-12 vector."""
    sim = make(variant)
    packet = read("N7:30", 2)
    assert packet == bytes.fromhex("01 00 0F 00 34 12 01 00 00 01 00 07 00 07 1E 02")
    assert sim.execute(packet) == bytes.fromhex("00 01 4F 00 34 12 1E 00")


@pytest.mark.parametrize("variant", VARIANTS)
def test_word_range_write_then_read_n7_30(variant: str) -> None:
    sim = make(variant)
    packet = write("N7:30", bytes.fromhex("22 11 44 33"))
    assert packet == bytes.fromhex("01 00 0F 00 34 12 00 00 00 02 00 07 00 07 1E 22 11 44 33")
    assert sim.execute(packet) == ok_reply()
    assert sim.word("N7", 30) == 0x1122 and sim.word("N7", 31) == 0x3344
    assert sim.execute(read("N7:30", 4)) == ok_reply(bytes.fromhex("22 11 44 33"))
    assert sim.applied_writes == [("word_range_write", "N7:30", bytes.fromhex("22 11 44 33"))]


@pytest.mark.parametrize("variant", VARIANTS)
def test_read_modify_write_b3_bits(variant: str) -> None:
    """B3/5 set (AND FFFF OR 0020), B3:1/0 reset (AND FFFE OR 0000): one RMW, two sets."""
    sim = make(variant)
    b3_0 = encode_logical_binary(parse_plc5_address("B3/5"))
    b3_1 = encode_logical_binary(parse_plc5_address("B3:1/0"))
    rmw = ReadModifyWrite(ReadModifyWrite.set_bit(b3_0, 5).sets + ReadModifyWrite.reset_bit(b3_1, 0).sets)
    packet = cmd(0x26, rmw.encode())
    assert packet == bytes.fromhex("01 00 0F 00 34 12 26 07 00 03 00 FF FF 20 00 07 00 03 01 FE FF 00 00")
    assert sim.execute(packet) == ok_reply()
    assert sim.word("B3", 0) == 0x0020
    assert sim.word("B3", 1) == 0xA5A4
    assert sim.execute(read("B3:0", 4)) == ok_reply(bytes.fromhex("20 00 A4 A5"))


@pytest.mark.parametrize("variant", VARIANTS)
def test_read_modify_write_checks_every_set_before_applying(variant: str) -> None:
    """B3:300 is past the 64-word B3 (p. 13-12 form FF 2C 01): EXT STS 06, and B3:0 is untouched."""
    sim = make(variant)
    good = encode_logical_binary(parse_plc5_address("B3:0"))
    bad = encode_logical_binary(parse_plc5_address("B3:300"), compact=True)
    assert bad == bytes.fromhex("06 03 FF 2C 01")
    rmw = ReadModifyWrite(((good, 0xFFFF, 0x0001), (bad, 0xFFFF, 0x0001)))
    assert sim.execute(cmd(0x26, rmw.encode())) == bytes.fromhex("00 01 4F F0 34 12 06")
    assert sim.word("B3", 0) == 0
    assert sim.applied_writes == []


@pytest.mark.parametrize("variant", VARIANTS)
def test_t4_2_acc_four_level_address(variant: str) -> None:
    """T4:2.ACC = 0F 00 04 02 02 (p. 13-12); PRE of T4:2 is 50 (sub-element 1)."""
    sim = make(variant)
    acc = encode_logical_binary(parse_plc5_address("T4:2.ACC"))
    assert acc == bytes.fromhex("0F 00 04 02 02")
    assert sim.execute(cmd(0x00, WordRangeWrite(acc, bytes.fromhex("07 00")).encode())) == ok_reply()
    assert sim.word("T4", 2, sub=2) == 7
    assert sim.execute(read("T4:2.PRE", 4)) == ok_reply(bytes.fromhex("32 00 07 00"))
    # the whole timer: control, PRE, ACC
    assert sim.execute(read("T4:2", 6)) == ok_reply(bytes.fromhex("00 00 32 00 07 00"))


@pytest.mark.parametrize("variant", VARIANTS)
def test_f8_2_float_two_words(variant: str) -> None:
    """F8:2 = 3.0 initially (1.5 x 2): IEEE single, low-order word first."""
    sim = make(variant)
    assert sim.execute(read("F8:2", 4)) == ok_reply(bytes.fromhex("00 00 40 40"))
    assert sim.execute(write("F8:2", struct.pack("<f", -2.5))) == ok_reply()
    assert sim.float_value("F8", 2) == -2.5
    assert sim.execute(read("F8:2", 4)) == ok_reply(struct.pack("<f", -2.5))


def test_logical_ascii_address_and_packet_offset() -> None:
    """Logical ASCII ``NUL $ N7:10 NUL`` (p. 13-15); packet offset 2 words moves the start to N7:12."""
    sim = make()
    params = WordRangeRead(encode_logical_ascii("N7:10"), 2, packet_offset=2, total_transaction=3).encode()
    assert sim.execute(cmd(0x01, params)) == ok_reply(bytes.fromhex("0C 00"))


@pytest.mark.parametrize(
    ("packet", "reply_tail"),
    [
        (read("N9:0", 2), "F0 34 12 06"),  # no file 9
        (read("N7:255", 4), "F0 34 12 07"),  # runs past the end of N7
        (cmd(0x01, bytes.fromhex("00 00 7B 00 07 00 07 00 F6")), "F0 34 12 09"),  # 246 bytes: over 244
        (cmd(0x01, bytes.fromhex("00 00 01 00 1F 00 07 00 00 00 02")), "F0 34 12 03"),  # 5 levels
        (cmd(0x01, bytes.fromhex("00 00 01 00 05 00 07 02")), "F0 34 12 02"),  # no file level
        (cmd(0x01, bytes.fromhex("00 00 01 00 07 01 07 00 02")), "F0 34 12 06"),  # data table 1
        (cmd(0x01, bytes.fromhex("00 00 01 00 07 00")), "10 34 12"),  # truncated
        (cmd(0x94, bytes.fromhex("06 80 07")), "10 34 12"),  # SLC read file info
    ],
)
def test_refusals(packet: bytes, reply_tail: str) -> None:
    assert make().execute(packet) == bytes.fromhex("00 01 4F") + bytes.fromhex(reply_tail)


def typed_logical_read_n7_30() -> bytes:
    """0F A2: size 02, file 07, type 89 (integer), element 1E, sub-element 00."""
    return cmd(0xA2, bytes.fromhex("02 07 89 1E 00"))


def typed_logical_write_n7_30() -> bytes:
    return cmd(0xAA, bytes.fromhex("02 07 89 1E 00 99 00"))


def test_typed_logical_refused_with_illegal_command() -> None:
    """``typed_logical=refuse``: STS 10 hex (illegal command or format); nothing written."""
    sim = make("refuse")
    assert sim.execute(typed_logical_read_n7_30()) == bytes.fromhex("00 01 4F 10 34 12")
    assert sim.execute(typed_logical_write_n7_30()) == bytes.fromhex("00 01 4F 10 34 12")
    assert sim.word("N7", 30) == 30
    assert sim.counters.commands["unsupported"] == 2


def test_typed_logical_accepted() -> None:
    sim = make("accept")
    assert sim.execute(typed_logical_read_n7_30()) == ok_reply(bytes.fromhex("1E 00"))
    assert sim.execute(typed_logical_write_n7_30()) == ok_reply()
    assert sim.execute(read("N7:30", 2)) == ok_reply(bytes.fromhex("99 00"))


def test_full_duplex_link_is_the_slc_models() -> None:
    """A word range read in a DF1 frame: DLE ACK, then the reply frame (KE p. 5-6 style)."""
    sim = make()
    outputs = sim.receive(encode_frame(read("N7:30", 2), Checksum.BCC), 0.0)
    wire = b"".join(o.data for o in outputs)
    assert wire == ACK_SYMBOL + encode_frame(bytes.fromhex("00 01 4F 00 34 12 1E 00"), Checksum.BCC)


def test_variant_table_contract() -> None:
    assert Plc5Simulator.VARIANTS["typed_logical"] == ("refuse", "accept")
    for choice in variant_matrix({"typed_logical": Plc5Simulator.VARIANTS["typed_logical"]}):
        assert Plc5Simulator(variants=choice).accept_typed_logical == (choice["typed_logical"] == "accept")
    with pytest.raises(ValueError, match="typed_logical"):
        Plc5Simulator(variants={"typed_logical": "maybe"})
