"""Byte-exact frames the public manuals print, reproduced by the codecs the gateway sends with.

The half-duplex framing vectors (1770-6.5.16 p. 5-5 / 5-7, KF2 p. 4-25) are in
``framing/test_half_duplex_framing.py`` and the address / parameter-builder vectors (p. 13-12, 1785-KE
p. 5-5 / 5-6) in ``test_plc5_address.py``.  This file checks the *other* paths that carry the
same bytes: the full-duplex framing codec (``gateway.protocols.df1.framing``, used by every
full-duplex link) and the PCCC request classes the PLC-5 unit sends (``encode_command`` of
``WordRangeRead`` / ``WordRangeWrite`` / ``plc5_read`` / ``plc5_write``), and the decoders, whole, byte
by byte and with trailing garbage.
"""

from __future__ import annotations

import pytest

from gateway.protocols.df1.framing import NEED_DATA, Checksum, Frame, encode_frame
from gateway.protocols.df1.framing.decoder import FrameDecoder
from gateway.protocols.df1.pccc import LogicalBinaryAddress, WordRangeRead, WordRangeWrite, decode_reply
from gateway.protocols.df1.pccc.commands import decode_command, encode_command
from gateway.protocols.df1.plc5_address import encode_logical_binary, parse_plc5_address
from gateway.protocols.df1.plc5_commands import plc5_read, plc5_write

# (page, checksum, application data, printed frame)
FULL_DUPLEX_FRAMES = [
    # 1770-6.5.16 p. 5-5 "Full-duplex protocol example": sum 20 hex, BCC E0
    ("1770-6.5.16 p. 5-5", Checksum.BCC, "08 09 06 00 02 04 03", "10 02 08 09 06 00 02 04 03 10 03 E0"),
    # p. 5-5: the value 10 hex sent as DLE DLE, counted once: sum 2E, BCC D2
    ("1770-6.5.16 p. 5-5", Checksum.BCC, "08 09 06 00 10 04 03", "10 02 08 09 06 00 10 10 04 03 10 03 D2"),
    # p. 5-7: "an actual frame that you can use to validate your CRC routine", CRC low byte first
    (
        "1770-6.5.16 p. 5-7",
        Checksum.CRC,
        "07 11 41 00 53 B9 00 00 00 00 00 00 00 00 00 00 00 00",
        "10 02 07 11 41 00 53 B9 00 00 00 00 00 00 00 00 00 00 00 00 10 03 6B 4C",
    ),
    # 1785-KE user manual p. 5-5: word range write to N10:15 and its reply
    (
        "1785-KE p. 5-5",
        Checksum.BCC,
        "29 20 0F 00 46 01 00 00 00 04 00 0F 00 0A 0F 00 22 11 44 33 66 55 88 77",
        "10 02 29 20 0F 00 46 01 00 00 00 04 00 0F 00 0A 0F 00 22 11 44 33 66 55 88 77 10 03 D1",
    ),
    ("1785-KE p. 5-5", Checksum.BCC, "20 29 4F 00 46 01", "10 02 20 29 4F 00 46 01 10 03 21"),
    # 1785-KE p. 5-6: word range read by logical ASCII address $N10:15, and its reply
    (
        "1785-KE p. 5-6",
        Checksum.BCC,
        "29 20 0F 00 47 01 01 00 00 04 00 00 24 4E 31 30 3A 31 35 00 08",
        "10 02 29 20 0F 00 47 01 01 00 00 04 00 00 24 4E 31 30 3A 31 35 00 08 10 03 E0",
    ),
    (
        "1785-KE p. 5-6",
        Checksum.BCC,
        "20 29 4F 00 47 01 22 11 44 33 66 55 88 77",
        "10 02 20 29 4F 00 47 01 22 11 44 33 66 55 88 77 10 03 BC",
    ),
    # 1785-KE p. 5-4: PLC-2 unprotected read of the same 4 words (CMD 01), and its reply
    ("1785-KE p. 5-4", Checksum.BCC, "29 20 01 00 45 01 28 00 08", "10 02 29 20 01 00 45 01 28 00 08 10 03 40"),
    (
        "1785-KE p. 5-4",
        Checksum.BCC,
        "20 29 41 00 45 01 22 11 44 33 66 55 88 77",
        "10 02 20 29 41 00 45 01 22 11 44 33 66 55 88 77 10 03 CC",
    ),
]


def _frames(decoder: FrameDecoder) -> list[object]:
    out: list[object] = []
    while (event := decoder.next_event()) is not NEED_DATA:
        out.append(event)
    return out


@pytest.mark.parametrize(("page", "checksum", "data", "frame"), FULL_DUPLEX_FRAMES)
def test_full_duplex_codec_reproduces_printed_frame(page: str, checksum: Checksum, data: str, frame: str) -> None:
    message, printed = bytes.fromhex(data), bytes.fromhex(frame)
    assert encode_frame(message, checksum) == printed, page
    whole = FrameDecoder(checksum)
    whole.feed(printed + b"\x55\x10")  # trailing garbage and half a DLE sequence: no extra event
    assert _frames(whole) == [Frame(message)], page
    by_byte = FrameDecoder(checksum)
    events: list[object] = []
    for i in range(len(printed)):
        by_byte.feed(printed[i : i + 1])
        events += _frames(by_byte)
    assert events == [Frame(message)], page


def test_word_range_write_request_class_sends_the_1785ke_frame() -> None:
    """1785-KE p. 5-5: ``WordRangeWrite`` with the four-level address of N10:15, TNS 0146, to node 51 octal."""
    address = LogicalBinaryAddress.of(0, 10, 15, 0)
    assert address.encode() == bytes.fromhex("0F 00 0A 0F 00")
    request = WordRangeWrite(address, bytes.fromhex("22 11 44 33 66 55 88 77"))
    packet = encode_command(request, dst=0o51, src=0x20, tns=0x0146)
    printed = "10 02 29 20 0F 00 46 01 00 00 00 04 00 0F 00 0A 0F 00 22 11 44 33 66 55 88 77 10 03 D1"
    assert encode_frame(packet, Checksum.BCC) == bytes.fromhex(printed)
    assert decode_command(packet).request == request
    reply = decode_reply(bytes.fromhex("20 29 4F 00 46 01"))  # p. 5-5 reply
    assert reply.ok and reply.tns == 0x0146 and reply.cmd == 0x4F


def test_word_range_read_reply_of_1785ke_decodes_low_byte_first() -> None:
    """1785-KE p. 5-6: the reply data 22 11 44 33 ... are the words 1122, 3344, 5566, 7788 hex."""
    reply = decode_reply(bytes.fromhex("20 29 4F 00 47 01 22 11 44 33 66 55 88 77"))
    assert reply.ok and reply.tns == 0x0147
    words = [int.from_bytes(reply.data[i : i + 2], "little") for i in range(0, 8, 2)]
    assert words == [0x1122, 0x3344, 0x5566, 0x7788]


def test_plc5_builders_send_the_1785ke_layout_for_n10_15() -> None:
    """1785-KE p. 5-5 / 5-6 layouts from the typed address ``N10:15`` (our default mask is 07, three
    levels, the p. 13-12 N7:30 form; the decoded address is the same as the printed 0F form)."""
    assert encode_logical_binary(parse_plc5_address("N10:15")) == bytes.fromhex("07 00 0A 0F")
    read = encode_command(plc5_read("N10:15", 4), dst=0o51, src=0x20, tns=0x0147)
    assert read == bytes.fromhex("29 20 0F 00 47 01 01 00 00 04 00 07 00 0A 0F 08")
    write = encode_command(plc5_write("N10:15", bytes.fromhex("22 11 44 33 66 55 88 77")), dst=0o51, src=0x20,
                           tns=0x0146)
    assert write == bytes.fromhex("29 20 0F 00 46 01 00 00 00 04 00 07 00 0A 0F 22 11 44 33 66 55 88 77")
    printed = decode_command(bytes.fromhex("29 20 0F 00 46 01 00 00 00 04 00 0F 00 0A 0F 00 22 11 44 33 66 55 88 77"))
    assert isinstance(printed.request, WordRangeWrite)
    assert printed.request.address.levels[:3] == (0, 10, 15) and printed.request.data == write[-8:]


def test_p13_12_addresses_through_the_request_class() -> None:
    """1770-6.5.16 p. 13-12: N7:30 = 07 00 07 1E and T4:2.ACC = 0F 00 04 02 02 in a word range read."""
    assert encode_command(plc5_read("N7:30", 1), dst=1, src=0, tns=1)[11:15] == bytes.fromhex("07 00 07 1E")
    assert encode_command(plc5_read("T4:2.ACC", 1), dst=1, src=0, tns=1)[11:16] == bytes.fromhex("0F 00 04 02 02")
    b3 = WordRangeRead(LogicalBinaryAddress(0x06, (3, 300)), 2)
    assert b3.encode_params()[4:9] == bytes.fromhex("06 03 FF 2C 01")  # B3:300, level 1 defaulted
