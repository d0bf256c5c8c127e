"""The target link's runner (``gateway/kinds/df1/target/driver.py``) on a real byte stream: the test
is the PLC on a TCP port the runner connects to (``socket://``), and sends it DF1 bytes by hand,
so every symbol and frame of the link is the test's choice (bad frames, DLE NAKs and DLE ENQs,
a withheld DLE ACK, a frame sent twice).

Expected values come from the manuals and the guide: 1770-6.5.16 chapter 4 (full-duplex link
layer) and p. 6-3 (duplicate detection), 1747-RM001G p. 13-52 Table 13.15 (the SLC channel's ENQ
retries: 3), docs/guide/target-mode.md (status block, ``/metrics`` keys, STS of refusals),
docs/guide/status-page-columns.md (a target's line quality) and docs/reference/config.md
(``check_dst``, ``duplicate_detect`` defaults).
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

from gateway.kinds.df1.target.driver import TargetRunner
from gateway.link_health import LineQuality
from gateway.protocols.df1.address import FileType
from gateway.protocols.df1.framing import (
    ACK_SYMBOL,
    ENQ_SYMBOL,
    NAK_SYMBOL,
    NEED_DATA,
    AckReceived,
    Checksum,
    EnqReceived,
    Frame,
    NakReceived,
    encode_frame,
)
from gateway.protocols.df1.framing.decoder import FrameDecoder
from gateway.protocols.df1.pccc import PcccHeader, ProtectedTypedLogicalRead, ProtectedTypedLogicalWrite, encode_command
from gateway.protocols.df1.pccc.target import PcccTarget
from gateway.protocols.df1.pccc.target_table import DataTable
from gateway.streams import SerialSettings
from gateway.transport import open_stream
from tests.waiting import until

from .plc_line import PLC_NODE, STATION

#: the PLC's DLE ACK wait is short here so a lost reply is given up in a fraction of a second
ACK_TIMEOUT = 0.05
#: STS of SLC typed logical commands on a file that does not exist (target-mode.md, "Commands and errors")
STS_NO_FILE = 0x50
#: STS of any command the target does not know (target-mode.md)
STS_ILLEGAL_COMMAND = 0x10
#: the gateway's DLE ENQs for a reply whose DLE ACK does not come (1747-RM001G Table 13.15: ENQ retries 3)
ENQ_RETRIES = 3
Event = AckReceived | NakReceived | EnqReceived | Frame


def write_n7(element: int, value: int, *, tns: int, dst: int = STATION) -> bytes:
    return encode_command(ProtectedTypedLogicalWrite(FileType.INTEGER, 7, element, 0, value.to_bytes(2, "little")),
                          dst=dst, src=PLC_NODE, tns=tns)


def read_n7(element: int, *, tns: int, dst: int = STATION, file: int = 7) -> bytes:
    return encode_command(ProtectedTypedLogicalRead(FileType.INTEGER, file, element, 0, 2), dst=dst, src=PLC_NODE,
                          tns=tns)


class PlcPort:
    """The PLC's end of the line: raw bytes out, the gateway's symbols and frames in."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, checksum: Checksum) -> None:
        self.reader, self.writer, self.checksum = reader, writer, checksum
        self.decoder = FrameDecoder(checksum)

    def send(self, data: bytes) -> None:
        self.writer.write(data)

    def frame(self, packet: bytes) -> bytes:
        return encode_frame(packet, self.checksum)

    async def next(self) -> Event:
        while (event := self.decoder.next_event()) is NEED_DATA:
            data = await asyncio.wait_for(self.reader.read(4096), 5)
            assert data, "the gateway closed the line"
            self.decoder.feed(data)
        assert isinstance(event, AckReceived | NakReceived | EnqReceived | Frame), event
        return event

    async def expect(self, kind: type[Event]) -> Event:
        event = await self.next()
        assert isinstance(event, kind), f"expected {kind.__name__}, the gateway sent {event}"
        return event

    async def reply(self) -> PcccHeader:
        frame = await self.expect(Frame)
        assert isinstance(frame, Frame)
        return PcccHeader.decode(frame.message)

    async def command(self, packet: bytes) -> PcccHeader:
        """Send a command frame: the gateway's DLE ACK, then its reply (not yet ACKed)."""
        self.send(self.frame(packet))
        await self.expect(AckReceived)
        return await self.reply()


@asynccontextmanager
async def target_link(checksum: Checksum = Checksum.CRC, **options: Any) -> AsyncIterator[tuple[TargetRunner, PlcPort]]:
    connections: asyncio.Queue[tuple[asyncio.StreamReader, asyncio.StreamWriter]] = asyncio.Queue()
    server = await asyncio.start_server(lambda r, w: connections.put_nowait((r, w)), "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    runner = TargetRunner(f"socket://127.0.0.1:{port}", **{"settings": SerialSettings(),
                                                             "target": PcccTarget(DataTable.of("N7:10")),
                                                             "station": STATION, "checksum": checksum,
                                                             "ack_timeout": ACK_TIMEOUT, **options})
    try:
        await runner.start()
        reader, writer = await asyncio.wait_for(connections.get(), 5)
        try:
            yield runner, PlcPort(reader, writer, checksum)
        finally:
            writer.close()
    finally:
        await runner.close()
        server.close()
        await server.wait_closed()


async def test_counters_metrics_and_line_quality_of_a_plc_session(tmp_path: Path) -> None:
    """Every number a target link reports, after a session with one of each thing that can happen."""
    trace = tmp_path / "target.trace"
    async with target_link(trace=trace) as (runner, plc):
        # a write, its reply NAKed twice by the PLC: sent again each time (p. 4-6), then ACKed
        assert (await plc.command(write_n7(0, 5, tns=1))).sts == 0
        for _ in range(2):
            plc.send(NAK_SYMBOL)
            assert (await plc.reply()).tns == 1
        plc.send(ACK_SYMBOL)
        # the same frame again (its DLE ACK was lost, p. 4-13): ACKed, not run, no second reply
        plc.send(plc.frame(write_n7(0, 5, tns=1)))
        await plc.expect(AckReceived)
        # a damaged frame: DLE NAK (p. 4-8)
        damaged = bytearray(plc.frame(read_n7(0, tns=2)))
        damaged[-1] ^= 0xFF
        plc.send(bytes(damaged))
        await plc.expect(NakReceived)
        # the frame again, intact; then the PLC's DLE ENQ gets the last response again (p. 4-8)
        reply = await plc.command(read_n7(0, tns=2))
        assert (reply.tns, reply.sts) == (2, 0)
        plc.send(ACK_SYMBOL)
        plc.send(ENQ_SYMBOL)
        await plc.expect(AckReceived)
        # two refusals: a file that does not exist (STS 50), a command the target does not know (STS 10)
        assert (await plc.command(read_n7(0, tns=3, file=99))).sts == STS_NO_FILE
        plc.send(ACK_SYMBOL)
        unknown = bytes([STATION, PLC_NODE, 0x0F, 0x00, 4, 0, 0xEE])
        assert (await plc.command(unknown)).sts == STS_ILLEGAL_COMMAND
        plc.send(ACK_SYMBOL)
        # a reply the PLC never ACKs: a DLE ENQ after each ACK timeout, ENQ_RETRIES of them, then lost
        assert (await plc.command(read_n7(0, tns=5))).sts == 0
        for _ in range(ENQ_RETRIES):
            await plc.expect(EnqReceived)
        await until(lambda: runner.metrics()["target_replies_lost"] == 1, what="the lost reply")

        assert runner.metrics() == {
            "target_commands": 5.0,  # TNS 1, 2, 3, 4, 5: the duplicate and the damaged frame are not commands
            "target_duplicates": 1.0,
            "target_refused": 2.0,
            "target_bad_frames": 1.0,
            "target_naks_sent": 1.0,
            "target_enqs_received": 1.0,
            "target_reply_retransmissions": 2.0,
            "target_replies_lost": 1.0,
        }
        # the status block: 1002 the last STS other than 0, 1005-1006 errors (target-mode.md)
        assert runner.last_sts == STS_ILLEGAL_COMMAND
        assert runner.counters.errors == 2
        # slc_gateway_retries_total by kind (target-mode.md); their sum is the block's 1007-1008
        assert runner.counters.retries_by_kind == {"nak": 2, "enq": ENQ_RETRIES, "enq_received": 1}
        assert runner.counters.retries == 2 + ENQ_RETRIES + 1
        # the status page's line quality of a target (status-page-columns.md)
        assert runner.line_quality() == LineQuality(check_errors=1, timeouts=0, naks=2, retransmits=2, resyncs=None)
    # the trace has one line per chunk of bytes that went out: never a TX line without bytes
    sent = [line.split("  |")[0].split(" TX")[1] for line in trace.read_text().splitlines() if " TX " in line]
    assert sent and all(chunk.strip() for chunk in sent), sent


async def test_nothing_counted_before_the_plc_speaks() -> None:
    async with target_link() as (runner, _plc):
        assert set(runner.metrics().values()) == {0.0}
        assert runner.line_quality() == LineQuality(check_errors=0, timeouts=0, naks=0, retransmits=0)


async def test_defaults_answer_any_dst_and_run_a_repeated_frame_once() -> None:
    """check_dst is false by default (full duplex ignores DST) and duplicate_detect true
    (docs/reference/config.md): a command for station 5 is answered, and sent twice runs once."""
    connections: asyncio.Queue[tuple[asyncio.StreamReader, asyncio.StreamWriter]] = asyncio.Queue()
    server = await asyncio.start_server(lambda r, w: connections.put_nowait((r, w)), "127.0.0.1", 0)
    table = DataTable.of("N7:10")
    runner = TargetRunner(f"socket://127.0.0.1:{server.sockets[0].getsockname()[1]}", settings=SerialSettings(),
                          target=PcccTarget(table), station=STATION, checksum=Checksum.CRC)
    try:
        await runner.start()
        reader, writer = await asyncio.wait_for(connections.get(), 5)
        plc = PlcPort(reader, writer, Checksum.CRC)
        assert (await plc.command(write_n7(3, 11, tns=1, dst=5))).sts == 0
        plc.send(ACK_SYMBOL)
        plc.send(plc.frame(write_n7(3, 11, tns=1, dst=5)))
        await plc.expect(AckReceived)
        reply = await plc.command(read_n7(3, tns=2, dst=5))
        assert reply.tns == 2  # no second reply to TNS 1 came first
        plc.send(ACK_SYMBOL)
        assert runner.metrics()["target_commands"] == 2 and runner.duplicates == 1
        writer.close()
    finally:
        await runner.close()
        server.close()
        await server.wait_closed()


async def test_check_dst_answers_only_the_station() -> None:
    """check_dst: answer only frames whose DST is station; another DST is ACKed (it arrived intact)."""
    async with target_link(check_dst=True) as (runner, plc):
        plc.send(plc.frame(read_n7(0, tns=1, dst=STATION + 1)))
        await plc.expect(AckReceived)
        reply = await plc.command(read_n7(0, tns=2))
        assert reply.tns == 2  # the frame for another station got no reply
        plc.send(ACK_SYMBOL)
        assert runner.metrics()["target_commands"] == 1


async def test_without_duplicate_detect_a_repeated_frame_runs_again() -> None:
    """1770-6.5.16 p. 6-3: only a receiver that detects duplicates ignores a message with the same
    SRC, CMD and TNS; with ``duplicate_detect = false`` the repeated frame is a command again."""
    async with target_link(duplicate_detect=False) as (runner, plc):
        for _ in range(2):
            assert (await plc.command(write_n7(0, 7, tns=1))).tns == 1
            plc.send(ACK_SYMBOL)
        await until(lambda: runner.metrics()["target_commands"] == 2, what="the second command")
        assert runner.duplicates == 0


async def test_bcc_link_answers_in_bcc() -> None:
    """checksum = "bcc": the PLC's BCC frames are taken and the replies carry a BCC (p. 2-6)."""
    async with target_link(Checksum.BCC) as (runner, plc):
        assert (await plc.command(write_n7(1, 42, tns=9))).sts == 0
        plc.send(ACK_SYMBOL)
        reply = await plc.command(read_n7(1, tns=10))
        assert reply.sts == 0
        assert runner.metrics()["target_bad_frames"] == 0


async def test_the_port_is_opened_with_the_links_settings_and_name() -> None:
    """The runner opens its port by the link's opener, with its serial settings and its name."""
    opened: list[tuple[str, SerialSettings, str]] = []

    async def opener(url: str, settings: SerialSettings, **kw: Any) -> Any:
        opened.append((url, settings, kw["link_name"]))
        return await open_stream(url, settings, **kw)

    settings = SerialSettings(baudrate=19200, bytesize=8, parity="N", stopbits=1)
    async with target_link(settings=settings, name="line3-plc", opener=opener) as (runner, plc):
        assert (await plc.command(read_n7(0, tns=1))).sts == 0
        plc.send(ACK_SYMBOL)
        assert opened == [(runner.url, SerialSettings(19200, 8, "N", 1), "line3-plc")]
