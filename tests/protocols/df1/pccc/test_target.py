"""The DF1 target (``pccc/target.py``): byte scripts for every command and refusal, and round trips
through the master side's own request encoders and reply decoders."""

from __future__ import annotations

import math
import struct
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.protocols.df1.address import FileType
from gateway.protocols.df1.pccc import (
    DataType,
    DiagnosticStatusInfo,
    Echo,
    LogicalBinaryAddress,
    ProtectedTypedLogicalMaskedWrite,
    ProtectedTypedLogicalRead,
    ProtectedTypedLogicalTwoFieldRead,
    ProtectedTypedLogicalTwoFieldWrite,
    ProtectedTypedLogicalWrite,
    ReadModifyWriteRequest,
    Request,
    TypedRead,
    TypedWrite,
    WordRangeRead,
    WordRangeWrite,
    decode_reply,
    decode_typed_data,
    encode_command,
    reply_matches,
)
from gateway.protocols.df1.pccc.target import (
    PcccTarget,
    Problem,
    TargetReply,
    UnwrittenReads,
    diagnostic_status_reply,
)
from gateway.protocols.df1.pccc.target_table import DataTable, ElementRef, TableFile, TableFileKind
from gateway.protocols.df1.pccc.target_transfer import Transfers


def H(text: str) -> bytes:
    return bytes.fromhex(text)


def make_target(unwritten_reads: UnwrittenReads = UnwrittenReads.ZERO) -> PcccTarget:
    table = DataTable.of("N7:10", "B3:4", "F8:4", "L9:4", "N10:400")
    return PcccTarget(table, unwritten_reads=unwritten_reads)


def run(target: PcccTarget, request: Request, now: float = 1.0, *, tns: int = 1, src: int = 2) -> TargetReply:
    result = target.execute(encode_command(request, dst=1, src=src, tns=tns), now)
    assert result.reply is not None
    return result


def N7(element: int) -> LogicalBinaryAddress:
    return LogicalBinaryAddress.for_element(7, element)


# ------------------------------------------------------------------ SLC typed logical commands


def test_typed_logical_write_then_read_byte_script() -> None:
    target = make_target()
    # 0F AA: size 4, file 7, type 89, element 1, sub 0, data 01 00 FF FF -> STS 00, DST / SRC swapped
    result = target.execute(H("01 02 0F 00 03 00 AA 04 07 89 01 00 01 00 FF FF"), now=5.0)
    assert result.reply == H("02 01 4F 00 03 00")
    assert result.written == (ElementRef(7, 1), ElementRef(7, 2))
    assert target.table[7].value(1) == 1 and target.table[7].value(2) == -1
    assert target.table[7].written_at(2) == 5.0 and target.table[7].written_at(0) is None
    # 0F A2: 6 bytes from N7:0 - N7:0 was never written: read as 0 and named
    result = target.execute(H("01 02 0F 00 04 00 A2 06 07 89 00 00"), now=6.0)
    assert result.reply == H("02 01 4F 00 04 00 00 00 01 00 FF FF")
    assert result.unwritten == (ElementRef(7, 0),)


def test_two_address_field_read_and_write() -> None:
    target = make_target()
    assert target.execute(H("01 02 0F 00 07 00 A9 02 07 89 03 34 12"), 1.0).reply == H("02 01 4F 00 07 00")
    assert target.execute(H("01 02 0F 00 08 00 A1 02 07 89 03"), 1.0).reply == H("02 01 4F 00 08 00 34 12")


def test_expanded_element_field() -> None:
    target = make_target()
    write = ProtectedTypedLogicalWrite(FileType.INTEGER, 10, 300, 0, H("2A 00"))
    assert write.encode_params() == H("02 0A 89 FF 2C 01 00 2A 00")
    run(target, write)
    assert target.table[10].value(300) == 42


def test_masked_write_changes_only_the_masked_bits() -> None:
    target = make_target()
    run(target, ProtectedTypedLogicalWrite(FileType.BIT, 3, 0, 0, H("FF 00")))
    # new = (old & ~mask) | (data & mask): (00FF & F0F0) | (AAAA & 0F0F) = 0AFA
    packet = H("01 02 0F 00 09 00 AB 02 03 85 00 00 0F 0F AA AA")
    assert target.execute(packet, 2.0).reply == H("02 01 4F 00 09 00")
    assert target.table[3].value(0) == 0x0AFA
    # an odd byte size: the mask's low byte goes over the odd byte (notes §7.3)
    run(target, ProtectedTypedLogicalMaskedWrite(FileType.BIT, 3, 1, 0, 0x00F0, H("FF")))
    assert target.table[3].value(1) == 0x00F0
    # byte size 0 is allowed and changes nothing
    result = run(target, ProtectedTypedLogicalMaskedWrite(FileType.BIT, 3, 2, 0, 0xFFFF, b""))
    assert result.sts == 0 and result.written == () and target.table[3].value(2) is None


@pytest.mark.parametrize(
    ("request_", "problem"),
    [
        (ProtectedTypedLogicalRead(FileType.INTEGER, 11, 0, 0, 2), Problem.NO_FILE),
        (ProtectedTypedLogicalRead(FileType.INTEGER, 7, 10, 0, 2), Problem.NOT_USABLE),
        (ProtectedTypedLogicalRead(FileType.INTEGER, 7, 0, 1, 2), Problem.NOT_USABLE),
        (ProtectedTypedLogicalRead(FileType.INTEGER, 7, 9, 0, 4), Problem.PAST_END),
        (ProtectedTypedLogicalRead(FileType.FLOAT, 7, 0, 0, 2), Problem.TYPE),
        (ProtectedTypedLogicalTwoFieldWrite(FileType.INTEGER, 7, 8, H("01 00 02 00 03 00")), Problem.PAST_END),
        (ProtectedTypedLogicalMaskedWrite(FileType.BIT, 4, 0, 0, 1, H("01 00")), Problem.NO_FILE),
    ],
)
def test_slc_address_problems_are_sts_50(request_: Request, problem: Problem) -> None:
    target = make_target()
    result = run(target, request_)
    assert (result.sts, result.ext_sts, result.problem) == (0x50, None, problem)
    assert result.reply == H("02 01 4F 50 01 00")
    assert all(f.value(e) is None for f in target.table for e in range(f.count))  # nothing written


def test_slc_packet_size_limits_are_sts_10() -> None:
    target = PcccTarget(DataTable.of("N7:256", "N300:256"))
    assert run(target, ProtectedTypedLogicalRead(FileType.INTEGER, 7, 0, 0, 236)).sts == 0  # 5/03-5/05 on DF1
    assert run(target, ProtectedTypedLogicalRead(FileType.INTEGER, 7, 0, 0, 237)).reply == H("02 01 4F 10 01 00")
    assert run(target, ProtectedTypedLogicalWrite(FileType.INTEGER, 7, 0, 0, bytes(228))).sts == 0
    assert run(target, ProtectedTypedLogicalWrite(FileType.INTEGER, 7, 0, 0, bytes(230))).sts == 0x10
    # two bytes less per address field in its three-byte form (notes §4.36)
    assert run(target, ProtectedTypedLogicalWrite(FileType.INTEGER, 300, 0, 0, bytes(228))).sts == 0x10
    assert run(target, ProtectedTypedLogicalWrite(FileType.INTEGER, 300, 0, 0, bytes(226))).sts == 0


# --------------------------------------------------------------------- word range 0F 01 / 00


def test_word_range_write_and_read_byte_script() -> None:
    target = make_target()
    # 0F 00: offset 0, total 2, address 0F 00 07 03 00 (N7:3), data 11 11 22 22
    assert target.execute(H("01 02 0F 00 0A 00 00 00 00 02 00 0F 00 07 03 00 11 11 22 22"), 1.0).reply == H(
        "02 01 4F 00 0A 00"
    )
    # 0F 01: offset 1 word, total 2, N7:3, size 2 bytes -> N7:4
    assert target.execute(H("01 02 0F 00 0B 00 01 01 00 02 00 0F 00 07 03 00 02"), 1.0).reply == H(
        "02 01 4F 00 0B 00 22 22"
    )


def test_word_range_over_a_float_file_addresses_its_words() -> None:
    target = make_target()
    target.table[8].set_value(1, 1.5, 0.0)
    data = run(target, WordRangeRead(LogicalBinaryAddress.for_element(8, 1), 4))
    assert decode_reply(data.reply or b"").data == struct.pack("<f", 1.5)
    run(target, WordRangeWrite(LogicalBinaryAddress.for_element(8, 2), H("C0 3F")))  # one word: the low one
    assert target.table[8].read_bytes(8, 4) == (H("C0 3F 00 00"), ())  # the high word of a new element: 0


@pytest.mark.parametrize(
    ("request_", "sts", "ext"),
    [
        (WordRangeRead(N7(0), 3), 0x10, None),  # odd size (1770-6.5.16 p. 8-9)
        (WordRangeRead(N7(0), 4, packet_offset=1, total=2), 0x10, None),  # past the total transaction
        (WordRangeRead(LogicalBinaryAddress.for_element(11, 0), 2), 0xF0, 0x06),  # no such file
        (WordRangeRead(N7(10), 2), 0xF0, 0x06),  # start past the end
        (WordRangeRead(LogicalBinaryAddress.for_element(7, 0, 1), 2), 0xF0, 0x06),  # sub-element
        (WordRangeRead(LogicalBinaryAddress(0x0F, (1, 7, 0, 0)), 2), 0xF0, 0x06),  # section 1
        (WordRangeRead(N7(9), 4), 0xF0, 0x09),  # runs past the end
        (WordRangeRead(LogicalBinaryAddress(0x1F, (0, 7, 0, 0, 0)), 2), 0xF0, 0x03),  # five levels
        (WordRangeRead(LogicalBinaryAddress(0x01, (0,)), 2), 0xF0, 0x02),  # no file level
        (WordRangeWrite(N7(9), H("01 00 02 00")), 0xF0, 0x09),
        (WordRangeWrite(N7(0), H("01 00 02 00"), packet_offset=1, total=2), 0x10, None),
    ],
)
def test_word_range_refusals(request_: Request, sts: int, ext: int | None) -> None:
    target = make_target()
    result = run(target, request_)
    reply = decode_reply(result.reply or b"")
    assert (reply.sts, reply.ext_sts) == (sts, ext)
    assert target.table[7].value(9) is None


def test_a_file_address_is_its_element_0() -> None:
    target = make_target()
    run(target, WordRangeWrite(LogicalBinaryAddress(0x06, (7, 0)), H("05 00")))
    assert run(target, WordRangeRead(LogicalBinaryAddress(0x02, (7,)), 2)).reply == H("02 01 4F 00 01 00 05 00")


# ----------------------------------------------------------------- multi-packet writes


def test_multi_packet_word_range_write_applies_with_its_last_packet() -> None:
    target = make_target()
    first = run(target, WordRangeWrite(N7(2), H("01 00 02 00"), packet_offset=0, total=5), now=1.0, tns=1)
    assert first.sts == 0 and first.pending and first.written == ()
    assert target.table[7].value(2) is None  # nothing applied yet
    second = run(target, WordRangeWrite(N7(2), H("03 00 04 00"), packet_offset=2, total=5), now=2.0, tns=2)
    assert second.pending and target.table[7].value(4) is None
    last = run(target, WordRangeWrite(N7(2), H("05 00"), packet_offset=4, total=5), now=3.0, tns=3)
    assert last.reply == H("02 01 4F 00 03 00") and not last.pending
    assert last.written == tuple(ElementRef(7, e) for e in range(2, 7))
    assert [target.table[7].value(e) for e in range(2, 7)] == [1, 2, 3, 4, 5]
    assert {target.table[7].written_at(e) for e in range(2, 7)} == {3.0}  # one write, all at once


def test_the_packets_of_one_transaction_may_write_its_address_in_different_forms() -> None:
    """The transaction is the element the address names, not its bytes: an independent PLC written
    from the manuals sent a two-packet word range write with the section level in one packet only."""
    target = make_target()
    with_section = LogicalBinaryAddress.of(0, 7, 2, 0)  # mask 0F: section, file, element, sub-element
    without = LogicalBinaryAddress(0x06, (7, 2))  # mask 06: file, element
    assert with_section.encode() != without.encode()
    first = run(target, WordRangeWrite(with_section, H("01 00 02 00"), packet_offset=0, total=4), tns=1)
    last = run(target, WordRangeWrite(without, H("03 00 04 00"), packet_offset=2, total=4), tns=2)
    assert first.pending and last.sts == 0 and not last.pending
    assert [target.table[7].value(e) for e in range(2, 6)] == [1, 2, 3, 4]


def test_a_packet_out_of_order_ends_the_transaction_and_nothing_applies() -> None:
    target = make_target()
    run(target, WordRangeWrite(N7(0), H("01 00 02 00"), packet_offset=0, total=6))
    gap = run(target, WordRangeWrite(N7(0), H("05 00 06 00"), packet_offset=4, total=6), tns=2)
    assert gap.reply == H("02 01 4F F0 02 00 08") and gap.problem is Problem.OUT_OF_ORDER
    assert len(gap.abandoned) == 1 and not target.transfers.pending
    # the transaction is gone: its next packet is out of order too
    late = run(target, WordRangeWrite(N7(0), H("03 00 04 00"), packet_offset=2, total=6), tns=3)
    assert late.ext_sts == 0x08 and late.abandoned == ()
    assert all(target.table[7].value(e) is None for e in range(10))


def test_a_repeated_packet_is_out_of_order() -> None:
    target = make_target()
    run(target, WordRangeWrite(N7(0), H("01 00"), packet_offset=0, total=3))
    run(target, WordRangeWrite(N7(0), H("02 00"), packet_offset=1, total=3))
    assert run(target, WordRangeWrite(N7(0), H("02 00"), packet_offset=1, total=3)).ext_sts == 0x08


def test_a_new_first_packet_abandons_the_transaction_under_way() -> None:
    target = make_target()
    run(target, WordRangeWrite(N7(0), H("01 00"), packet_offset=0, total=2))
    again = run(target, WordRangeWrite(N7(0), H("09 00"), packet_offset=0, total=2))
    assert again.pending and len(again.abandoned) == 1
    run(target, WordRangeWrite(N7(0), H("08 00"), packet_offset=1, total=2))
    assert [target.table[7].value(e) for e in (0, 1)] == [9, 8]


def test_transactions_of_other_senders_and_addresses_run_side_by_side() -> None:
    target = make_target()
    run(target, WordRangeWrite(N7(0), H("01 00"), packet_offset=0, total=2), src=2)
    run(target, WordRangeWrite(N7(0), H("0A 00"), packet_offset=0, total=2), src=3)
    run(target, WordRangeWrite(N7(5), H("64 00"), packet_offset=0, total=2), src=2)
    run(target, WordRangeWrite(N7(0), H("0B 00"), packet_offset=1, total=2), src=3)
    run(target, WordRangeWrite(N7(0), H("02 00"), packet_offset=1, total=2), src=2)
    run(target, WordRangeWrite(N7(5), H("65 00"), packet_offset=1, total=2), src=2)
    assert [target.table[7].value(e) for e in (0, 1, 5, 6)] == [1, 2, 100, 101]


def test_an_abandoned_transaction_expires_and_the_oldest_gives_way() -> None:
    target = PcccTarget(DataTable.of("N7:10"), transfers=Transfers(timeout=10.0, limit=2))
    run(target, WordRangeWrite(N7(0), H("01 00"), packet_offset=0, total=2), now=0.0, src=1)
    run(target, WordRangeWrite(N7(0), H("01 00"), packet_offset=0, total=2), now=5.0, src=2)
    crowded = run(target, WordRangeWrite(N7(0), H("01 00"), packet_offset=0, total=2), now=6.0, src=3)
    assert [t.key for t in crowded.abandoned] == [(1, 0x00, 7, 0, 2)]  # (SRC, FNC, file, byte, total)
    echo = run(target, Echo(b""), now=15.5)  # any packet: the one of src 2 waited 10.5 s
    assert [t.key for t in echo.abandoned] == [(2, 0x00, 7, 0, 2)]
    assert run(target, WordRangeWrite(N7(0), H("02 00"), packet_offset=1, total=2), now=16.0, src=3).sts == 0
    assert target.table[7].value(1) == 2
    with pytest.raises(ValueError):
        Transfers(timeout=0)


def test_a_target_may_keep_one_transfer_for_under_a_second() -> None:
    """The smallest bounds: any positive timeout, a limit of 1 (the next sender's transfer makes
    the open one give way)."""
    target = PcccTarget(DataTable.of("N7:10"), transfers=Transfers(timeout=0.5, limit=1))
    run(target, WordRangeWrite(N7(0), H("01 00"), packet_offset=0, total=2), now=0.0, src=1)
    crowded = run(target, WordRangeWrite(N7(0), H("0A 00"), packet_offset=0, total=2), now=0.1, src=2)
    assert [t.key for t in crowded.abandoned] == [(1, 0x00, 7, 0, 2)]
    late = run(target, WordRangeWrite(N7(0), H("0B 00"), packet_offset=1, total=2), now=0.7, src=2)
    assert [t.key for t in late.abandoned] == [(2, 0x00, 7, 0, 2)] and late.ext_sts != 0
    for timeout, limit in ((-1.0, 1), (0.5, 0)):
        with pytest.raises(ValueError):
            Transfers(timeout=timeout, limit=limit)


def test_a_multi_packet_write_that_cannot_fit_is_refused_at_its_first_packet() -> None:
    target = make_target()
    result = run(target, WordRangeWrite(N7(8), H("01 00"), packet_offset=0, total=3))
    assert result.ext_sts == 0x09 and not target.transfers.pending


# ------------------------------------------------------------------ typed read / write 0F 68 / 67


def test_typed_write_and_read_byte_script() -> None:
    target = make_target()
    # 0F 67: offset 0, total 2, N7:0, type/data 95 09 (array, 5 bytes) 42 (integer, 2 bytes), data
    packet = H("01 02 0F 00 0C 00 67 00 00 02 00 0F 00 07 00 00 95 09 42 07 00 08 00")
    assert target.execute(packet, 1.0).reply == H("02 01 4F 00 0C 00")
    # 0F 68: offset 0, total 2, N7:0, count 2 -> the same typed data back
    reply = target.execute(H("01 02 0F 00 0D 00 68 00 00 02 00 0F 00 07 00 00 02 00"), 1.0).reply
    assert reply == H("02 01 4F 00 0D 00 95 09 42 07 00 08 00")


def test_typed_read_of_one_element_is_bare_and_of_each_file_type() -> None:
    target = make_target()
    target.table[8].set_value(0, -2.25, 0.0)
    target.table[3].set_value(0, 0x8001, 0.0)
    one = decode_reply(run(target, TypedRead(LogicalBinaryAddress.for_element(8, 0), 1)).reply or b"")
    assert one.data == H("94 08") + struct.pack("<f", -2.25)  # float (ID 8 in a byte of its own), 4 bytes
    bits = decode_typed_data(decode_reply(run(target, TypedRead(LogicalBinaryAddress.for_element(3, 0), 2)).reply
                                          or b"").data)
    assert (bits.data_type, bits.element_size, bits.data) == (DataType.BIT, 2, H("01 80 00 00"))


@pytest.mark.parametrize(
    ("request_", "sts", "ext"),
    [
        (TypedRead(LogicalBinaryAddress.for_element(9, 0), 1), 0xF0, 0x11),  # L: no typed ID
        (TypedWrite(N7(0), DataType.FLOAT, 4, bytes(4)), 0xF0, 0x11),  # not the file's type
        (TypedWrite(N7(0), DataType.INTEGER, 4, bytes(4)), 0xF0, 0x11),  # not its element size
        (TypedRead(N7(0), 2, packet_offset=1, total=2), 0x10, None),
        (TypedRead(LogicalBinaryAddress.for_element(10, 0), 122), 0x10, None),  # 3 + 244 bytes > 244
        (TypedWrite(LogicalBinaryAddress.for_element(10, 0), DataType.INTEGER, 2, bytes(232)), 0x10, None),
        (TypedRead(N7(10), 1), 0xF0, 0x06),
        (TypedRead(N7(8), 3), 0xF0, 0x09),
    ],
)
def test_typed_refusals(request_: Request, sts: int, ext: int | None) -> None:
    result = run(make_target(), request_)
    assert (result.sts, result.ext_sts) == (sts, ext)


def test_typed_read_and_write_at_their_limits() -> None:
    target = make_target()
    assert run(target, TypedRead(LogicalBinaryAddress.for_element(10, 0), 120)).sts == 0  # 3 + 240
    assert run(target, TypedWrite(LogicalBinaryAddress.for_element(10, 0), DataType.INTEGER, 2, bytes(226))).sts == 0


def test_multi_packet_typed_write_counts_elements() -> None:
    target = make_target()
    address = LogicalBinaryAddress.for_element(8, 1)
    first = run(target, TypedWrite(address, DataType.FLOAT, 4, struct.pack("<f", 0.5), packet_offset=0, total=2))
    assert first.pending
    run(target, TypedWrite(address, DataType.FLOAT, 4, struct.pack("<f", 0.25), packet_offset=1, total=2))
    assert (target.table[8].value(1), target.table[8].value(2)) == (0.5, 0.25)


# ------------------------------------------------------------------ diagnostics, other commands


def test_diagnostic_status_identifies_a_computer_interface_not_a_controller() -> None:
    target = make_target()
    reply = target.execute(H("01 02 06 00 0E 00 03"), 1.0).reply
    assert reply == H("02 01 46 00 0E 00 00 FE 00 00 00") + b"DF1-GATEWAY" + bytes(8)
    info = DiagnosticStatusInfo(decode_reply(reply or b"").data)
    assert info.family is None and info.processor_type == 0 and info.catalog == "DF1-GATEWAY"
    assert diagnostic_status_reply("X")[5:16] == b"X" + b" " * 10


def test_echo_sends_the_data_back() -> None:
    target = make_target()
    assert target.execute(H("01 02 06 00 0F 00 00 10 02 AB"), 1.0).reply == H("02 01 46 00 0F 00 10 02 AB")


@pytest.mark.parametrize(
    "packet",
    [
        "01 02 0F 00 10 00 26 07 00 07 00 FF FF 00 00",  # read-modify-write: a PLC-5 command we do not have
        "01 02 0F 00 10 00 94 06 80 07",  # read file info
        "01 02 0F 00 10 00 80 06",  # set processor mode
        "01 02 06 00 10 00 01",  # diagnostic read
        "01 02 01 00 10 00 00 00 02",  # unprotected read
        "01 02 0F 00 10 00 A2 04 07 89",  # truncated
        "01 02 0F 00 10 00",  # no FNC
    ],
)
def test_unknown_commands_and_bad_formats_are_sts_10(packet: str) -> None:
    result = make_target().execute(H(packet), 1.0)
    assert result.reply == bytes((0x02, 0x01, H(packet)[2] | 0x40, 0x10, 0x10, 0x00))
    assert result.problem is Problem.FORMAT


def test_replies_and_short_packets_get_no_answer() -> None:
    target = make_target()
    assert target.execute(H("01 02 4F 00 01 00"), 1.0).reply is None
    assert target.execute(H("01 02 0F"), 1.0).reply is None


# ------------------------------------------------------------------------ never-written reads


def test_unwritten_reads_refused_when_asked() -> None:
    target = make_target(unwritten_reads=UnwrittenReads.REFUSE)
    assert run(target, ProtectedTypedLogicalRead(FileType.INTEGER, 7, 0, 0, 2)).reply == H("02 01 4F F0 01 00 10")
    assert run(target, WordRangeRead(N7(0), 2)).ext_sts == 0x10
    run(target, ProtectedTypedLogicalWrite(FileType.INTEGER, 7, 0, 0, H("07 00")))
    assert run(target, ProtectedTypedLogicalRead(FileType.INTEGER, 7, 0, 0, 2)).reply == H("02 01 4F 00 01 00 07 00")


# ------------------------------------------------------------------------------ data table


def test_data_table_values_and_raw_bits() -> None:
    table = DataTable.of("N7:2", "B3:1", "F8:2", "L9:2")
    table[7].set_value(0, -32768, 1.0)
    table[3].set_value(0, 0xFFFF, 1.0)
    table[9].set_value(0, -(2**31), 1.0)
    nan = struct.unpack("<f", H("01 00 C0 7F"))[0]
    table[8].write_bytes(0, H("01 00 C0 7F"), 2.0)
    assert table[8].read_bytes(0, 4) == (H("01 00 C0 7F"), ())  # the bits written, NaN payload kept
    assert math.isnan(table[8].value(0) or 0.0) and math.isnan(nan)
    assert table[9].read_bytes(0, 8) == (H("00 00 00 80 00 00 00 00"), (1,))  # low-order word first
    for file_number, value in ((7, 32768), (3, -1), (9, 2**31)):
        with pytest.raises(ValueError):
            table[file_number].set_value(1, value, 0.0)
    with pytest.raises(IndexError):
        table[7].value(2)
    with pytest.raises(IndexError):
        table[7].write_bytes(2, H("01 00 02 00"), 0.0)  # runs past the end: nothing written
    assert table[7].value(1) is None and [f.name for f in table] == ["N7", "B3", "F8", "L9"]
    assert TableFileKind.from_letter("l") is TableFileKind.LONG


@pytest.mark.parametrize("specs", [("X7:2",), ("N7",), ("N7:0",), ("N7:2", "F7:2"), ("Nx:2",)])
def test_data_table_specs_are_checked(specs: tuple[str, ...]) -> None:
    with pytest.raises(ValueError):
        DataTable.of(*specs)
    with pytest.raises(ValueError):
        TableFile(TableFileKind.INTEGER, 70000, 1)


def test_a_file_is_numbered_0_to_65535_and_holds_1_to_65536_elements() -> None:
    """The whole range of a PCCC file number and element number (two bytes each)."""
    assert [TableFile(TableFileKind.INTEGER, n, 1).name for n in (0, 0xFFFF)] == ["N0", "N65535"]
    full = TableFile(TableFileKind.INTEGER, 7, 0x10000)
    full.set_value(0xFFFF, 5, 1.0)
    assert full.value(0xFFFF) == 5
    for number, count in ((-1, 1), (0x10000, 1), (7, 0), (7, 0x10001)):
        with pytest.raises(ValueError):
            TableFile(TableFileKind.INTEGER, number, count)


# --------------------------------------------------------------- round trips (one wire rule)


_ELEMENTS = 10


@st.composite
def _writes(draw: st.DrawFn) -> tuple[Any, ...]:
    """A write to N7 by one of the commands: (request, byte offset, data, mask)."""
    element = draw(st.integers(0, _ELEMENTS - 1))
    count = draw(st.integers(1, _ELEMENTS - element))
    data = draw(st.binary(min_size=2 * count, max_size=2 * count))
    kind = draw(st.sampled_from(["AA", "A9", "AB", "00", "67"]))
    if kind == "AA":
        return ProtectedTypedLogicalWrite(FileType.INTEGER, 7, element, 0, data), 2 * element, data, 0xFFFF
    if kind == "A9":
        return ProtectedTypedLogicalTwoFieldWrite(FileType.INTEGER, 7, element, data), 2 * element, data, 0xFFFF
    if kind == "AB":
        mask = draw(st.integers(0, 0xFFFF))
        return ProtectedTypedLogicalMaskedWrite(FileType.INTEGER, 7, element, 0, mask, data), 2 * element, data, mask
    if kind == "00":
        return WordRangeWrite(N7(element), data), 2 * element, data, 0xFFFF
    return TypedWrite(N7(element), DataType.INTEGER, 2, data), 2 * element, data, 0xFFFF


@st.composite
def _reads(draw: st.DrawFn) -> tuple[Any, ...]:
    element = draw(st.integers(0, _ELEMENTS - 1))
    count = draw(st.integers(1, _ELEMENTS - element))
    kind = draw(st.sampled_from(["A2", "A1", "01", "68"]))
    request: Request
    if kind == "A2":
        request = ProtectedTypedLogicalRead(FileType.INTEGER, 7, element, 0, 2 * count)
    elif kind == "A1":
        request = ProtectedTypedLogicalTwoFieldRead(FileType.INTEGER, 7, element, 2 * count)
    elif kind == "01":
        request = WordRangeRead(N7(element), 2 * count)
    else:
        request = TypedRead(N7(element), count)
    return request, 2 * element, 2 * count


@settings(max_examples=150, deadline=None)
@given(st.lists(st.one_of(_writes(), _reads()), min_size=1, max_size=12))
def test_every_command_against_a_byte_model(steps: list[tuple[Any, ...]]) -> None:
    """Master-side encoders -> target -> master-side decoders, checked against a plain byte image."""
    target = PcccTarget(DataTable.of("N7:10"))
    image = bytearray(2 * _ELEMENTS)
    written: set[int] = set()
    for tns, step in enumerate(steps):
        packet = encode_command(step[0], dst=1, src=2, tns=tns)
        result = target.execute(packet, float(tns))
        reply = decode_reply(result.reply or b"")
        assert reply_matches(packet, reply) and reply.ok, reply
        if len(step) == 4:
            _request, offset, data, mask = step
            for i, byte in enumerate(data):
                bits = mask.to_bytes(2, "little")[i % 2]
                image[offset + i] = (image[offset + i] & ~bits & 0xFF) | (byte & bits)
            written |= {(offset + i) // 2 for i in range(len(data))}
            assert {ref.element for ref in result.written} == {(offset + i) // 2 for i in range(len(data))}
        else:
            request, offset, size = step
            data = reply.data
            if isinstance(request, TypedRead):
                data = decode_typed_data(data).data
            assert data == bytes(image[offset : offset + size])
            unread = {e for e in range(offset // 2, (offset + size) // 2) if e not in written}
            assert {ref.element for ref in result.unwritten} == unread


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=40))
def test_any_bytes_get_a_decodable_answer_or_none(packet: bytes) -> None:
    result = make_target().execute(packet, 0.0)
    if result.reply is not None:
        reply = decode_reply(result.reply)
        assert reply_matches(packet, reply)
        assert reply.ok or reply.error() is not None


def test_read_modify_write_request_is_not_a_target_command() -> None:
    result = run(make_target(), ReadModifyWriteRequest(((N7(0), 0xFFFF, 1),)))
    assert result.sts == 0x10


def test_a_word_range_read_over_244_bytes_does_not_decode_and_is_sts_10() -> None:
    # SIZE F6 (246 bytes): more than a reply carries (S4516 §2.6.1: "DATA (up to 244 Bytes)")
    result = make_target().execute(H("01 02 0F 00 11 00 01 00 00 7B 00 0F 00 0A 00 00 F6"), 1.0)
    assert result.reply == H("02 01 4F 10 11 00") and result.request is None


def test_a_long_file_by_the_typed_logical_commands_with_file_type_91() -> None:
    target = make_target()
    run(target, ProtectedTypedLogicalWrite(0x91, 9, 1, 0, struct.pack("<i", -123456)))
    assert target.table[9].value(1) == -123456
    reply = decode_reply(run(target, ProtectedTypedLogicalRead(0x91, 9, 1, 0, 4)).reply or b"")
    assert reply.data == struct.pack("<i", -123456)
    assert run(target, ProtectedTypedLogicalRead(FileType.INTEGER, 9, 1, 0, 4)).sts == 0x50  # not an N file


@settings(max_examples=100, deadline=None)
@given(st.integers(0, 3), st.lists(st.binary(min_size=4, max_size=4), min_size=1, max_size=4))
def test_floats_keep_their_bits_through_typed_write_and_read(element: int, values: list[bytes]) -> None:
    target = make_target()
    values = values[: 4 - element]
    data = b"".join(values)
    address = LogicalBinaryAddress.for_element(8, element)
    assert run(target, TypedWrite(address, DataType.FLOAT, 4, data)).written == tuple(
        ElementRef(8, element + k) for k in range(len(values))
    )
    typed = decode_typed_data(decode_reply(run(target, TypedRead(address, len(values))).reply or b"").data)
    assert (typed.data_type, typed.element_size, typed.data) == (DataType.FLOAT, 4, data)


# ------------------------------------------------------------- limits, offsets, what a reply names


def test_a_typed_read_reply_never_exceeds_244_bytes() -> None:
    """KF2 p. 5-57: 244 reply data bytes; 120 words are 99 09 F1 42 + 240 bytes, 121 would be 246."""
    target = make_target()
    reply = decode_reply(run(target, TypedRead(LogicalBinaryAddress.for_element(10, 0), 120)).reply or b"")
    assert len(reply.data) == 244 and reply.data[:4] == H("99 09 F1 42")
    assert run(target, TypedRead(LogicalBinaryAddress.for_element(10, 0), 121)).sts == 0x10


def test_a_typed_write_takes_240_bytes_of_address_type_data_and_data() -> None:
    """1770-6.5.16 p. 7-30, KF2 p. 5-51: address 07 00 0A FF 00 01 (6) + 99 09 E7 42 (4) + 230 data = 240."""
    target = make_target()
    address = LogicalBinaryAddress.of(0, 10, 256)
    assert run(target, TypedWrite(address, DataType.INTEGER, 2, bytes(230))).sts == 0
    assert run(target, TypedWrite(address, DataType.INTEGER, 2, bytes(232))).sts == 0x10


def test_a_typed_read_with_a_packet_offset_reads_from_the_element_plus_the_offset() -> None:
    target = make_target()
    for element in range(6):
        target.table[7].set_value(element, 10 + element, 0.0)
    result = run(target, TypedRead(N7(2), 2, packet_offset=1, total=3))
    assert decode_typed_data(decode_reply(result.reply or b"").data).data == H("0D 00 0E 00")  # N7:3, N7:4


def test_the_reply_names_the_request_it_answered_whether_done_or_refused() -> None:
    target = make_target()
    read = ProtectedTypedLogicalRead(FileType.INTEGER, 7, 0, 0, 2)
    assert run(target, read).request == read
    refused = ProtectedTypedLogicalRead(FileType.INTEGER, 11, 0, 0, 2)
    assert run(target, refused).request == refused
    too_big = WordRangeRead(N7(0), 4, packet_offset=1, total=2)
    assert run(target, too_big).request == too_big


def test_a_whole_first_packet_abandons_the_transaction_under_way_and_applies() -> None:
    target = make_target()
    run(target, WordRangeWrite(N7(0), H("01 00"), packet_offset=0, total=2))
    whole = run(target, WordRangeWrite(N7(0), H("07 00 08 00"), packet_offset=0, total=2))
    assert not whole.pending and [t.key for t in whole.abandoned] == [(2, 0x00, 7, 0, 2)]
    assert [target.table[7].value(e) for e in (0, 1)] == [7, 8]


def test_the_diagnostic_status_name_is_11_characters_padded_with_spaces() -> None:
    assert diagnostic_status_reply("ABCDEFGHIJKL")[5:16] == b"ABCDEFGHIJK"
    assert len(diagnostic_status_reply("ABCDEFGHIJKL")) == 24
    assert diagnostic_status_reply("GW")[5:16] == b"GW" + b" " * 9


def test_the_data_table_records_when_each_element_was_written_and_can_forget_it() -> None:
    table = DataTable()
    n7 = table.add(TableFileKind.INTEGER, 7, 3)
    assert table[7] is n7 and (n7.kind, n7.number, n7.count) == (TableFileKind.INTEGER, 7, 3)
    with pytest.raises(ValueError, match="file number 7 is defined twice"):
        table.add(TableFileKind.FLOAT, 7, 1)
    n7.set_value(1, 5, 3.5)
    assert n7.value(1) == 5 and n7.written_at(1) == 3.5
    n7.forget(1)
    assert n7.value(1) is None and n7.written_at(1) is None
    assert n7.read_bytes(2, 2) == (H("00 00"), (1,))
    for element in (3, -1):
        with pytest.raises(IndexError, match=f"N7: element {element} outside 0-2"):
            n7.forget(element)
        with pytest.raises(IndexError, match=f"N7: element {element} outside 0-2"):
            n7.set_value(element, 1, 0.0)
        with pytest.raises(IndexError, match=f"N7: element {element} outside 0-2"):
            n7.value(element)


def test_a_masked_write_at_an_odd_byte_keeps_the_bits_outside_the_mask() -> None:
    """write_bytes: mask[i % 2] over data byte i, the old bits kept where the mask is 0."""
    n7 = TableFile(TableFileKind.INTEGER, 7, 2)
    n7.write_bytes(0, H("34 12 78 56"), 1.0)
    assert n7.write_bytes(1, H("FF FF"), 2.0, mask=H("0F F0")) == (0, 1)
    assert n7.read_bytes(0, 4) == (H("34 1F F8 56"), ())  # byte 1: (12 & F0) | (FF & 0F); byte 2: (78 & 0F) | F0


def test_a_byte_range_of_no_bytes_is_outside_every_file() -> None:
    n7 = TableFile(TableFileKind.INTEGER, 7, 2)
    with pytest.raises(IndexError):
        n7.read_bytes(0, 0)
    with pytest.raises(IndexError):
        n7.write_bytes(0, b"", 0.0)


@pytest.mark.parametrize("spec", ["Nx:2", "N7:x", "N:2", "N7:2:3"])
def test_a_data_table_spec_error_shows_what_a_spec_looks_like(spec: str) -> None:
    with pytest.raises(ValueError, match="expected a spec like N7:100"):
        DataTable.of(spec)
