"""SLC 5/04 DF1 simulator: driven by a host-side Df1DataLink in memory with a fake clock."""

from __future__ import annotations

import asyncio
import struct
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.kinds.df1.sim.slc500 import Slc500Options, Slc500Simulator
from gateway.protocols.df1.address import FileType
from gateway.protocols.df1.framing import (
    ACK_SYMBOL,
    ENQ_SYMBOL,
    NEED_DATA,
    AckReceived,
    Checksum,
    DecoderEvent,
    encode_frame,
)
from gateway.protocols.df1.framing import (
    Frame as WireFrame,
)
from gateway.protocols.df1.framing.decoder import FrameDecoder
from gateway.protocols.df1.full_duplex.datalink import Df1DataLink, MessageReceived
from gateway.protocols.df1.pccc import (
    DataType,
    DiagnosticStatus,
    DiagnosticStatusInfo,
    FileInfo,
    LogicalBinaryAddress,
    PcccHeader,
    PcccReply,
    ProcessorFamily,
    ProcessorMode,
    ProtectedTypedLogicalMaskedWrite,
    ProtectedTypedLogicalRead,
    ProtectedTypedLogicalWrite,
    ReadFileInfo,
    Request,
    SetProcessorMode,
    TnsAllocator,
    TypedRead,
    TypedWrite,
    WordRangeRead,
    decode_reply,
    decode_typed_data,
    encode_command,
    encode_reply,
)
from gateway.sim import create_simulator
from gateway.sim.serve import SimStream

N, F, T, C, R, B, S, OUT, INP = (
    FileType.INTEGER,
    FileType.FLOAT,
    FileType.TIMER,
    FileType.COUNTER,
    FileType.CONTROL,
    FileType.BIT,
    FileType.STATUS,
    FileType.OUTPUT,
    FileType.INPUT,
)


class Bench:
    """A host link wired to the simulator; ``now`` is the fake clock, bytes move instantly."""

    def __init__(self, *, ladder: bool = False, ack_timeout: float = 1.0, **options: str) -> None:
        self.sim = Slc500Simulator.from_options(options, ladder=ladder)
        self.host = Df1DataLink(checksum=self.sim.options.checksum, ack_timeout=ack_timeout)
        self.now = 0.0
        self.tns = TnsAllocator(start=1)
        self.replies: dict[int, list[PcccReply]] = {}
        self.wire: list[bytes] = []  # every output of the simulator

    def _deliver(self, outputs: list[bytes]) -> None:
        for data in outputs:
            self.wire.append(data)
            self.host.receive_data(data, self.now)
        while (event := self.host.next_event()) is not NEED_DATA:
            if isinstance(event, MessageReceived):
                reply = decode_reply(event.payload)
                self.replies.setdefault(reply.tns, []).append(reply)

    def exchange(self) -> None:
        """Move bytes both ways until both sides are quiet."""
        for _ in range(10_000):
            data = self.host.data_to_send()
            outputs = self.sim.receive(data, self.now) if data else []
            assert all(out.delay == 0 for out in outputs)
            self._deliver([out.data for out in outputs])
            if not data and not outputs:
                return
        raise AssertionError("the link never went quiet")

    def run_until(self, until: float) -> None:
        """Run both sides' timers in order up to ``until``."""
        self.exchange()
        while True:
            deadlines = [d for d in (self.sim.next_deadline(), self.host.next_deadline()) if d is not None]
            due = [d for d in deadlines if d <= until]
            if not due:
                break
            self.now = max(self.now, min(due))
            self.host.handle_timeout(self.now)
            self._deliver([out.data for out in self.sim.poll(self.now)])
            self.exchange()
        self.now = max(self.now, until)

    def send_raw(self, packet: bytes) -> None:
        self.host.send(packet, self.now)
        self.exchange()

    def send(self, request: Request, *, dst: int = 1) -> int:
        tns = self.tns.allocate()
        self.send_raw(encode_command(request, dst=dst, src=0, tns=tns))
        return tns

    def wait(self, tns: int, timeout: float = 10.0) -> PcccReply | None:
        end = self.now + timeout
        while tns not in self.replies and self.now < end:
            self.run_until(min(end, self.now + 0.05))
        got = self.replies.get(tns)
        return got[0] if got else None

    def transact(self, request: Request, *, dst: int = 1, timeout: float = 10.0) -> PcccReply | None:
        return self.wait(self.send(request, dst=dst), timeout)

    def ok(self, request: Request) -> bytes:
        reply = self.transact(request)
        assert reply is not None, "no reply"
        assert reply.sts == 0, reply.error()
        return reply.data

    def status(self, request: Request) -> tuple[int, int | None]:
        reply = self.transact(request)
        assert reply is not None, "no reply"
        return reply.sts, reply.ext_sts


def read(file_type: int, file_number: int, element: int, sub: int = 0, size: int = 2) -> ProtectedTypedLogicalRead:
    return ProtectedTypedLogicalRead(file_type, file_number, element, sub, size)


def write(file_type: int, file_number: int, element: int, data: bytes, sub: int = 0) -> ProtectedTypedLogicalWrite:
    return ProtectedTypedLogicalWrite(file_type, file_number, element, sub, data)


def words(*values: int) -> bytes:
    return b"".join((v & 0xFFFF).to_bytes(2, "little") for v in values)


def decode_wire(data: bytes, checksum: Checksum = Checksum.CRC) -> list[DecoderEvent]:
    decoder = FrameDecoder(checksum)
    decoder.feed(data)
    events: list[DecoderEvent] = []
    while (event := decoder.next_event()) is not NEED_DATA:
        events.append(event)
    return events


# ----------------------------------------------------------------------------- identification


def test_diagnostic_status_identifies_an_slc_5_04() -> None:
    bench = Bench()
    info = DiagnosticStatusInfo(bench.ok(DiagnosticStatus()))
    assert info.processor_type == 0x5B
    assert info.family is ProcessorFamily.SLC5_04
    assert info.catalog == "1747-L542"
    assert info.mode_status == ProcessorMode.RUN
    assert bench.sim.counters.commands == {"diagnostic_status": 1}


def test_bcc_link() -> None:
    bench = Bench(checksum="bcc")
    assert bench.sim.link.checksum is Checksum.BCC
    assert DiagnosticStatusInfo(bench.ok(DiagnosticStatus())).processor_type == 0x5B


def test_other_station_number() -> None:
    bench = Bench(station="9")
    assert bench.transact(DiagnosticStatus(), dst=1, timeout=1.0) is None
    assert bench.sim.counters.ignored == 1
    tns = bench.send(DiagnosticStatus(), dst=9)
    info = DiagnosticStatusInfo.build(
        processor_type=0x5B, series="C", frn=3, catalog="1747-L542", mode_status=ProcessorMode.RUN
    )
    # the reply, byte for byte: DST 0 (our SRC), SRC 9, CMD 06 | 40, STS 0, our TNS, the status
    packet = bytes((0x00, 0x09, 0x46, 0x00)) + tns.to_bytes(2, "little") + info.raw
    assert bench.wire == [ACK_SYMBOL, ACK_SYMBOL, encode_frame(packet, Checksum.CRC)]
    assert bench.wait(tns) == decode_reply(packet)


# ---------------------------------------------------------------------------------------- reads


@pytest.mark.parametrize(
    ("request_", "expected"),
    [
        (read(N, 7, 5), words(5)),
        (read(N, 7, 0, size=20), words(*range(10))),
        (read(N, 7, 200, size=6), words(-1, 32767, -32768)),
        (read(N, 7, 255), words(0x1234)),
        (read(F, 8, 3, size=4), struct.pack("<f", 4.5)),
        (read(F, 8, 0, size=12), struct.pack("<3f", 0.0, 1.5, 3.0)),
        (read(T, 4, 1, size=6), words(0, 20, 0)),
        (read(T, 4, 3, sub=1), words(100)),
        (read(C, 5, 0, sub=1), words(100)),
        (read(C, 5, 2, size=6), words(0, 20, 0)),
        (read(R, 6, 2, sub=1), words(30)),
        (read(B, 3, 1, size=4), words(0xA5A5, 1)),
        (read(S, 2, 1), words(0x1806)),
        (read(OUT, 0, 1, sub=2), words(0x0102)),
        (read(OUT, 0, 0, size=32), words(*range(8), *(0x100 + w for w in range(8)))),
        (read(INP, 1, 2, sub=3), words(0x1203)),
        (read(N, 10, 99), words(0)),
        (read(B, 12, 15), words(0)),
        (read(F, 13, 9, size=4), struct.pack("<f", 0.0)),
    ],
    ids=str,
)
def test_protected_typed_logical_read(request_: ProtectedTypedLogicalRead, expected: bytes) -> None:
    assert Bench().ok(request_) == expected


def test_floats_are_little_endian_ieee754_low_word_first() -> None:
    sim = Slc500Simulator(ladder=False)
    assert sim.float_value("F8", 7) == 10.5
    image = sim.file_bytes(FileType.FLOAT, 8)
    assert image[28:32] == struct.pack("<f", 10.5)
    raw = struct.unpack("<I", struct.pack("<f", 10.5))[0]
    assert (sim.word("F8", 7, 0), sim.word("F8", 7, 1)) == (raw & 0xFFFF, raw >> 16)


def test_read_at_max_size() -> None:
    assert Bench().ok(read(N, 7, 0, size=236)) == words(*range(118))


def test_helpers() -> None:
    sim = Slc500Simulator(ladder=False)
    sim.set_word("N7", 3, -2)
    assert sim.word("N7", 3) == 0xFFFE
    sim.set_word("T4", 5, 77, sub=2)
    assert sim.word("T4", 5, 2) == 77
    assert sim.word("O", 3, 7) == sim.word("O0", 3, 7) == 0x0307
    assert sim.word("S", 1) & 0x1F == ProcessorMode.RUN
    sim.set_float("F13", 2, -0.25)
    assert sim.float_value("F13", 2) == -0.25
    assert len(sim.file_bytes(FileType.TIMER, 4)) == 120
    with pytest.raises(KeyError):
        sim.word("N9", 0)
    with pytest.raises(KeyError):
        sim.word("F7", 0)  # file 7 is an integer file
    with pytest.raises(KeyError):
        sim.file_bytes(FileType.BIT, 7)
    with pytest.raises(IndexError):
        sim.word("N10", 100)


# --------------------------------------------------------------------------------------- writes


@pytest.mark.parametrize(
    ("file", "element", "sub", "file_type", "number", "text"),
    [
        ("N7", 5, 0, N, 7, "N7:5"),
        ("N10", 99, 0, N, 10, "N10:99"),
        ("B3", 3, 0, B, 3, "B3:3"),
        ("B12", 15, 0, B, 12, "B12:15"),
        ("T4", 2, 1, T, 4, "T4:2.PRE"),
        ("C5", 1, 2, C, 5, "C5:1.ACC"),
        ("R6", 0, 1, R, 6, "R6:0.LEN"),
        ("S2", 5, 0, S, 2, "S:5"),
        ("O0", 1, 3, OUT, 0, "O:1.3"),
        ("I1", 0, 0, INP, 1, "I:0.0"),
    ],
)
def test_protected_typed_logical_write(
    file: str, element: int, sub: int, file_type: FileType, number: int, text: str
) -> None:
    bench = Bench()
    assert bench.ok(write(file_type, number, element, words(0x4321), sub=sub)) == b""
    assert bench.sim.word(file, element, sub) == 0x4321
    assert bench.ok(read(file_type, number, element, sub)) == words(0x4321)
    assert bench.sim.applied_writes == [("write", text, words(0x4321))]
    assert bench.sim.counters.commands == {"write": 1, "read": 1}


def test_write_floats_and_structures() -> None:
    bench = Bench()
    bench.ok(write(F, 8, 2, struct.pack("<2f", -7.25, 1e6)))
    assert (bench.sim.float_value("F8", 2), bench.sim.float_value("F8", 3)) == (-7.25, 1e6)
    bench.ok(write(F, 13, 9, struct.pack("<f", 3.5)))
    assert bench.sim.float_value("F13", 9) == 3.5
    bench.ok(write(T, 4, 10, words(0, 500, 250, 0, 600, 300)))
    assert [bench.sim.word("T4", 11, sub) for sub in range(3)] == [0, 600, 300]
    assert [entry[1] for entry in bench.sim.applied_writes] == ["F8:2", "F13:9", "T4:10"]


def test_masked_write_changes_only_masked_bits() -> None:
    bench = Bench()
    bench.sim.set_word("N7", 10, 0x0F0F)
    bench.sim.set_word("N7", 11, 0x1234)
    bench.ok(ProtectedTypedLogicalMaskedWrite(N, 7, 10, 0, 0x00F0, words(0xFFFF, 0x0000)))
    assert bench.sim.word("N7", 10) == 0x0FFF
    assert bench.sim.word("N7", 11) == 0x1204  # the same mask applies to every word
    assert bench.sim.word("N7", 12) == 12
    assert bench.sim.applied_writes == [("masked_write", "N7:10", words(0xFFFF, 0))]


def test_masked_write_sets_and_clears_one_bit() -> None:
    bench = Bench()
    bench.ok(ProtectedTypedLogicalMaskedWrite(B, 3, 1, 0, 1 << 9, words(1 << 9)))
    assert bench.sim.word("B3", 1) == 0xA5A5 | 1 << 9
    bench.ok(ProtectedTypedLogicalMaskedWrite(B, 3, 1, 0, 1 << 0, words(0)))
    assert bench.sim.word("B3", 1) == (0xA5A5 | 1 << 9) & ~1
    bench.ok(ProtectedTypedLogicalMaskedWrite(T, 4, 7, 0, 1 << 13, words(0xFFFF)))  # T4:7/DN
    assert bench.sim.word("T4", 7) == 1 << 13


def test_masked_write_odd_size_uses_the_low_mask_byte() -> None:
    bench = Bench()
    bench.sim.set_word("N7", 20, 0x0000)
    bench.sim.set_word("N7", 21, 0x0000)
    bench.ok(ProtectedTypedLogicalMaskedWrite(N, 7, 20, 0, 0xF00F, b"\xff\xff\xff"))
    assert bench.sim.word("N7", 20) == 0xF00F
    assert bench.sim.word("N7", 21) == 0x000F


# ---------------------------------------------------------------------------- typed read/write


def test_typed_read_integer_and_float() -> None:
    bench = Bench()
    typed = decode_typed_data(bench.ok(TypedRead(LogicalBinaryAddress.for_element(7, 2), 4)))
    assert (typed.data_type, typed.element_size, typed.data) == (DataType.INTEGER, 2, words(2, 3, 4, 5))
    typed = decode_typed_data(bench.ok(TypedRead(LogicalBinaryAddress.for_element(8, 1), 2)))
    assert (typed.data_type, typed.element_size, typed.data) == (DataType.FLOAT, 4, struct.pack("<2f", 1.5, 3.0))
    typed = decode_typed_data(bench.ok(TypedRead(LogicalBinaryAddress.for_element(4, 0), 1)))
    assert (typed.data_type, typed.element_size, typed.data) == (DataType.TIMER, 6, words(0, 10, 0))
    # three levels (file, element, sub-element) without the section
    typed = decode_typed_data(bench.ok(TypedRead(LogicalBinaryAddress(0x0E, (7, 9, 0)), 1)))
    assert typed.data == words(9)


def test_typed_write() -> None:
    bench = Bench()
    bench.ok(TypedWrite(LogicalBinaryAddress.for_element(7, 30), DataType.INTEGER, 2, words(-5, 6)))
    assert (bench.sim.word("N7", 30), bench.sim.word("N7", 31)) == (0xFFFB, 6)
    bench.ok(TypedWrite(LogicalBinaryAddress.for_element(13, 0), DataType.FLOAT, 4, struct.pack("<f", 2.75)))
    assert bench.sim.float_value("F13", 0) == 2.75
    assert bench.sim.applied_writes == [
        ("typed_write", "N7:30", words(-5, 6)),
        ("typed_write", "F13:0", struct.pack("<f", 2.75)),
    ]


@pytest.mark.parametrize(
    ("request_", "ext_sts"),
    [
        (TypedRead(LogicalBinaryAddress.for_element(1, 0), 1), 0x06),  # no typed access to inputs
        (TypedRead(LogicalBinaryAddress.for_element(9, 0), 1), 0x06),  # no file 9
        (TypedRead(LogicalBinaryAddress.for_element(7, 256), 1), 0x06),
        (TypedRead(LogicalBinaryAddress.for_element(7, 250), 10), 0x07),
        (TypedRead(LogicalBinaryAddress.for_element(7, 0), 119), 0x09),
        (TypedRead(LogicalBinaryAddress.for_element(4, 0, 2), 1), 0x06),  # no sub-element addressing
        (TypedRead(LogicalBinaryAddress(0x04, (3,)), 1), 0x02),  # no file level
        (TypedRead(LogicalBinaryAddress(0x1F, (0, 7, 0, 0, 0)), 1), 0x03),
        (TypedWrite(LogicalBinaryAddress.for_element(0, 0), DataType.INTEGER, 2, words(1)), 0x06),  # outputs
        (TypedWrite(LogicalBinaryAddress.for_element(7, 0), DataType.FLOAT, 4, b"\0\0\0\0"), 0x11),
        (TypedWrite(LogicalBinaryAddress.for_element(8, 0), DataType.INTEGER, 2, words(1)), 0x11),
    ],
    ids=str,
)
def test_typed_errors(request_: Request, ext_sts: int) -> None:
    bench = Bench()
    assert bench.status(request_) == (0xF0, ext_sts)
    assert bench.sim.applied_writes == []


# ---------------------------------------------------------------------------- file info, mode


@pytest.mark.parametrize(
    ("number", "info"),
    [
        (7, FileInfo(512, 256, 0x89)),
        (4, FileInfo(120, 20, 0x86)),
        (8, FileInfo(256, 64, 0x8A)),
        (2, FileInfo(328, 164, 0x84)),
        (0, FileInfo(64, 32, 0x8B)),
        (13, FileInfo(40, 10, 0x8A)),
    ],
)
def test_read_file_info(number: int, info: FileInfo) -> None:
    assert FileInfo.decode(Bench().ok(ReadFileInfo(number))) == info


def test_read_file_info_of_a_missing_file() -> None:
    assert Bench().status(ReadFileInfo(9)) == (0x50, None)


def test_set_processor_mode() -> None:
    bench = Bench(ladder=True)
    bench.ok(SetProcessorMode(ProcessorMode.PROGRAM))
    assert bench.sim.mode == ProcessorMode.PROGRAM
    assert bench.sim.word("S2", 1) == 0x1800 | ProcessorMode.PROGRAM
    # data reads and writes still work in program mode; the ladder stops
    bench.ok(write(N, 7, 1, words(99)))
    before = bench.sim.word("N7", 0)
    bench.run_until(bench.now + 2.0)
    assert bench.ok(read(N, 7, 0, size=4)) == words(before, 99)
    assert DiagnosticStatusInfo(bench.ok(DiagnosticStatus())).mode_status == ProcessorMode.PROGRAM
    bench.ok(SetProcessorMode(ProcessorMode.RUN))
    assert bench.sim.mode == ProcessorMode.RUN
    assert bench.status(SetProcessorMode(0x05)) == (0x10, None)
    assert [entry for entry in bench.sim.applied_writes if entry[0] == "mode"] == [
        ("mode", "S:1", b"\x01"),
        ("mode", "S:1", b"\x06"),
    ]


# ---------------------------------------------------------------------------------------- errors


@pytest.mark.parametrize(
    ("request_", "status"),
    [
        (read(N, 9, 0), (0xF0, 0x06)),  # no file 9
        (read(B, 7, 0), (0xF0, 0x06)),  # file 7 is not a bit file
        (read(0x8D, 7, 0), (0xF0, 0x06)),
        (read(N, 7, 256), (0xF0, 0x06)),
        (read(N, 10, 100), (0xF0, 0x06)),
        (read(T, 4, 0, sub=3), (0xF0, 0x06)),
        (read(OUT, 0, 4), (0xF0, 0x06)),  # slots 0-3
        (read(OUT, 0, 0, sub=8), (0xF0, 0x06)),
        (read(N, 10, 99, size=4), (0xF0, 0x07)),  # runs past the end
        (read(F, 8, 63, size=8), (0xF0, 0x07)),
        (read(N, 7, 0, size=237), (0xF0, 0x09)),
        (write(N, 7, 0, bytes(229)), (0xF0, 0x09)),
        (write(N, 7, 255, bytes(228)), (0xF0, 0x09)),  # a 3-byte element field costs 2 bytes
        (write(N, 10, 99, words(1, 2)), (0xF0, 0x07)),
        (write(N, 11, 0, words(1)), (0xF0, 0x06)),
        (ProtectedTypedLogicalMaskedWrite(N, 7, 256, 0, 0xFFFF, words(1)), (0xF0, 0x06)),
        (ProtectedTypedLogicalMaskedWrite(N, 7, 0, 0, 0xFFFF, bytes(229)), (0xF0, 0x09)),
        (WordRangeRead(LogicalBinaryAddress.for_element(7, 0), 2), (0x10, None)),  # PLC-5 only
    ],
    ids=str,
)
def test_refusals(request_: Request, status: tuple[int, int | None]) -> None:
    bench = Bench()
    before = bench.sim.file_bytes(N, 7)
    assert bench.status(request_) == status
    assert bench.sim.applied_writes == []
    assert bench.sim.file_bytes(N, 7) == before
    assert bench.sim.counters.refusals == 1


def test_write_at_the_limit_with_one_byte_fields() -> None:
    bench = Bench()
    bench.ok(write(N, 7, 0, words(*range(1000, 1114))))
    assert bench.sim.word("N7", 113) == 1113


@pytest.mark.parametrize(
    "body",
    [
        b"\x0f\x00\x01\x00\x17",  # CMD 0F FNC 17: read bytes physical, not supported
        b"\x07\x00\x01\x00\x03",  # CMD 07
        b"\x0f\x00\x01\x00\xa2\x02\x07",  # truncated protected typed logical read
        b"\x0f\x00\x01\x00\xa2\x00\x07\x89\x00\x00",  # size 0
        b"\x0f\x00\x01\x00\x80\x01\x02",  # trailing byte after the mode
    ],
)
def test_unsupported_and_malformed_commands_get_sts_10(body: bytes) -> None:
    bench = Bench()
    packet = bytes((1, 0)) + body  # DST SRC CMD STS TNS ...
    bench.send_raw(packet)
    reply = bench.wait(0x0001)
    assert reply is not None
    assert (reply.sts, reply.ext_sts, reply.cmd) == (0x10, None, packet[2] | 0x40)


def test_replies_are_ignored_and_runt_packets_naked() -> None:
    bench = Bench()
    bench.send_raw(b"\x01\x00\x4f\x00\x05\x00")  # a reply addressed to us: ACKed, no answer
    bench.send_raw(b"\x01\x00\x0f")  # shorter than a header: "too small", DLE NAK (1770-6.5.16 p. 4-8)
    bench.run_until(2.0)
    assert bench.replies == {}
    assert bench.sim.counters.ignored == 1
    assert bench.sim.link.counters.acks_sent == 1  # the host sends the runt again after each NAK:
    assert bench.sim.link.counters.bad_frames == 1 + bench.host.nak_limit


# ---------------------------------------------------------------------------- link behaviour


def test_duplicate_frame_is_acked_but_executed_once() -> None:
    sim = Slc500Simulator(ladder=False)
    frame = encode_frame(encode_command(write(N, 7, 40, words(7)), dst=1, src=0, tns=0x0102), Checksum.CRC)
    wire = b"".join(out.data for out in sim.receive(frame + frame, 0.0))
    events = decode_wire(wire)
    assert sum(1 for e in events if isinstance(e, WireFrame)) == 1
    assert sum(1 for e in events if isinstance(e, AckReceived)) == 2
    assert sim.applied_writes == [("write", "N7:40", words(7))]
    assert (sim.counters.frames_received, sim.counters.duplicates_received) == (2, 1)


def test_host_resends_after_a_lost_ack_and_the_write_happens_once() -> None:
    bench = Bench()
    tns = bench.tns.allocate()
    packet = encode_command(write(N, 7, 41, words(8)), dst=1, src=0, tns=tns)
    # the same frame twice, as a host that missed our ACK and sent it again
    for _ in range(2):
        bench._deliver([out.data for out in bench.sim.receive(encode_frame(packet, Checksum.CRC), bench.now)])
    bench.run_until(3.0)
    assert bench.sim.applied_writes == [("write", "N7:41", words(8))]
    assert len(bench.replies[tns]) == 1


def test_frames_split_anywhere_and_trailing_bytes() -> None:
    packet = encode_command(read(N, 7, 3, size=4), dst=1, src=0, tns=9)
    frame = encode_frame(packet, Checksum.CRC)
    whole = Slc500Simulator(ladder=False)
    expected = b"".join(out.data for out in whole.receive(frame, 0.0))
    piecewise = Slc500Simulator(ladder=False)
    got = b"".join(b"".join(out.data for out in piecewise.receive(frame[i : i + 1], 0.0)) for i in range(len(frame)))
    assert got == expected
    trailing = Slc500Simulator(ladder=False)
    got = b"".join(out.data for out in trailing.receive(frame + b"\x10\x02\x01", 0.0))
    assert got == expected
    frames = [e for e in decode_wire(expected) if isinstance(e, WireFrame)]
    assert decode_reply(frames[0].message).data == words(3, 4)


def test_unacknowledged_reply_is_enquired_then_given_up() -> None:
    sim = Slc500Simulator.from_options({"link_ack_timeout": "0.25"}, ladder=False)
    frame = encode_frame(encode_command(DiagnosticStatus(), dst=1, src=0, tns=1), Checksum.CRC)
    outputs = sim.receive(frame, 0.0)
    assert outputs[0].data == ACK_SYMBOL
    assert sim.next_deadline() == 0.25
    assert [out.data for out in sim.poll(0.1)] == []
    assert [out.data for out in sim.poll(0.25)] == [ENQ_SYMBOL]
    now = 0.25
    for _ in range(5):
        deadline = sim.next_deadline()
        if deadline is None:
            break
        now = deadline
        sim.poll(now)
    assert sim.next_deadline() is None
    assert sim.counters.replies_failed == 1


def test_nak_makes_the_simulator_retransmit() -> None:
    sim = Slc500Simulator(ladder=False)
    frame = encode_frame(encode_command(DiagnosticStatus(), dst=1, src=0, tns=1), Checksum.CRC)
    outputs = sim.receive(frame, 0.0)
    reply_frame = outputs[-1].data
    assert [out.data for out in sim.receive(b"\x10\x15", 0.1)] == [reply_frame]
    assert sim.receive(b"\x10\x06", 0.2) == []
    assert sim.counters.replies_acked == 1


# ---------------------------------------------------------------------------------------- ladder


def test_ladder_timers_counter_and_clock() -> None:
    sim = Slc500Simulator(ladder=True)
    sim.poll(0.0)  # the ladder starts
    sim.poll(1.0)  # 10 scans
    assert [sim.word("T4", k, 2) for k in range(4)] == [10, 10, 10, 10]
    assert sim.word("T4", 0) & (1 << 13)  # T4:0/DN at PRE 10
    assert sim.word("T4", 1) & (1 << 15 | 1 << 14) == 1 << 15 | 1 << 14  # EN, TT
    assert not sim.word("T4", 1) & (1 << 13)
    assert sim.word("N7", 0) == 10
    assert sim.word("B3", 0) & 1 == 0  # toggled 10 times
    assert sim.word("C5", 0, 2) == 5  # 5 rising edges
    sim.poll(1.05)
    assert sim.word("N7", 0) == 10
    sim.poll(1.1)
    assert (sim.word("N7", 0), sim.word("B3", 0) & 1, sim.word("C5", 0, 2)) == (11, 1, 6)
    sim.poll(100.0)
    assert [sim.word("T4", k, 2) for k in range(4)] == [10, 20, 50, 100]
    assert all(sim.word("T4", k) & (1 << 13) for k in range(4))
    assert sim.word("C5", 0) & (1 << 13)  # DN: ACC >= PRE 100
    assert sim.word("T4", 4, 2) == 0  # not in the ladder
    assert sim.word("N7", 1) == 1


def test_ladder_counter_overflow_and_n7_wrap() -> None:
    sim = Slc500Simulator(ladder=True)
    sim.set_word("C5", 0, 32766, sub=2)
    sim.set_word("N7", 0, 0xFFFE)
    sim.poll(0.0)
    sim.poll(0.6)  # 6 scans, 3 rising edges
    assert sim.word("N7", 0) == 4
    assert sim.word("C5", 0, 2) == (32766 + 3 - 65536) & 0xFFFF
    assert sim.word("C5", 0) & (1 << 12)  # OV


def test_ladder_off_freezes_everything() -> None:
    sim = Slc500Simulator(ladder=False)
    images = {n: sim.file_bytes(t, n) for n, t in ((3, B), (4, T), (5, C), (7, N))}
    sim.poll(0.0)
    sim.poll(50.0)
    assert {n: sim.file_bytes(t, n) for n, t in ((3, B), (4, T), (5, C), (7, N))} == images


def test_ladder_seen_through_reads() -> None:
    bench = Bench(ladder=True)
    first = int.from_bytes(bench.ok(read(N, 7, 0)), "little")
    bench.run_until(bench.now + 0.5)
    second = int.from_bytes(bench.ok(read(N, 7, 0)), "little")
    assert second - first == 5


# ------------------------------------------------------------------------------ fault injection


def run_writes(bench: Bench, count: int, *, timeout: float = 10.0) -> list[int]:
    """``count`` writes one after another; returns the TNS of those answered."""
    answered = []
    for k in range(count):
        tns = bench.send(write(N, 10, k % 100, words(k)))
        if bench.wait(tns, timeout) is not None:
            answered.append(tns)
    return answered


def assert_exactly_once(bench: Bench, count: int) -> None:
    writes = bench.sim.applied_writes
    assert [(kind, data) for kind, _, data in writes] == [("write", words(k)) for k in range(count)]


@pytest.mark.parametrize("option", ["corrupt", "garble"])
def test_corrupt_frames_are_naked_and_retransmitted(option: str) -> None:
    bench = Bench(corrupt="3", seed="5") if option == "corrupt" else Bench(garble="3", seed="5")
    answered = run_writes(bench, 30)
    assert len(answered) == 30
    assert bench.sim.counters.corrupted > 0
    assert bench.host.counters.naks_sent >= bench.sim.counters.corrupted
    assert bench.sim.link.counters.retransmissions >= bench.sim.counters.corrupted
    assert_exactly_once(bench, 30)


def test_corrupt_every_frame_still_delivers_every_reply() -> None:
    bench = Bench(corrupt="1")
    assert len(run_writes(bench, 5)) == 5
    assert bench.sim.counters.corrupted == bench.host.counters.naks_sent == 5
    assert bench.sim.link.counters.retransmissions == 5


def test_corrupt_with_bcc() -> None:
    bench = Bench(checksum="bcc", corrupt="2", seed="3")
    assert len(run_writes(bench, 20)) == 20
    assert bench.host.counters.bad_frames == bench.sim.counters.corrupted > 0


def test_drop_executes_but_never_answers() -> None:
    bench = Bench(drop="3", seed="2")
    answered = run_writes(bench, 30, timeout=2.0)
    dropped = bench.sim.counters.dropped
    assert 0 < dropped < 30
    assert len(answered) == 30 - dropped
    assert bench.sim.counters.replies_sent == 30 - dropped
    assert_exactly_once(bench, 30)


def test_withheld_acks_are_recovered_by_enq() -> None:
    bench = Bench(withhold_ack="2", seed="4")
    assert len(run_writes(bench, 20)) == 20
    bench.run_until(bench.now + 5.0)  # the last command may still wait for its ACK
    withheld = bench.sim.counters.withheld_acks
    assert withheld > 0
    assert bench.host.counters.enqs_sent == withheld
    assert bench.host.counters.retransmissions == 0
    assert bench.host.counters.send_failures == 0
    assert_exactly_once(bench, 20)


def test_duplicated_frames_are_discarded_by_the_host() -> None:
    bench = Bench(duplicate="2", seed="6")
    answered = run_writes(bench, 20)
    assert len(answered) == 20
    assert bench.sim.counters.duplicates > 0
    assert bench.host.counters.duplicates == bench.sim.counters.duplicates
    assert all(len(bench.replies[tns]) == 1 for tns in answered)


def test_noise_is_ignored_by_the_host() -> None:
    bench = Bench(noise="2", seed="7")
    assert len(run_writes(bench, 20)) == 20
    assert bench.sim.counters.noise > 0
    noisy = [out for out in bench.wire if out[0] != 0x10]
    assert len(noisy) == bench.sim.counters.noise
    assert all(1 <= out.index(0x10) <= 8 for out in noisy)  # 1-8 bytes, none of them DLE
    assert bench.host.counters.bad_frames == 0
    assert_exactly_once(bench, 20)


def test_delay_holds_the_reply() -> None:
    bench = Bench(delay="0.3")
    tns = bench.send(DiagnosticStatus())
    assert bench.sim.next_deadline() == pytest.approx(0.3)
    bench.run_until(0.29)
    assert tns not in bench.replies
    bench.run_until(0.31)
    assert tns in bench.replies


def test_every_fault_at_once() -> None:
    bench = Bench(corrupt="6", withhold_ack="5", duplicate="5", noise="3", seed="11")
    answered = run_writes(bench, 60)
    counters = bench.sim.counters
    assert min(counters.corrupted, counters.withheld_acks, counters.duplicates, counters.noise) > 0
    assert len(answered) == 60
    assert_exactly_once(bench, 60)
    for k in range(60):
        assert bench.sim.word("N10", k) == k


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    corrupt=st.integers(0, 4),
    withhold_ack=st.integers(0, 4),
    duplicate=st.integers(0, 4),
    noise=st.integers(0, 4),
    checksum=st.sampled_from(["bcc", "crc"]),
)
def test_faults_never_lose_or_repeat_a_write(
    seed: int, corrupt: int, withhold_ack: int, duplicate: int, noise: int, checksum: str
) -> None:
    bench = Bench(
        seed=str(seed),
        corrupt=str(corrupt),
        withhold_ack=str(withhold_ack),
        duplicate=str(duplicate),
        noise=str(noise),
        checksum=checksum,
    )
    assert len(run_writes(bench, 12)) == 12
    assert_exactly_once(bench, 12)
    assert bench.sim.counters.replies_failed == 0


# --------------------------------------------------------------------------------------- options


def test_options_defaults_and_aliases() -> None:
    assert Slc500Options.from_options({}) == Slc500Options()
    options = Slc500Options.from_options(
        {
            "checksum": "BCC",
            "station": "5",
            "garble": "4",
            "drop": "5",
            "withhold_ack": "6",
            "duplicate": "7",
            "noise": "8",
            "delay": "0.25",
            "seed": "42",
            "link_ack_timeout": "2",
        }
    )
    assert options == Slc500Options(Checksum.BCC, 5, 4, 5, 6, 7, 8, 0.25, 42, 2.0)
    sim = Slc500Simulator.from_options({"corrupt": "3"}, ladder=False)
    assert sim.options.corrupt == 3
    assert sim.link.ack_timeout == 0.5
    assert not sim.ladder


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"bogus": "1"}, "unknown"),
        ({"power_cycle_every": "3"}, "unknown"),
        ({"corrupt": "x"}, "corrupt"),
        ({"drop": "-1"}, "drop"),
        ({"noise": "1.5"}, "noise"),
        ({"checksum": "xor"}, "checksum"),
        ({"station": "255"}, "station"),
        ({"delay": "-0.1"}, "delay"),
        ({"delay": "nan"}, "delay"),
        ({"link_ack_timeout": "0"}, "link_ack_timeout"),
        ({"seed": ""}, "seed"),
        ({"garble": "2", "corrupt": "3"}, "garble"),
    ],
)
def test_bad_options_are_rejected(options: dict[str, str], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        Slc500Simulator.from_options(options)


def test_create_simulator() -> None:
    sim = create_simulator("slc504", {"checksum": "bcc", "ladder": "0", "drop": "9"})
    assert isinstance(sim, Slc500Simulator)
    assert sim.options.checksum is Checksum.BCC
    assert sim.options.drop == 9
    assert not sim.ladder


# ------------------------------------------------------------------------------ real in-process


async def test_through_sim_stream() -> None:
    loop = asyncio.get_running_loop()
    sim = Slc500Simulator.from_options({"delay": "0.01", "noise": "2", "duplicate": "2"}, ladder=True)
    stream = SimStream(sim)
    host = Df1DataLink(checksum=Checksum.CRC, ack_timeout=0.5)
    tns = TnsAllocator(start=1)
    try:

        async def transact(request: Request) -> PcccReply:
            number = tns.allocate()
            host.send(encode_command(request, dst=1, src=0, tns=number), loop.time())
            stream.write(host.data_to_send())
            async with asyncio.timeout(5):
                while True:
                    host.receive_data(await stream.read(), loop.time())
                    out = host.data_to_send()
                    if out:
                        stream.write(out)
                    while (event := host.next_event()) is not NEED_DATA:
                        if isinstance(event, MessageReceived):
                            reply = decode_reply(event.payload)
                            if reply.tns == number:
                                return reply

        info = DiagnosticStatusInfo((await transact(DiagnosticStatus())).data)
        assert info.family is ProcessorFamily.SLC5_04
        assert (await transact(write(N, 7, 50, words(-3)))).ok
        reply = await transact(read(N, 7, 50, size=2))
        assert reply.data == words(-3)
        assert sim.applied_writes == [("write", "N7:50", words(-3))]
    finally:
        await stream.close()


# ------------------------------------------------------------------ variants: one per reading


NAK = b"\x10\x15"


def wire_of(outputs: list[Any]) -> list[bytes]:
    return [out.data for out in outputs]


def command_frame(request: Request, tns: int, checksum: Checksum = Checksum.CRC) -> bytes:
    return encode_frame(encode_command(request, dst=1, src=0, tns=tns), checksum)


def reply_frame(frame: bytes, data: bytes = b"") -> bytes:
    [event] = decode_wire(frame)
    assert isinstance(event, WireFrame)
    return encode_frame(encode_reply(PcccHeader.decode(event.message), data=data), Checksum.CRC)


def variant_sim(**variants: str) -> Slc500Simulator:
    return Slc500Simulator(Slc500Options(link_ack_timeout=0.5), ladder=False, variants=variants)


def test_variants_table_defaults_and_bad_names() -> None:
    assert Slc500Simulator.VARIANTS == {
        "duplicate_detect": ("on", "off"),
        "duplicate_reply": ("ack_only", "resend"),
        "ack_order": ("ack_first", "reply_first", "embedded"),
        "bad_frame": ("nak", "silence", "ignore"),
        "enq_answer": ("last", "nak"),
        "reply_addresses": ("swapped", "unswapped", "own_station"),
    }
    assert variant_sim().variants == {name: values[0] for name, values in Slc500Simulator.VARIANTS.items()}
    with pytest.raises(ValueError, match="unknown variant 'dup'"):
        variant_sim(dup="on")
    with pytest.raises(ValueError, match="is not one of on, off"):
        variant_sim(duplicate_detect="maybe")
    sim = Slc500Simulator.from_options({"drop": "3"}, variants={"ack_order": "reply_first"})
    assert sim.variants["ack_order"] == "reply_first" and sim.options.drop == 3


@pytest.mark.parametrize(("detect", "runs"), [("on", 1), ("off", 2)])
def test_duplicate_detection_on_drops_a_resent_write_off_runs_it_again(detect: str, runs: int) -> None:
    sim = variant_sim(duplicate_detect=detect)
    frame = command_frame(write(N, 7, 3, b"\x01\x00"), tns=5)
    first = wire_of(sim.receive(frame, 0.0))
    assert first == [ACK_SYMBOL, reply_frame(frame)]
    sim.receive(ACK_SYMBOL, 0.0)
    second = wire_of(sim.receive(frame, 0.1))
    assert second == ([ACK_SYMBOL] if detect == "on" else [ACK_SYMBOL, reply_frame(frame)])
    assert sim.applied_writes == [("write", "N7:3", b"\x01\x00")] * runs
    assert sim.counters.duplicates_received == (1 if detect == "on" else 0)


def test_duplicate_reply_resend_answers_a_duplicate_with_the_last_reply_again() -> None:
    sim = variant_sim(duplicate_reply="resend")
    frame = command_frame(write(N, 7, 3, b"\x01\x00"), tns=5)
    sim.receive(frame, 0.0)
    sim.receive(ACK_SYMBOL, 0.0)
    assert wire_of(sim.receive(frame, 0.1)) == [ACK_SYMBOL, reply_frame(frame)]
    assert sim.applied_writes == [("write", "N7:3", b"\x01\x00")]  # still executed once
    assert sim.counters.replies_resent == 1


@pytest.mark.parametrize("order", ["ack_first", "reply_first", "embedded"])
def test_ack_order(order: str) -> None:
    sim = variant_sim(ack_order=order)
    frame = command_frame(read(N, 7, 5), tns=9)
    reply = reply_frame(frame, words(5))
    expected = {
        "ack_first": [ACK_SYMBOL, reply],
        "reply_first": [reply, ACK_SYMBOL],
        "embedded": [reply[:2] + ACK_SYMBOL + reply[2:]],
    }[order]
    assert wire_of(sim.receive(frame, 0.0)) == expected


def test_reply_first_with_a_dropped_reply_still_acks() -> None:
    sim = Slc500Simulator(Slc500Options(drop=1), ladder=False, variants={"ack_order": "reply_first"})
    assert wire_of(sim.receive(command_frame(read(N, 7, 5), tns=9), 0.0)) == [ACK_SYMBOL]


def test_reply_first_with_a_turnaround_acks_after_the_reply() -> None:
    sim = Slc500Simulator(Slc500Options(delay=0.2), ladder=False, variants={"ack_order": "reply_first"})
    frame = command_frame(read(N, 7, 5), tns=9)
    assert wire_of(sim.receive(frame, 0.0)) == []
    assert wire_of(sim.poll(0.2)) == [reply_frame(frame, words(5)), ACK_SYMBOL]


def damaged(frame: bytes) -> bytes:
    body = bytearray(frame)
    body[8] ^= 0x01  # a message byte (not a DLE): the CRC no longer matches
    return bytes(body)


@pytest.mark.parametrize(
    ("answer", "at_once", "on_enq"),
    [("nak", [NAK], [NAK]), ("silence", [], [NAK]), ("ignore", [], [ACK_SYMBOL])],
)
def test_bad_frame_readings(answer: str, at_once: list[bytes], on_enq: list[bytes]) -> None:
    sim = variant_sim(bad_frame=answer)
    good = command_frame(read(N, 7, 5), tns=1)
    sim.receive(good, 0.0)  # the last response is now DLE ACK
    sim.receive(ACK_SYMBOL, 0.0)
    bad = damaged(command_frame(write(N, 7, 3, b"\x01\x00"), tns=2))
    assert wire_of(sim.receive(bad, 0.1)) == at_once
    assert wire_of(sim.receive(ENQ_SYMBOL, 0.2)) == on_enq
    assert sim.applied_writes == [] and sim.link.counters.bad_frames == 1


@pytest.mark.parametrize(("answer", "expected"), [("last", ACK_SYMBOL), ("nak", NAK)])
def test_enq_answer(answer: str, expected: bytes) -> None:
    sim = variant_sim(enq_answer=answer)
    sim.receive(command_frame(read(N, 7, 5), tns=1), 0.0)
    sim.receive(ACK_SYMBOL, 0.0)
    assert wire_of(sim.receive(ENQ_SYMBOL, 0.1)) == [expected]


def test_inbound_faults_lose_and_damage_frames_from_the_host() -> None:
    lose = Slc500Simulator(Slc500Options(lose_in=1), ladder=False)
    frame = command_frame(write(N, 7, 3, b"\x01\x00"), tns=2)
    assert wire_of(lose.receive(frame[:5], 0.0)) == []  # a partial frame waits for the rest
    assert wire_of(lose.receive(frame[5:], 0.0)) == []
    assert lose.counters.lost_in == 1 and lose.counters.frames_received == 0 and lose.applied_writes == []
    assert wire_of(lose.receive(ENQ_SYMBOL, 0.1)) == [NAK]  # nothing answered yet: DLE NAK
    corrupt = Slc500Simulator(Slc500Options(corrupt_in=1), ladder=False)
    assert wire_of(corrupt.receive(frame, 0.0)) == [NAK]
    assert corrupt.counters.corrupted_in == 1 and corrupt.link.counters.bad_frames == 1


def test_faults_on_writes_spares_reads() -> None:
    sim = Slc500Simulator.from_options({"drop": "1", "lose_in": "0", "faults_on": "writes"}, ladder=False)
    read_frame = command_frame(read(N, 7, 5), tns=1)
    assert wire_of(sim.receive(read_frame, 0.0)) == [ACK_SYMBOL, reply_frame(read_frame, words(5))]
    sim.receive(ACK_SYMBOL, 0.0)
    assert wire_of(sim.receive(command_frame(write(N, 7, 3, b"\x01\x00"), tns=2), 0.1)) == [ACK_SYMBOL]
    assert sim.applied_writes == [("write", "N7:3", b"\x01\x00")] and sim.counters.dropped == 1
    lose = Slc500Simulator.from_options({"lose_in": "1", "faults_on": "writes"}, ladder=False)
    assert wire_of(lose.receive(read_frame, 0.0))[0] == ACK_SYMBOL
    assert wire_of(lose.receive(command_frame(write(N, 7, 3, b"\x01\x00"), tns=2), 0.1)) == []
    with pytest.raises(ValueError, match="faults_on"):
        Slc500Simulator.from_options({"faults_on": "reads"})


def test_the_processor_executes_commands_without_a_link() -> None:
    """``Slc500Processor.execute``: a command packet in, its reply packet out (no DF1 link, no faults)."""
    from gateway.kinds.df1.sim.slc500_processor import Slc500Processor

    processor = Slc500Processor(ladder=False)
    reply = processor.execute(encode_command(read(FileType.INTEGER, 7, 201), dst=1, src=0, tns=0x1234))
    assert reply is not None
    decoded = decode_reply(reply)
    assert (decoded.dst, decoded.src, decoded.tns, decoded.sts, decoded.data) == (0, 1, 0x1234, 0, b"\xff\x7f")
    written = processor.execute(encode_command(write(FileType.INTEGER, 7, 3, b"\x2a\x00"), dst=1, src=0, tns=2))
    assert written is not None and decode_reply(written).sts == 0
    assert processor.word("N7", 3) == 42
    assert processor.applied_writes == [("write", "N7:3", b"\x2a\x00")]
    missing = processor.execute(encode_command(read(FileType.INTEGER, 9, 0), dst=1, src=0, tns=3))
    assert missing is not None and (decode_reply(missing).sts, decode_reply(missing).ext_sts) == (0xF0, 0x06)
    assert processor.execute(encode_command(read(FileType.INTEGER, 7, 0), dst=5, src=0, tns=4)) is None
    assert processor.counters.ignored == 1
