"""``Df1Driver`` paired with the simulated SLC 5/04, in-process (``sim://``) and over TCP.

No mocks: the driver talks DF1 full duplex to ``gateway.kinds.df1.sim.slc500`` through a ``SimStream``
or through real sockets on 127.0.0.1 (``serve_tcp`` + ``socket://``, a serial device server in
raw mode).  Every simulator is its own instance (``instance=``/``seed=`` in the URL, or created
directly for TCP), so no two tests share controller state.

Expected values come from the simulator's documented initial data table (N7:k = k, F8:k = 1.5 k,
B3:1 = 0xA5A5 ...) and from its memory (``sim.word``), never from the driver's own decoding.
"""

from __future__ import annotations

import asyncio
import dataclasses
import itertools
import random
import struct
import time
import uuid
from collections import Counter
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from dataclasses import dataclass
from typing import Any
from urllib.parse import urlencode

import pytest

from gateway.errors import LinkDown, LinkTimeout
from gateway.kinds.df1.full.driver import Df1Driver, WriteOutcomeUnknown
from gateway.kinds.df1.sim.slc500 import Slc500Simulator
from gateway.link_health import LineQuality
from gateway.protocols.df1.address import FileType
from gateway.protocols.df1.framing import Checksum
from gateway.protocols.df1.pccc import (
    LogicalBinaryAddress,
    PcccError,
    PcccReply,
    ProcessorFamily,
    ProtectedTypedLogicalMaskedWrite,
    ProtectedTypedLogicalRead,
    ProtectedTypedLogicalWrite,
    ReadFileInfo,
    Request,
    WordRangeRead,
)
from gateway.sim import create_simulator, get_simulator
from gateway.sim.serve import SimStream, close_tcp, serve_tcp
from gateway.sim.variants import variant_matrix
from gateway.streams import SerialSettings

HOST = "127.0.0.1"
N, F, B = FileType.INTEGER, FileType.FLOAT, FileType.BIT
_seeds = itertools.count(1000)


pytestmark = pytest.mark.usefixtures("forget_simulators")


@dataclass
class Controller:
    sim: Slc500Simulator
    url: str
    server: asyncio.Server | None = None

    async def stop(self) -> None:
        """Switch the device server off: listener and connections closed."""
        assert self.server is not None
        await close_tcp(self.server)

    async def restart(self) -> None:
        """The device server comes back on the same port, with the same controller behind it."""
        port = int(self.url.rsplit(":", 1)[1])
        self.server = await serve_tcp(self.sim, HOST, port)


@asynccontextmanager
async def controller(transport: str, **options: Any) -> AsyncIterator[Controller]:
    """A fresh simulated SLC 5/04 (ladder frozen) reached in-process or over TCP."""
    options = {"ladder": "0", "seed": str(next(_seeds)), **{k: str(v) for k, v in options.items()}}
    if transport == "sim":
        url = "sim://slc504?" + urlencode({**options, "instance": uuid.uuid4().hex})
        sim = get_simulator(url)
        assert isinstance(sim, Slc500Simulator)
        yield Controller(sim, url)
        return
    sim = create_simulator("slc504", options)
    assert isinstance(sim, Slc500Simulator)
    server = await serve_tcp(sim, HOST, 0)
    ctl = Controller(sim, f"socket://{HOST}:{server.sockets[0].getsockname()[1]}", server)
    try:
        yield ctl
    finally:
        if ctl.server is not None:
            await close_tcp(ctl.server)


@asynccontextmanager
async def driver_for(ctl: Controller, **options: Any) -> AsyncIterator[Df1Driver]:
    checksum = Checksum(ctl.sim.options.checksum)
    driver = Df1Driver(ctl.url, **{"checksum": checksum, "timeout": 0.5, "retries": 3, **options})
    await driver.start()
    try:
        yield driver
    finally:
        await driver.close()


def read(file_type: FileType, file_number: int, element: int, size: int = 2, sub: int = 0) -> Request:
    return ProtectedTypedLogicalRead(file_type, file_number, element, sub, size)


def write(file_type: FileType, file_number: int, element: int, data: bytes, sub: int = 0) -> Request:
    return ProtectedTypedLogicalWrite(file_type, file_number, element, sub, data)


def words(reply: PcccReply) -> list[int]:
    return [int.from_bytes(reply.data[i : i + 2], "little") for i in range(0, len(reply.data), 2)]


def floats(reply: PcccReply) -> list[float]:
    return list(struct.unpack(f"<{len(reply.data) // 4}f", reply.data))


TRANSPORTS = pytest.mark.parametrize("transport", ["sim", "tcp"])


# --------------------------------------------------------------------------------------------
# Reads and writes


@TRANSPORTS
@pytest.mark.parametrize("checksum", ["crc", "bcc"])
async def test_reads_and_writes_of_n7_f8_and_bits(transport: str, checksum: str) -> None:
    async with controller(transport, checksum=checksum) as ctl, driver_for(ctl) as driver:
        sim = ctl.sim
        assert driver.checksum is Checksum(checksum)
        # N7:k = k, N7:200..202 = -1, 32767, -32768 (initial data table)
        assert words(await driver.execute(read(N, 7, 0, 20))) == list(range(10))
        assert words(await driver.execute(read(N, 7, 200, 6))) == [0xFFFF, 0x7FFF, 0x8000]
        assert words(await driver.execute(read(N, 7, 255))) == [0x1234]
        assert words(await driver.execute(read(N, 7, 0, 236))) == [sim.word("N7", k) for k in range(118)]
        # F8:k = 1.5 k, each 4 bytes little-endian
        assert floats(await driver.execute(read(F, 8, 2, 12))) == [3.0, 4.5, 6.0]
        # B3:1 = 0xA5A5
        assert words(await driver.execute(read(B, 3, 1))) == [0xA5A5]

        await driver.execute(write(N, 7, 5, (-1234 & 0xFFFF).to_bytes(2, "little")))
        assert sim.word("N7", 5) == (-1234 & 0xFFFF)
        await driver.execute(write(F, 8, 2, struct.pack("<f", -2.5)))
        assert sim.float_value("F8", 2) == -2.5
        assert floats(await driver.execute(read(F, 8, 2, 4))) == [-2.5]
        # a masked write changes only the masked bit: set B3:1/1, clear B3:1/0 (0xA5A5 -> 0xA5A6)
        await driver.execute(ProtectedTypedLogicalMaskedWrite(B, 3, 1, 0, 0x0002, (0x0002).to_bytes(2, "little")))
        await driver.execute(ProtectedTypedLogicalMaskedWrite(B, 3, 1, 0, 0x0001, bytes(2)))
        assert sim.word("B3", 1) == 0xA5A6
        assert words(await driver.execute(read(B, 3, 1))) == [0xA5A6]
        # a timer's accumulator: T4:3.ACC is word 2 of element 3
        await driver.execute(write(FileType.TIMER, 4, 3, (77).to_bytes(2, "little"), sub=2))
        assert sim.word("T4", 3, 2) == 77
        assert sim.applied_writes == [
            ("write", "N7:5", (-1234 & 0xFFFF).to_bytes(2, "little")),
            ("write", "F8:2", struct.pack("<f", -2.5)),
            ("masked_write", "B3:1", b"\x02\x00"),
            ("masked_write", "B3:1", b"\x00\x00"),
            ("write", "T4:3.ACC", b"\x4d\x00"),
        ]
        assert driver.available
        assert driver.counters.transactions == 13 and driver.counters.errors == 0


async def test_a_driver_for_the_wrong_checksum_gets_no_answer() -> None:
    async with controller("sim", checksum="bcc") as ctl, driver_for(ctl, checksum=Checksum.CRC, timeout=0.05,
                                                                      retries=1) as driver:
        with pytest.raises(LinkTimeout):
            await driver.execute(read(N, 7, 0))
        assert ctl.sim.counters.frames_received == 0
        assert not driver.available


# --------------------------------------------------------------------------------------------
# Refusals: STS / EXT STS as PcccError with the manual's text


REFUSALS = [
    pytest.param(read(N, 7, 300), 0xF0, 0x06, "Address doesn't point to something usable", id="element-past-end"),
    pytest.param(read(N, 11, 0), 0xF0, 0x06, "Address doesn't point to something usable", id="no-such-file"),
    pytest.param(read(N, 7, 250, 20), 0xF0, 0x07, "File is wrong size", id="runs-past-end"),
    pytest.param(read(N, 7, 0, 238), 0xF0, 0x09, "Data or file is too large", id="too-large"),
    pytest.param(write(N, 7, 256, b"\x01\x00"), 0xF0, 0x06, "Address doesn't point to something usable",
                 id="write-past-end"),
    pytest.param(WordRangeRead(LogicalBinaryAddress.for_element(7, 0), 2), 0x10, None, "Illegal command or format",
                 id="plc5-command"),
]


@TRANSPORTS
@pytest.mark.parametrize(("request_", "sts", "ext_sts", "description"), REFUSALS)
async def test_refusals_raise_pccc_error_with_the_manuals_description(
    transport: str, request_: Request, sts: int, ext_sts: int | None, description: str
) -> None:
    async with controller(transport) as ctl, driver_for(ctl) as driver:
        with pytest.raises(PcccError) as caught:
            await driver.execute(request_, "the command")
        error = caught.value
        assert (error.sts, error.ext_sts) == (sts, ext_sts)
        assert error.description == description
        assert description in str(error) and "the command" in str(error)
        assert driver.last_sts == sts
        assert driver.counters.refusals == 1
        # A refusal is an answer: the link is up and the next command works.
        assert driver.available
        assert words(await driver.execute(read(N, 7, 3))) == [3]
        assert ctl.sim.applied_writes == []


# --------------------------------------------------------------------------------------------
# Link loss


async def test_link_loss_fails_fast_with_link_down_then_reconnects() -> None:
    async with controller("tcp") as ctl, driver_for(ctl, timeout=2.0, reconnect_min=0.05,
                                                     reconnect_max=0.2) as driver:
        assert words(await driver.execute(read(N, 7, 1))) == [1]
        # A command on the line when the device server goes away fails at once, not after 2 s.
        ctl.sim.options = dataclasses.replace(ctl.sim.options, delay=1.0)
        pending = asyncio.create_task(driver.execute(read(N, 7, 2)))
        await asyncio.sleep(0.1)
        lost = time.monotonic()
        await ctl.stop()
        with pytest.raises(LinkDown):
            await pending
        assert time.monotonic() - lost < 0.5
        # While it is down every request fails at once.
        for _ in range(3):
            started = time.monotonic()
            with pytest.raises(LinkDown):
                await driver.execute(read(N, 7, 2))
            assert time.monotonic() - started < 0.1
        assert not driver.available
        ctl.sim.options = dataclasses.replace(ctl.sim.options, delay=0.0)
        ctl.sim.set_word("N7", 2, 4321)  # changed while away
        await ctl.restart()
        async with asyncio.timeout(5):
            while True:
                try:
                    reply = await driver.execute(read(N, 7, 2))
                    break
                except LinkDown:
                    await asyncio.sleep(0.02)
        assert words(reply) == [4321]
        assert driver.available
        assert driver.counters.reconnects >= 1
        await driver.execute(write(N, 7, 2, (99).to_bytes(2, "little")))
        assert ctl.sim.applied_writes == [("write", "N7:2", b"\x63\x00")]


async def test_unreachable_device_server_is_link_down() -> None:
    async with controller("tcp") as ctl:
        await ctl.stop()
        driver = Df1Driver(ctl.url, timeout=0.05)
        started = time.monotonic()
        with pytest.raises(LinkDown):
            await driver.start()
        assert time.monotonic() - started < 2


# --------------------------------------------------------------------------------------------
# Exactly once under faults

FAULTS = {"corrupt": 10, "drop": 15, "withhold_ack": 10, "duplicate": 10, "noise": 10}


@pytest.mark.parametrize(("transport", "checksum"), [("sim", "crc"), ("sim", "bcc"), ("tcp", "crc")])
async def test_every_acknowledged_write_applied_exactly_once_under_faults(transport: str, checksum: str) -> None:
    rng = random.Random(f"{transport}-{checksum}")
    async with controller(transport, checksum=checksum, **FAULTS) as ctl, driver_for(
        ctl, timeout=0.05, retries=3
    ) as driver:
        sim = ctl.sim
        acked: list[tuple[str, str, bytes]] = []
        unknown: list[tuple[str, str, bytes]] = []
        values = iter(range(1000, 60000))
        async with asyncio.timeout(40):
            for n in range(240):
                kind = n % 4
                value = next(values)
                if kind == 0:  # a word
                    element = rng.randrange(100)
                    target, data = f"N7:{element}", value.to_bytes(2, "little")
                    request: Request = write(N, 7, element, data)
                elif kind == 1:  # a float
                    element = rng.randrange(64)
                    target, data = f"F8:{element}", struct.pack("<f", value + 0.25)
                    request = write(F, 8, element, data)
                elif kind == 2:  # a masked write of a whole word of bits
                    element = rng.randrange(64)
                    target, data = f"B3:{element}", value.to_bytes(2, "little")
                    request = ProtectedTypedLogicalMaskedWrite(B, 3, element, 0, 0xFFFF, data)
                else:  # a read, which must give exactly what the controller holds
                    element = rng.randrange(0, 100)
                    try:
                        reply = await driver.execute(read(N, 7, element, 8))
                    except LinkTimeout:
                        continue  # no valid answer after every retry: no data, never wrong data
                    assert words(reply) == [sim.word("N7", element + i) for i in range(4)], element
                    continue
                kind_name = "masked_write" if kind == 2 else "write"
                try:
                    await driver.execute(request)
                except (WriteOutcomeUnknown, LinkTimeout):
                    unknown.append((kind_name, target, data))
                else:
                    acked.append((kind_name, target, data))
        applied = Counter(sim.applied_writes)
        for entry in acked:
            assert applied[entry] == 1, (entry, applied[entry])
        for entry in unknown:
            assert applied[entry] <= 1, (entry, applied[entry])
        assert set(applied) <= set(acked) | set(unknown)
        assert len(acked) + len(unknown) == 180
        assert len(acked) >= 150, (len(acked), len(unknown))
        # some replies were dropped after the write was executed: the read-back proved them applied
        assert driver.transaction_counters.verified > 0
        # the faults did happen
        counters = sim.counters
        assert counters.corrupted and counters.dropped and counters.withheld_acks
        assert counters.duplicates and counters.noise
        assert driver.counters.retries_by_kind.get("nak", 0) == 0  # the simulator NAKs no frame
        assert driver.counters.retries_by_kind.get("enq", 0) > 0  # withheld ACKs were recovered by ENQ


# --------------------------------------------------------------------------------------------
# Every reading of the manuals (gateway.kinds.df1.sim.slc500 VARIANTS): driver + simulator over TCP

VARIANTS = list(variant_matrix(Slc500Simulator.VARIANTS))


def pairwise(table: dict[str, tuple[str, ...]], fixed: dict[str, str] | None = None) -> list[dict[str, str]]:
    """A few combinations covering every pair of values of two variants (greedy).

    The sans-I/O property test (tests/protocols/df1/full_duplex/test_transaction.py) runs every combination; a
    driver with real timers runs the pairs, which catch the interactions of two readings.
    """
    fixed = fixed or {}
    combos = [c for c in variant_matrix(table) if all(c[k] == v for k, v in fixed.items())]
    names = sorted(table)

    def pairs(combo: dict[str, str]) -> set[tuple[str, str, str, str]]:
        return {(a, combo[a], b, combo[b]) for i, a in enumerate(names) for b in names[i + 1 :]}

    wanted = set().union(*(pairs(c) for c in combos))
    chosen: list[dict[str, str]] = []
    while wanted:
        best = max(combos, key=lambda c: len(pairs(c) & wanted))
        chosen.append(best)
        wanted -= pairs(best)
    return chosen


def variant_id(variants: dict[str, str]) -> str:
    return ",".join(f"{name}={value}" for name, value in sorted(variants.items())) or "defaults"


@asynccontextmanager
async def variant_controller(variants: dict[str, str], **options: Any) -> AsyncIterator[Controller]:
    """A simulated SLC 5/04 with the given readings, on an in-process stream (unpaced)."""
    sim = Slc500Simulator.from_options(
        {"seed": str(next(_seeds)), **{k: str(v) for k, v in options.items()}}, ladder=False, variants=variants
    )
    yield Controller(sim, "sim://slc504")


@asynccontextmanager
async def variant_driver(ctl: Controller, **options: Any) -> AsyncIterator[Df1Driver]:
    async def opener(url: str, settings: Any, **_: Any) -> SimStream:
        return SimStream(ctl.sim)

    async with driver_for(ctl, opener=opener, **options) as driver:
        yield driver


async def write_many(driver: Df1Driver, sim: Slc500Simulator, count: int, seed: str) -> tuple[list[Any], list[Any]]:
    """``count`` writes of distinct values (words and masked bit words) with reads between them.

    Returns (acknowledged, unknown) writes as (kind, address, data); every read that succeeds
    must give exactly what the controller holds (the ladder is frozen).
    """
    rng = random.Random(seed)
    acked: list[tuple[str, str, bytes]] = []
    unknown: list[tuple[str, str, bytes]] = []
    for n in range(count):
        element = rng.randrange(64)
        data = (10_000 + n).to_bytes(2, "little")
        if n % 3 == 2:
            entry, request = ("masked_write", f"B3:{element}", data), ProtectedTypedLogicalMaskedWrite(
                B, 3, element, 0, 0xFFFF, data
            )
        else:
            entry, request = ("write", f"N7:{element}", data), write(N, 7, element, data)
        try:
            await driver.execute(request)
        except WriteOutcomeUnknown:
            unknown.append(entry)
        else:
            acked.append(entry)
        try:
            reply = await driver.execute(read(N, 7, element, 4))
        except LinkTimeout:
            continue
        assert words(reply) == [sim.word("N7", element + i) for i in range(2)]
    return acked, unknown


def assert_exactly_once(sim: Slc500Simulator, acked: list[Any], unknown: list[Any]) -> None:
    applied = Counter(sim.applied_writes)
    for entry in acked:
        assert applied[entry] == 1, ("acknowledged write applied", applied[entry], "times", entry)
    for entry in unknown:
        assert applied[entry] <= 1, ("unacknowledged write applied", applied[entry], "times", entry)
    assert set(applied) <= set(acked) | set(unknown)


@pytest.mark.parametrize(
    "variants", pairwise(Slc500Simulator.VARIANTS, {"duplicate_detect": "off"}), ids=variant_id
)
async def test_duplicate_detection_off_and_one_in_five_replies_lost_after_execution(variants: dict[str, str]) -> None:
    """Acceptance (issue 9): acknowledged writes exactly once, unacknowledged at most once."""
    async with variant_controller(variants, drop=5) as ctl, variant_driver(ctl, timeout=0.05, retries=2) as driver:
        async with asyncio.timeout(60):
            acked, unknown = await write_many(driver, ctl.sim, 60, variant_id(variants))
        assert ctl.sim.counters.dropped > 0
        assert_exactly_once(ctl.sim, acked, unknown)
        # a lost reply of an applied write is proved by the read-back: it is a success, not 0x0B
        assert driver.transaction_counters.verified > 0
        # unknown only when every read-back's reply was lost too (1 in 125 with two retries)
        assert len(acked) + len(unknown) == 60 and len(unknown) <= 3, unknown


@pytest.mark.parametrize("variants", pairwise(Slc500Simulator.VARIANTS), ids=variant_id)
async def test_every_variant_on_a_bad_line_both_ways(variants: dict[str, str]) -> None:
    """Frames lost and damaged on the way in, replies lost, ACKs withheld, frames damaged out."""
    faults = {"drop": 6, "lose_in": 8, "corrupt_in": 8, "withhold_ack": 8, "corrupt": 8, "link_ack_timeout": 0.03}
    async with variant_controller(variants, **faults) as ctl, variant_driver(
        ctl, timeout=0.05, ack_timeout=0.03, retries=2
    ) as driver:
        async with asyncio.timeout(60):
            acked, unknown = await write_many(driver, ctl.sim, 40, variant_id(variants))
        assert_exactly_once(ctl.sim, acked, unknown)
        counters = ctl.sim.counters
        assert counters.lost_in + counters.corrupted_in + counters.dropped > 0


async def test_a_write_whose_reply_is_lost_after_execution_is_a_success_proved_by_the_read_back() -> None:
    async with variant_controller({}, drop=1, faults_on="writes") as ctl, variant_driver(ctl, timeout=0.05) as driver:
        reply = await driver.execute(write(N, 7, 9, b"\x39\x30"))
        assert reply.ok
        assert ctl.sim.applied_writes == [("write", "N7:9", b"\x39\x30")]
        assert ctl.sim.counters.dropped == 1
        assert driver.transaction_counters.verified == 1 and driver.transaction_counters.read_backs == 1


@pytest.mark.parametrize("variants", [{}, {"enq_answer": "nak"}, {"bad_frame": "ignore"}], ids=variant_id)
async def test_a_write_acked_but_never_applied_is_outcome_unknown(variants: dict[str, str]) -> None:
    """The write frame is lost whole; the ENQ gets the previous ACK (or a NAK): not applied."""
    async with variant_controller(variants, lose_in=1, faults_on="writes") as ctl, variant_driver(
        ctl, timeout=0.05, ack_timeout=0.05
    ) as driver:
        assert words(await driver.execute(read(N, 7, 9))) == [9]  # a frame ACKed before
        with pytest.raises(WriteOutcomeUnknown, match="read-back"):
            await driver.execute(write(N, 7, 9, b"\x39\x30"))
        assert ctl.sim.applied_writes == [] and ctl.sim.word("N7", 9) == 9
        assert ctl.sim.counters.lost_in == 1
        assert driver.transaction_counters.read_backs >= 1 and driver.transaction_counters.verified == 0


# --------------------------------------------------------------------------------------------
# The driver's own bookkeeping: defaults, TNS, verdicts counted, line quality, priorities, probe


class RecordingStream(SimStream):
    """A ``SimStream`` that keeps every byte the driver wrote, to read the frames on the wire."""

    def __init__(self, device: Slc500Simulator, wire: list[bytes]) -> None:
        super().__init__(device)
        self._wire_log = wire

    def write(self, data: bytes) -> None:
        self._wire_log.append(data)
        super().write(data)

    def start_push(self, receive: Callable[[bytes], None], lost: Callable[[str], None]) -> bool:
        self.lost = lost
        return super().start_push(receive, lost)


def command_headers(wire: list[bytes]) -> list[tuple[int, int, int, int]]:
    """(DST, SRC, CMD, TNS) of every command frame the driver sent (DLE STX, DLE doubling undone)."""
    data = b"".join(wire)
    headers = []
    start = data.find(b"\x10\x02")
    while start >= 0:
        end = data.find(b"\x10\x03", start)
        body = data[start + 2 : end].replace(b"\x10\x10", b"\x10")
        headers.append((body[0], body[1], body[2], int.from_bytes(body[4:6], "little")))
        start = data.find(b"\x10\x02", end)
    return headers


@asynccontextmanager
async def recorded_driver(ctl: Controller, **options: Any) -> AsyncIterator[tuple[Df1Driver, list[bytes],
                                                                                  list[RecordingStream]]]:
    """A driver on in-process streams to ``ctl.sim`` (a new stream per connect), its bytes recorded."""
    wire: list[bytes] = []
    streams: list[RecordingStream] = []

    async def opener(url: str, settings: Any, **_: Any) -> RecordingStream:
        streams.append(RecordingStream(ctl.sim, wire))
        return streams[-1]

    async with driver_for(ctl, opener=opener, **options) as driver:
        yield driver, wire, streams


async def reconnect(driver: Df1Driver, streams: list[RecordingStream]) -> None:
    """The stream breaks; wait until the driver has opened a new one."""
    count = len(streams)
    streams[-1].lost("cable pulled")
    for _ in range(500):
        if len(streams) > count and driver.connected:
            return
        await asyncio.sleep(0.01)
    raise AssertionError("the driver did not reconnect within 5 s")


def test_defaults_are_the_documented_df1_line() -> None:
    # docs/guide/df1-full-duplex.md: "19200 8N1 by default"
    driver = Df1Driver("sim://slc504")
    assert (driver.settings.baudrate, driver.settings.bytesize, driver.settings.parity,
            driver.settings.stopbits) == (19200, 8, "N", 1)
    assert driver.last_sts == 0  # no refusal yet: STS 0 is "success"
    # nothing on the line yet, nothing to report (status-page-columns.md: DF1 full duplex counts all four)
    assert driver.line_quality() == LineQuality(check_errors=0, timeouts=0, naks=0, retransmits=0)


async def test_commands_carry_station_source_and_the_first_tns_then_new_ones_after_a_reconnect() -> None:
    async with variant_controller({}) as ctl, recorded_driver(ctl, first_tns=0x1234, reconnect_min=0.01) as (
        driver, wire, streams
    ):
        await driver.execute(read(N, 7, 0))
        await driver.execute(read(N, 7, 1))
        # DST = the controller's station (1), SRC = our node (default 0: docs/reference/cli.md),
        # CMD 0F (protected typed logical read), TNS from the given first one
        assert command_headers(wire)[0] == (1, 0, 0x0F, 0x1234)
        await reconnect(driver, streams)
        # After a reconnect the numbering goes on: the controller's duplicate detection (same SRC,
        # CMD and TNS as the last message) must not discard the next command.
        assert words(await driver.execute(read(N, 7, 2))) == [2]
        tns = [header[3] for header in command_headers(wire)]
        assert len(tns) == 3 and len(set(tns)) == 3, tns
        assert ctl.sim.counters.duplicates_received == 0


async def test_reconnects_in_a_row_never_go_back_to_a_tns_already_sent() -> None:
    """Two reconnects with no command between them: the next command's TNS is still a new one (the
    controller's duplicate detection drops a command that repeats the last message's SRC/CMD/TNS)."""
    async with variant_controller({}) as ctl, recorded_driver(ctl, first_tns=0x1234, reconnect_min=0.01) as (
        driver, wire, streams
    ):
        await driver.execute(read(N, 7, 0))
        await driver.execute(read(N, 7, 1))
        await reconnect(driver, streams)
        await reconnect(driver, streams)
        assert words(await driver.execute(read(N, 7, 2))) == [2]
        tns = [header[3] for header in command_headers(wire)]
        assert tns[:2] == [0x1234, 0x1235] and tns[2] not in tns[:2], [hex(t) for t in tns]


async def test_each_session_starts_at_its_own_tns() -> None:
    """A new session must not repeat the last one's SRC/CMD/TNS (duplicate detection would drop it)."""
    first = set()
    for _ in range(3):
        async with variant_controller({}) as ctl, recorded_driver(ctl) as (driver, wire, _streams):
            await driver.execute(read(N, 7, 0))
            first.add(command_headers(wire)[0][3])
    assert len(first) > 1, first


async def test_a_refusal_counts_each_time_and_carries_the_commands_own_description() -> None:
    async with variant_controller({}) as ctl, variant_driver(ctl) as driver:
        for count in (1, 2):
            with pytest.raises(PcccError) as caught:
                await driver.execute(ReadFileInfo(11))
            # notes §7.5: read file info of a missing file is STS 50 "Bad address; file doesn't exist"
            assert caught.value.sts == 0x50
            assert caught.value.description == "Bad address; file doesn't exist"
            assert driver.counters.refusals == count
        assert driver.last_sts == 0x50
        # without a name, the error names the command by its type
        with pytest.raises(PcccError, match="ReadFileInfo"):
            await driver.execute(ReadFileInfo(11))


async def test_no_answer_is_one_timeout_per_request_with_a_message_naming_link_and_command() -> None:
    async with controller("sim", checksum="bcc") as ctl, driver_for(
        ctl, checksum=Checksum.CRC, timeout=0.05, retries=0, name="line-9"
    ) as driver:
        for count in (1, 2):
            with pytest.raises(LinkTimeout) as caught:
                await driver.execute(read(N, 7, 0), "poll N7:0")
            assert "line-9" in str(caught.value) and "poll N7:0" in str(caught.value)
            # status-page-columns.md: timeouts = requests with no valid answer after their retries
            assert driver.counters.timeouts == count and driver.line_quality().timeouts == count
        assert "poll N7:0" in driver.last_error
        assert driver.counters.errors == 2 and driver.counters.transactions == 0


async def test_a_write_of_unknown_outcome_is_one_timeout_and_a_failed_transaction() -> None:
    async with variant_controller({}, lose_in=1, faults_on="writes") as ctl, variant_driver(
        ctl, timeout=0.05, ack_timeout=0.05, name="line-8"
    ) as driver:
        await driver.execute(read(N, 7, 9))
        for count in (1, 2):
            with pytest.raises(WriteOutcomeUnknown) as caught:
                await driver.execute(write(N, 7, 9, b"\x39\x30"), "write N7:9")
            assert "line-8" in str(caught.value) and "write N7:9" in str(caught.value)
            assert driver.counters.timeouts == count
            assert driver.counters.errors == count and driver.counters.transactions == 1
            assert "write N7:9" in driver.last_error


async def test_line_quality_counts_naks_retransmissions_and_bad_frames_across_reconnects() -> None:
    # every frame damaged on the way in is answered DLE NAK (bad_frame=nak, the default) and sent
    # again; every damaged frame out is a bad CRC for us
    # (retries enough that no frame is given up after its last NAK: each NAK is then one frame again)
    faults = {"corrupt_in": 3, "corrupt": 3}
    async with variant_controller({}, **faults) as ctl, recorded_driver(
        ctl, timeout=0.1, ack_timeout=0.02, retries=8, reconnect_min=0.01
    ) as (driver, _wire, streams):
        sim = ctl.sim

        async def some_reads() -> None:
            for element in range(12):
                assert words(await driver.execute(read(N, 7, element))) == [element]

        await some_reads()
        first = driver.line_quality()
        assert sim.counters.corrupted_in > 0 and sim.counters.corrupted > 0
        # each DLE NAK the controller sent is one for us, and our frame went again after it
        assert first.naks == first.retransmits == sim.link.counters.naks_sent > 0
        assert first.check_errors == sim.counters.corrupted == driver.counters.crc_errors
        assert first.timeouts == 0
        # counted since the link was created: a reconnect loses none of them
        for _ in range(2):
            await reconnect(driver, streams)
            await some_reads()
        after = driver.line_quality()
        assert after.naks == after.retransmits == sim.link.counters.naks_sent > first.naks
        assert after.check_errors == sim.counters.corrupted > first.check_errors


async def test_enqs_sent_for_withheld_acks_are_counted_across_reconnects() -> None:
    # (the replies come late, so the ACK wait ends before a reply could stand for the ACK)
    async with variant_controller({}, withhold_ack=2, delay=0.06) as ctl, recorded_driver(
        ctl, timeout=0.2, ack_timeout=0.02, retries=3, reconnect_min=0.01
    ) as (driver, _wire, streams):
        sim = ctl.sim
        for round_ in range(2):
            if round_:
                await reconnect(driver, streams)
            for element in range(8):
                assert words(await driver.execute(read(N, 7, element))) == [element]
            # a withheld DLE ACK: we ask with DLE ENQ (answered with the ACK), once per frame
            assert driver.counters.retries_by_kind["enq"] == sim.counters.withheld_acks > 0


@pytest.mark.parametrize("bad_frame", ["nak", "ignore"])
async def test_with_no_retries_a_frame_goes_once(bad_frame: str) -> None:
    """retries = 0 (docs/reference/config.md: retries before a request fails): a frame the controller
    cannot read (wrong checksum) is not sent again after its DLE NAK, nor asked about with DLE ENQ."""
    async with variant_controller({"bad_frame": bad_frame}, checksum="bcc") as ctl, recorded_driver(
        ctl, checksum=Checksum.CRC, timeout=0.05, ack_timeout=0.02, retries=0
    ) as (driver, wire, _streams):
        with pytest.raises(LinkTimeout):
            await driver.execute(read(N, 7, 0))
        sent = b"".join(wire)
        assert sent.count(b"\x10\x02") == 1 and b"\x10\x05" not in sent
        assert driver.line_quality().retransmits == 0 and driver.counters.retries_by_kind["enq"] == 0


async def test_a_clean_line_has_nothing_to_report() -> None:
    async with variant_controller({}) as ctl, variant_driver(ctl) as driver:
        await driver.execute(read(N, 7, 0))
        assert driver.line_quality() == LineQuality(check_errors=0, timeouts=0, naks=0, retransmits=0)
        assert driver.counters.retries_by_kind["enq"] == 0


async def test_a_long_frame_on_a_slow_line_is_not_taken_for_a_lost_ack() -> None:
    """The DLE ACK can only come after the whole frame went out: at 9600 baud a write of 228 bytes
    (the SLC 5/04's largest) takes about 0.25 s on the wire, so a clean line draws no DLE ENQ."""
    settings = SerialSettings(baudrate=9600, bytesize=8, parity="N", stopbits=1)
    async with variant_controller({}) as ctl:
        async def paced(url: str, line: Any, **_: Any) -> SimStream:
            return SimStream(ctl.sim, line)

        async with driver_for(ctl, opener=paced, settings=settings, timeout=0.5, ack_timeout=0.02) as driver:
            for element in range(10):  # the link learns how fast ACKs come on this line
                assert words(await driver.execute(read(N, 7, element))) == [element]
            await driver.execute(write(N, 7, 0, bytes(range(228))))
            assert ctl.sim.word("N7", 113) == 0xE3E2
            assert driver.counters.retries_by_kind["enq"] == 0


async def test_a_write_goes_ahead_of_queued_polls() -> None:
    """Writes jump ahead of polls (docs/guide: a write is not held up by the poll cycle)."""
    async with variant_controller({}, delay=0.3) as ctl, variant_driver(ctl) as driver:
        first = asyncio.create_task(driver.execute(read(N, 7, 5)))  # on the line, its reply 0.3 s away
        for _ in range(100):
            if ctl.sim.counters.frames_received:
                break
            await asyncio.sleep(0.001)
        polls = [asyncio.create_task(driver.execute(read(N, 7, 5))) for _ in range(2)]
        await asyncio.sleep(0)
        await driver.execute(write(N, 7, 5, (777).to_bytes(2, "little")))
        assert words(await first) == [5]
        assert [words(await poll) for poll in polls] == [[777], [777]]


async def test_probe_identifies_the_slc_5_04() -> None:
    async with variant_controller({}) as ctl, variant_driver(ctl) as driver:
        info = await driver.probe()
        # notes §6.0: processor type 5B hex = SLC 5/04
        assert info.processor_type == 0x5B and info.family is ProcessorFamily.SLC5_04


async def test_a_probe_without_answer_says_it_was_the_diagnostic_status() -> None:
    async with controller("sim", checksum="bcc") as ctl, driver_for(
        ctl, checksum=Checksum.CRC, timeout=0.05, retries=0
    ) as driver:
        with pytest.raises(LinkTimeout) as caught:
            await driver.probe()
        assert ": diagnostic status: " in str(caught.value)  # "link <name>: <command>: <reason>"
