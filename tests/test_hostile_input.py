"""Hostile input from every side: Modbus clients, controllers, configuration files.

Modbus side (a real ``Gateway`` running in a thread of its own, a read-only SLC 150 behind it,
real sockets on 127.0.0.1):

* hypothesis streams of truncated frames, wrong protocol ids, lengths that lie, huge counts,
  unknown function codes and plain noise, sent whole, in random chunks or one byte at a time:
  every complete frame before the first broken header is answered exactly as an independent
  model of the Modbus specification and of the unit's map says, nothing else is ever sent,
  and the connection is closed after the client's EOF;
* 1,000 connections at once: all served with a high ``max_connections``; with a low one the
  refused connections are closed at once and the admitted ones are served;
* idle connections are closed after ``idle_timeout``, busy ones are not;
* a well-behaved client polls throughout every test and must be answered correctly and fast;
* memory held by gateway code (tracemalloc) and open connections return to where they were.

Serial side: random bytes from the "controller" never crash a driver or produce a value: the
sans-I/O decoders are fed hypothesis bytes (whole, byte by byte, in random chunks), the drivers
talk to a fake controller on TCP that answers everything with random bytes, and a whole gateway
in front of such controllers answers every read with 0x0B.

Configuration: ``slc-gateway check-config BADFILE`` prints one clear line and exits 1, never a
traceback, whatever the file holds.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import os
import random
import resource
import socket
import struct
import subprocess
import sys
import threading
import time
import tracemalloc
import uuid
from collections import Counter
from collections.abc import AsyncIterator, Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from gateway.app import Gateway
from gateway.cli import main as cli_main
from gateway.config import parse_config
from gateway.errors import GatewayError
from gateway.kinds.df1.full.driver import Df1Driver
from gateway.kinds.slc_ascii.driver import SlcAsciiDriver
from gateway.protocols.df1 import framing as df1_framing
from gateway.protocols.df1.framing import Checksum, encode_frame
from gateway.protocols.df1.framing.decoder import FrameDecoder
from gateway.protocols.df1.full_duplex.datalink import Df1DataLink, MessageReceived, SendComplete, SendFailed
from gateway.protocols.df1.pccc import PcccReply, ProtectedTypedLogicalRead, ProtectedTypedLogicalWrite, decode_reply
from gateway.protocols.slc_ascii import commands as slc_commands
from gateway.protocols.slc_ascii import framing as slc_framing
from gateway.protocols.slc_ascii.memory_map import is_readable
from gateway.sim import reset_simulators
from tests.net import mbap

HOST = "127.0.0.1"
UNIT = 1  # the read-only SLC 150 behind the threaded gateway

ILLEGAL_FUNCTION, ILLEGAL_ADDRESS, ILLEGAL_VALUE = 0x01, 0x02, 0x03
PATH_UNAVAILABLE, TARGET_FAILED = 0x0A, 0x0B

#: Modbus addresses the SLC 100/150 default map serves (module docstring of gateway.modbus.mapping).
HOLDING = set(range(64))
INPUT = set(range(32)) | set(range(66, 75)) | set(range(129, 137))
STATUS = range(1000, 1012)  # the status block, 1000-1011
COILS = set(range(701, 869))
DISCRETE = (
    {g * 100 + r for g in range(7) for r in range(1, 19) if g * 100 + r >= 1}
    | set(range(701, 877))
    | set(range(901, 933))
    | set(range(951, 983))
)


# ============================================================================================
# A gateway in a thread of its own (the tests drive it with blocking sockets and other loops)


class GatewayThread:
    """``Gateway(config)`` running on its own event loop in a daemon thread."""

    def __init__(self, config_text: str) -> None:
        self.config = parse_config(config_text)
        self.loop = asyncio.new_event_loop()
        self.gw: Gateway | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._stop: asyncio.Event | None = None
        self.thread = threading.Thread(target=self._run, name="gateway-under-test", daemon=True)

    def _run(self) -> None:
        asyncio.set_event_loop(self.loop)
        try:
            self.loop.run_until_complete(self._main())
        except BaseException as exc:  # reported by start()
            self._error = exc
            self._ready.set()
        finally:
            self.loop.close()

    async def _main(self) -> None:
        self._stop = asyncio.Event()
        async with Gateway(self.config) as gw:
            self.gw = gw
            self._ready.set()
            await self._stop.wait()

    def start(self) -> GatewayThread:
        self.thread.start()
        assert self._ready.wait(10), "the gateway did not start"
        if self._error is not None:
            raise self._error
        return self

    def stop(self) -> None:
        if self._stop is not None and self.thread.is_alive():
            self.loop.call_soon_threadsafe(self._stop.set)
        self.thread.join(10)

    def call(self, function: Callable[[], Any]) -> Any:
        """Run ``function`` on the gateway's loop (to read its state safely)."""

        async def run() -> Any:
            return function()

        return asyncio.run_coroutine_threadsafe(run(), self.loop).result(5)

    @property
    def port(self) -> int:
        assert self.gw is not None
        return self.gw.port

    @property
    def server(self) -> Any:
        assert self.gw is not None
        return self.gw.servers[0]


def read_frame(sock: socket.socket) -> tuple[int, int, bytes]:
    header = recv_exactly(sock, 7)
    tid, protocol, length, unit = struct.unpack(">HHHB", header)
    assert protocol == 0 and 2 <= length <= 254, header.hex()
    return tid, unit, recv_exactly(sock, length - 1)


def recv_exactly(sock: socket.socket, size: int) -> bytes:
    data = b""
    while len(data) < size:
        chunk = sock.recv(size - len(data))
        if not chunk:
            raise ConnectionError("closed")
        data += chunk
    return data


class WellBehavedClient:
    """Polls holding 0-3 of the unit every few milliseconds on one connection, in a thread."""

    def __init__(self, port: int, expected: list[int]) -> None:
        self.port = port
        self.expected = expected
        self.served = 0
        self.failures: list[str] = []
        self.slowest = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="well-behaved-client", daemon=True)

    def start(self) -> WellBehavedClient:
        self._thread.start()
        return self

    def _run(self) -> None:
        request = struct.pack(">BHH", 3, 0, len(self.expected))
        tid = 0
        try:
            sock = socket.create_connection((HOST, self.port), timeout=5)
        except OSError as exc:
            self.failures.append(f"cannot connect: {exc}")
            return
        with sock:
            while not self._stop.is_set():
                tid = (tid + 1) & 0xFFFF
                started = time.monotonic()
                try:
                    sock.sendall(mbap(tid, UNIT, request))
                    reply = read_frame(sock)
                except OSError as exc:
                    self.failures.append(f"request {tid}: {exc!r}")
                    return
                took = time.monotonic() - started
                self.slowest = max(self.slowest, took)
                values = list(struct.unpack(f">{len(self.expected)}H", reply[2][2:])) if reply[2][0] == 3 else None
                if reply[0] != tid or reply[1] != UNIT or values != self.expected:
                    self.failures.append(f"request {tid}: reply {reply!r}")
                else:
                    self.served += 1
                self._stop.wait(0.005)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(10)

    def check_served_since(self, before: int, what: str) -> None:
        assert not self.failures, f"the well-behaved client failed during {what}: {self.failures[:5]}"
        assert self.served > before, f"the well-behaved client was not served during {what}"


def gateway_toml(*, max_connections: int = 1200, idle_timeout: float = 0.0, read_only: bool = True) -> str:
    # A paced line (as a real one): an unpaced simulator makes the poller spin flat out, and the
    # CPU it burns (with tracemalloc on) would be measured as the well-behaved client's latency.
    url = f"sim://slc150?ladder=0&paced=1&instance={uuid.uuid4().hex}"
    return (
        f'[modbus]\nlisten = "127.0.0.1:0"\nmax_connections = {max_connections}\nidle_timeout = {idle_timeout}\n'
        # Every test client comes from 127.0.0.1: no per-address cap below the total one here.
        f"max_connections_per_address = {max_connections}\n\n"
        f'[[link]]\nname = "press"\nprotocol = "slc-ascii"\nport = "{url}"\nunit = {UNIT}\nbaudrate = 38400\n'
        f"read_only = {'true' if read_only else 'false'}\n"
    )


def wait_until_served(port: int) -> list[int]:
    """Until a whole scan of the unit is cached; the values of holding 0-63."""
    deadline = time.monotonic() + 10
    with socket.create_connection((HOST, port), timeout=5) as sock:
        while True:
            sock.sendall(mbap(1, UNIT, struct.pack(">BHH", 3, 0, 64)) + mbap(2, UNIT, struct.pack(">BHH", 2, 951, 32)))
            first, second = read_frame(sock), read_frame(sock)
            if first[2][0] == 3 and second[2][0] == 2:
                return list(struct.unpack(">64H", first[2][2:]))
            assert time.monotonic() < deadline, "the gateway never served a whole scan"
            time.sleep(0.02)


class Hostile:
    """The threaded gateway, its simulator's holding values, and the well-behaved client."""

    def __init__(self, gateway: GatewayThread, holding: list[int], good: WellBehavedClient) -> None:
        self.gateway = gateway
        self.holding = holding
        self.good = good


@pytest.fixture(scope="module")
def hostile() -> Iterator[Hostile]:
    gateway = GatewayThread(gateway_toml()).start()
    try:
        holding = wait_until_served(gateway.port)
        good = WellBehavedClient(gateway.port, holding[:4]).start()
        try:
            yield Hostile(gateway, holding, good)
        finally:
            good.stop()
    finally:
        gateway.stop()
        reset_simulators()


def gateway_traced_bytes() -> int:
    gc.collect()
    snapshot = tracemalloc.take_snapshot().filter_traces(
        [tracemalloc.Filter(True, "*/gateway/*"), tracemalloc.Filter(False, "*/gateway/sim/*")]
    )
    return sum(stat.size for stat in snapshot.statistics("filename"))


@contextlib.contextmanager
def traced() -> Iterator[None]:
    started = not tracemalloc.is_tracing()
    if started:
        tracemalloc.start()
    try:
        yield
    finally:
        if started:
            tracemalloc.stop()


# ============================================================================================
# Modbus: an independent model of what the server must answer


def expected_reply(unit: int, pdu: bytes, holding: list[int]) -> bytes | tuple[str, int]:
    """The reply PDU, or ("bits", count) for a successful bit read (values not modelled)."""
    fc = pdu[0]
    size = len(pdu)

    def exception(code: int) -> bytes:
        return bytes((fc | 0x80, code))

    if unit != UNIT:
        return exception(PATH_UNAVAILABLE)
    if fc in (1, 2, 3, 4):
        if size != 5:
            return exception(ILLEGAL_VALUE)
        address, count = struct.unpack_from(">HH", pdu, 1)
        if not 1 <= count <= (2000 if fc in (1, 2) else 125):
            return exception(ILLEGAL_VALUE)
        if address + count > 0x10000:
            return exception(ILLEGAL_ADDRESS)
        addresses = range(address, address + count)
        if fc == 3:
            if not set(addresses) <= HOLDING:
                return exception(ILLEGAL_ADDRESS)
            return bytes((3, 2 * count)) + struct.pack(f">{count}H", *holding[address : address + count])
        if fc == 4:
            if address >= STATUS.start:
                ok = address + count <= STATUS.stop
            else:
                ok = set(addresses) <= INPUT
            return ("registers", count) if ok else exception(ILLEGAL_ADDRESS)
        table = COILS if fc == 1 else DISCRETE
        return ("bits", count) if set(addresses) <= table else exception(ILLEGAL_ADDRESS)
    if fc in (5, 6):
        if size != 5:
            return exception(ILLEGAL_VALUE)
        value = struct.unpack_from(">H", pdu, 3)[0]
        if fc == 5 and value not in (0xFF00, 0x0000):
            return exception(ILLEGAL_VALUE)
        return exception(ILLEGAL_ADDRESS)  # the link is read only
    if fc in (15, 16):
        if size < 6:
            return exception(ILLEGAL_VALUE)
        address, count, byte_count = struct.unpack_from(">HHB", pdu, 1)
        if fc == 15:
            valid = 1 <= count <= 1968 and byte_count == (count + 7) // 8
        else:
            valid = 1 <= count <= 123 and byte_count == 2 * count
        if not valid or size != 6 + byte_count:
            return exception(ILLEGAL_VALUE)
        if address + count > 0x10000:
            return exception(ILLEGAL_ADDRESS)
        return exception(ILLEGAL_ADDRESS)  # read only
    return exception(ILLEGAL_FUNCTION)


def split_requests(stream: bytes) -> tuple[list[tuple[int, int, bytes]], bool]:
    """The complete frames the server must answer, and whether a broken header ends the stream."""
    frames = []
    position = 0
    while len(stream) - position >= 7:
        tid, protocol, length, unit = struct.unpack_from(">HHHB", stream, position)
        if protocol != 0 or not 2 <= length <= 254:
            return frames, True
        end = position + 6 + length
        if end > len(stream):
            break
        frames.append((tid, unit, stream[position + 7 : end]))
        position = end
    return frames, False


def split_replies(data: bytes) -> list[tuple[int, int, bytes]]:
    replies = []
    position = 0
    while position < len(data):
        assert len(data) - position >= 9, f"a partial reply: {data[position:].hex()}"
        tid, protocol, length, unit = struct.unpack_from(">HHHB", data, position)
        assert protocol == 0 and 3 <= length <= 254, f"a malformed reply header: {data[position:].hex()}"
        end = position + 6 + length
        assert end <= len(data), f"a reply shorter than its length: {data[position:].hex()}"
        replies.append((tid, unit, data[position + 7 : end]))
        position = end
    return replies


def reply_matches(expected: bytes | tuple[str, int], pdu: bytes, fc: int) -> bool:
    if isinstance(expected, bytes):
        return pdu == expected
    kind, count = expected
    if kind == "registers":
        return pdu[0] == fc and pdu[1] == 2 * count and len(pdu) == 2 + 2 * count
    return pdu[0] == fc and pdu[1] == (count + 7) // 8 and len(pdu) == 2 + (count + 7) // 8


def exchange(port: int, stream: bytes, delivery: str, rng: random.Random) -> bytes:
    """Send ``stream``, half-close, read until the server closes: what came back."""
    with socket.create_connection((HOST, port), timeout=5) as sock:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        try:
            if delivery == "whole":
                sock.sendall(stream)
            else:
                position = 0
                while position < len(stream):
                    step = 1 if delivery == "bytes" else rng.randint(1, 40)
                    sock.sendall(stream[position : position + step])
                    position += step
                    if delivery == "bytes" or rng.random() < 0.3:
                        time.sleep(0.0002)
            sock.shutdown(socket.SHUT_WR)
        except OSError:
            pass  # the server already closed a connection that broke the framing
        received = b""
        while True:
            try:
                chunk = sock.recv(65536)
            except ConnectionResetError:
                break
            except TimeoutError:
                pytest.fail(f"the server neither answered nor closed within 5 s; got {received.hex()}")
            if not chunk:
                break
            received += chunk
    return received


_COUNTS = st.sampled_from([0, 1, 2, 123, 124, 125, 126, 1968, 1969, 2000, 2001, 0x7FFF, 0xFFFF]) | st.integers(
    0, 0xFFFF
)
_ADDRESSES = st.sampled_from([0, 1, 31, 63, 64, 701, 868, 951, 999, 1000, 1010, 1011, 0xFFFE, 0xFFFF]) | st.integers(
    0, 0xFFFF
)


@st.composite
def request_pdus(draw: st.DrawFn) -> bytes:
    fc = draw(st.sampled_from([1, 2, 3, 4, 5, 6, 15, 16]) | st.integers(0, 255))
    address = draw(_ADDRESSES)
    if fc in (15, 16):
        count = draw(_COUNTS)
        natural = (count + 7) // 8 if fc == 15 else 2 * count
        byte_count = draw(st.just(min(natural, 255)) | st.integers(0, 255))
        payload = draw(st.binary(min_size=0, max_size=min(byte_count + 2, 246)))
        pdu = struct.pack(">BHHB", fc, address, count & 0xFFFF, byte_count) + payload
    elif fc in (5, 6):
        value = draw(st.sampled_from([0xFF00, 0x0000, 0x00FF, 1]) | st.integers(0, 0xFFFF))
        pdu = struct.pack(">BHH", fc, address, value)
    else:
        pdu = struct.pack(">BHH", fc, address, draw(_COUNTS))
    mutation = draw(st.sampled_from(["none", "none", "none", "truncate", "extend"]))
    if mutation == "truncate":
        pdu = pdu[: draw(st.integers(1, len(pdu)))]
    elif mutation == "extend":
        pdu += draw(st.binary(min_size=1, max_size=8))
    return pdu[:253]


@st.composite
def frames(draw: st.DrawFn) -> bytes:
    kind = draw(st.sampled_from(["request", "request", "request", "protocol", "length", "noise"]))
    tid = draw(st.integers(0, 0xFFFF))
    unit = draw(st.sampled_from([UNIT, UNIT, UNIT, 0, 2, 255]))
    if kind == "noise":
        return draw(st.binary(min_size=1, max_size=64))
    pdu = draw(request_pdus())
    if kind == "protocol":
        return mbap(tid, unit, pdu, protocol=draw(st.integers(1, 0xFFFF)))
    if kind == "length":  # a length that lies: too short, too long, 0, 1, past 254
        length = draw(st.sampled_from([0, 1, 255, 256, 0xFFFF]) | st.integers(2, 254))
        return mbap(tid, unit, pdu, length=length)
    return mbap(tid, unit, pdu)


@settings(max_examples=150, deadline=None, suppress_health_check=list(HealthCheck))
@given(
    parts=st.lists(frames(), min_size=1, max_size=6),
    delivery=st.sampled_from(["whole", "whole", "chunks", "bytes"]),
    seed=st.integers(0, 2**32 - 1),
)
def fuzz_one(hostile: Hostile, parts: list[bytes], delivery: str, seed: int) -> None:
    stream = b"".join(parts)
    if delivery == "bytes" and len(stream) > 300:
        delivery = "chunks"
    received = exchange(hostile.gateway.port, stream, delivery, random.Random(seed))
    requests, broken = split_requests(stream)
    replies = split_replies(received)
    # Every reply answers one request, exactly as the model says; without a broken header,
    # every request is answered.  (After a broken header the server closes at once and drops
    # the replies still in flight, so only a subset can be required.)
    expected = Counter()
    pending: dict[tuple[int, int], list[tuple[bytes | tuple[str, int], int]]] = {}
    for tid, unit, pdu in requests:
        expected[(tid, unit)] += 1
        pending.setdefault((tid, unit), []).append((expected_reply(unit, pdu, hostile.holding), pdu[0]))
    for tid, unit, pdu in replies:
        candidates = pending.get((tid, unit), [])
        match = next((i for i, (want, fc) in enumerate(candidates) if reply_matches(want, pdu, fc)), None)
        assert match is not None, (
            f"reply {tid:#06x} unit {unit} {pdu.hex()} answers no request; expected {candidates}; stream {stream.hex()}"
        )
        candidates.pop(match)
    if not broken:
        left = {key: value for key, value in pending.items() if value}
        assert not left, f"requests left unanswered: {left}; stream {stream.hex()}"


def test_modbus_fuzz_streams_are_answered_exactly_or_closed(hostile: Hostile) -> None:
    before = hostile.good.served
    with traced():
        baseline = gateway_traced_bytes()
        fuzz_one(hostile)
        assert wait_for(lambda: hostile.gateway.call(lambda: hostile.gateway.server.connection_count) == 1, 5)
        grown = gateway_traced_bytes() - baseline
    assert grown < 256 * 1024, f"gateway code holds {grown} more bytes after the fuzz"
    hostile.good.check_served_since(before, "the fuzz")
    assert hostile.good.slowest < 1.0, hostile.good.slowest


def wait_for(predicate: Callable[[], bool], within: float) -> bool:
    deadline = time.monotonic() + within
    while not predicate():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.02)
    return True


def test_pipelined_requests_one_byte_at_a_time(hostile: Hostile) -> None:
    stream = (
        mbap(0x0101, UNIT, struct.pack(">BHH", 3, 0, 3))
        + mbap(0x0202, UNIT, struct.pack(">BHH", 0x2B, 0x0E01, 0))  # unknown function (MEI)
        + mbap(0x0303, 9, struct.pack(">BHH", 3, 0, 1))  # unknown unit
        + mbap(0x0404, UNIT, struct.pack(">BHH", 3, 0, 126))  # one register too many
    )
    with socket.create_connection((HOST, hostile.gateway.port), timeout=5) as sock:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        for byte in stream:
            sock.sendall(bytes((byte,)))
            time.sleep(0.001)
        replies = {frame[0]: frame for frame in (read_frame(sock) for _ in range(4))}
    values = struct.pack(">3H", *hostile.holding[:3])
    assert replies == {
        0x0101: (0x0101, UNIT, bytes((3, 6)) + values),
        0x0202: (0x0202, UNIT, bytes((0xAB, ILLEGAL_FUNCTION))),
        0x0303: (0x0303, 9, bytes((0x83, PATH_UNAVAILABLE))),
        0x0404: (0x0404, UNIT, bytes((0x83, ILLEGAL_VALUE))),
    }


# ============================================================================================
# Many connections, idle connections


def need_descriptors(count: int) -> None:
    soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft < count:
        pytest.skip(f"needs {count} file descriptors, ulimit -n is {soft}")


async def open_and_ask(port: int, tid: int) -> tuple[asyncio.StreamReader, asyncio.StreamWriter, bytes]:
    reader, writer = await asyncio.open_connection(HOST, port)
    writer.write(mbap(tid, UNIT, struct.pack(">BHH", 3, 0, 2)))
    await writer.drain()
    try:
        async with asyncio.timeout(10):
            header = await reader.readexactly(7)
            length = struct.unpack(">H", header[4:6])[0]
            return reader, writer, header + await reader.readexactly(length - 1)
    except (asyncio.IncompleteReadError, ConnectionError):
        return reader, writer, b""


async def close_all(writers: list[asyncio.StreamWriter]) -> None:
    for writer in writers:
        writer.close()
    await asyncio.gather(*(writer.wait_closed() for writer in writers), return_exceptions=True)


async def test_a_thousand_connections_at_once_are_all_served(hostile: Hostile) -> None:
    need_descriptors(2300)
    before = hostile.good.served
    port = hostile.gateway.port
    results = await asyncio.gather(*(open_and_ask(port, n) for n in range(1000)))
    try:
        values = struct.pack(">2H", *hostile.holding[:2])
        bad = [n for n, (_, _, reply) in enumerate(results) if reply != mbap(n, UNIT, bytes((3, 4)) + values)]
        assert not bad, f"{len(bad)} of 1000 connections were not answered correctly, e.g. #{bad[0]}"
        assert hostile.gateway.call(lambda: hostile.gateway.server.connection_count) == 1001
    finally:
        await close_all([writer for _, writer, _ in results])
    assert await asyncio.to_thread(
        wait_for, lambda: hostile.gateway.call(lambda: hostile.gateway.server.connection_count) == 1, 10
    ), "the closed connections were not released"
    hostile.good.check_served_since(before, "1,000 connections")


async def test_connections_over_the_limit_are_closed_at_once() -> None:
    need_descriptors(2300)
    gateway = GatewayThread(gateway_toml(max_connections=100)).start()
    try:
        port = gateway.port
        holding = await asyncio.to_thread(wait_until_served, port)
        good = WellBehavedClient(port, holding[:4]).start()
        try:
            await asyncio.sleep(0.1)
            started = time.monotonic()
            results = await asyncio.gather(*(open_and_ask(port, n) for n in range(1000)))
            took = time.monotonic() - started
            try:
                answered = [n for n, (_, _, reply) in enumerate(results) if reply]
                refused = [n for n, (_, _, reply) in enumerate(results) if not reply]
                # 99 slots left beside the well-behaved client; the other 901 closed without a byte.
                assert len(answered) == 99, (len(answered), len(refused))
                assert took < 10, f"refused connections were not closed promptly ({took:.1f} s for all)"
                counters = gateway.call(lambda: gateway.server.counters)
                assert counters.connections_refused == 901
            finally:
                await close_all([writer for _, writer, _ in results])
            good.check_served_since(0, "1,000 connections against a limit of 100")
        finally:
            good.stop()
    finally:
        gateway.stop()
        reset_simulators()


@pytest.fixture
async def idle_gateway() -> AsyncIterator[Gateway]:
    async with Gateway(parse_config(gateway_toml(idle_timeout=0.5))) as gw:
        yield gw
    reset_simulators()


async def test_idle_connections_are_closed_after_idle_timeout(idle_gateway: Gateway) -> None:
    port = idle_gateway.port
    silent_reader, silent_writer = await asyncio.open_connection(HOST, port)
    partial_reader, partial_writer = await asyncio.open_connection(HOST, port)
    busy_reader, busy_writer, _ = await open_and_ask(port, 1)
    opened = time.monotonic()
    partial_writer.write(mbap(5, UNIT, struct.pack(">BHH", 3, 0, 1))[:9])  # a frame that never completes
    try:

        async def closed_after(reader: asyncio.StreamReader) -> float:
            with contextlib.suppress(ConnectionError):
                assert await reader.read(100) == b""
            return time.monotonic() - opened

        async def keep_busy() -> None:
            for tid in range(12):  # 2.4 s of one request every 0.2 s
                busy_writer.write(mbap(tid, UNIT, struct.pack(">BHH", 3, 0, 1)))
                await busy_writer.drain()
                header = await busy_reader.readexactly(7)
                await busy_reader.readexactly(struct.unpack(">H", header[4:6])[0] - 1)
                await asyncio.sleep(0.2)

        async with asyncio.timeout(5):
            silent, partial, _ = await asyncio.gather(closed_after(silent_reader), closed_after(partial_reader),
                                                      keep_busy())
        assert 0.4 <= silent <= 1.5, silent
        assert 0.4 <= partial <= 1.5, partial
        assert idle_gateway.servers[0].connection_count == 1  # the busy one, still open
        assert idle_gateway.servers[0].counters.connections_dropped == 2
    finally:
        await close_all([silent_writer, partial_writer, busy_writer])


# ============================================================================================
# Serial side: the sans-I/O decoders


def chunked(data: bytes, cuts: list[int]) -> list[bytes]:
    points = sorted({c % (len(data) + 1) for c in cuts})
    return [data[a:b] for a, b in zip([0, *points], [*points, len(data)], strict=True)]


def slc_events(chunks: list[bytes]) -> list[Any]:
    decoder = slc_framing.ReplyDecoder()
    events = []
    for chunk in chunks:
        decoder.receive_data(chunk)
        while (event := decoder.next_event()) is not slc_framing.NEED_DATA:
            events.append(event)
    return events


SLC_REPLY_TYPES = (
    slc_framing.DataReply,
    slc_framing.Ack,
    slc_framing.Refused,
    slc_framing.Fault,
    slc_framing.IdMismatch,
    slc_framing.Garbled,
)
SLC_ALPHABET = st.sampled_from([*b":;#RETIZ0123456789ABCDEFabcdef\r\n", 0x8D, 0xBA, 0x00, 0x7F])
slc_noise = st.binary(max_size=200) | st.lists(SLC_ALPHABET, max_size=200).map(bytes)


@settings(max_examples=300, deadline=None)
@given(data=slc_noise, cuts=st.lists(st.integers(0, 400), max_size=8))
def test_slc_reply_decoder_takes_any_bytes(data: bytes, cuts: list[int]) -> None:
    whole = slc_events([data])
    assert all(isinstance(event, SLC_REPLY_TYPES) for event in whole)
    assert slc_events([bytes((b,)) for b in data]) == whole
    assert slc_events(chunked(data, cuts)) == whole


@settings(max_examples=200, deadline=None)
@given(
    before=slc_noise,
    after=slc_noise,
    data=st.binary(min_size=1, max_size=2),
    msg_id=st.integers(0, 0x7F),
    address=st.integers(0, 0x112),
)
def test_slc_reply_found_in_noise_and_parsed_only_when_it_echoes_the_request(
    before: bytes, after: bytes, data: bytes, msg_id: int, address: int
) -> None:
    assume(is_readable(address, len(data)))
    body = f"{len(data):04X}{address:04X}{data.hex().upper()}"
    frame = slc_framing.encode_data_reply(body, msg_id)
    events = slc_events([before + frame + after])
    assert slc_framing.DataReply(body, msg_id) in events
    assert slc_commands.parse_read_reply(address, len(data), body) == data
    for other_address, other_count in ((address ^ 1, len(data)), (address, len(data) % 2 + 1)):
        with pytest.raises(GatewayError):
            slc_commands.parse_read_reply(other_address, other_count, body)


@settings(max_examples=300, deadline=None)
@given(body=st.text(alphabet="0123456789ABCDEFabcdefXYZ:; ", max_size=40), address=st.integers(0, 0x112),
       count=st.sampled_from([1, 2]))
def test_slc_read_reply_parser_takes_any_body(body: str, address: int, count: int) -> None:
    try:
        data = slc_commands.parse_read_reply(address, count, body)
    except GatewayError:
        return
    assert len(data) == count
    layouts = (f"{count:04X}{address:04X}{data.hex()}", f"{count:02X}{address:04X}{data.hex()}")
    assert body.upper() in (layout.upper() for layout in layouts)


DF1_ALPHABET = st.sampled_from([0x10, 0x10, 0x02, 0x03, 0x05, 0x06, 0x15, 0x00, 0xFF, 0x41])
df1_noise = st.binary(max_size=200) | st.lists(DF1_ALPHABET, max_size=200).map(bytes)


def df1_events(chunks: list[bytes], checksum: Checksum) -> list[Any]:
    decoder = FrameDecoder(checksum)
    events = []
    for chunk in chunks:
        decoder.feed(chunk)
        while (event := decoder.next_event()) is not df1_framing.NEED_DATA:
            events.append(event)
    return events


@settings(max_examples=300, deadline=None)
@given(data=df1_noise, cuts=st.lists(st.integers(0, 400), max_size=8), checksum=st.sampled_from(list(Checksum)))
def test_df1_frame_decoder_takes_any_bytes(data: bytes, cuts: list[int], checksum: Checksum) -> None:
    whole = df1_events([data], checksum)
    assert all(isinstance(event, df1_framing.DecoderEvent.__args__) for event in whole)  # type: ignore[attr-defined]
    assert df1_events([bytes((b,)) for b in data], checksum) == whole
    assert df1_events(chunked(data, cuts), checksum) == whole


@settings(max_examples=200, deadline=None)
@given(
    before=df1_noise.map(lambda b: b.replace(b"\x10", b"")),
    after=df1_noise,
    message=st.binary(min_size=1, max_size=120),
    checksum=st.sampled_from(list(Checksum)),
)
def test_df1_frame_found_in_noise(before: bytes, after: bytes, message: bytes, checksum: Checksum) -> None:
    events = df1_events([before + encode_frame(message, checksum) + after], checksum)
    assert df1_framing.Frame(message) in events


@settings(max_examples=300, deadline=None)
@given(
    steps=st.lists(
        st.one_of(
            st.tuples(st.just("bytes"), df1_noise),
            st.tuples(st.just("send"), st.binary(min_size=1, max_size=40)),
            st.tuples(st.just("time"), st.floats(0.0, 2.0)),
        ),
        max_size=30,
    ),
    checksum=st.sampled_from(list(Checksum)),
)
def test_df1_link_takes_any_bytes_and_timing(steps: list[tuple[str, Any]], checksum: Checksum) -> None:
    link = Df1DataLink(checksum=checksum, ack_timeout=0.5, enq_limit=2, nak_limit=2)
    now = 0.0
    sent: dict[int, bytes] = {}
    settled: set[int] = set()
    for kind, value in steps:
        if kind == "bytes":
            link.receive_data(value, now)
        elif kind == "send":
            sent[link.send(value, now)] = value
        else:
            now += value
            deadline = link.next_deadline()
            if deadline is not None and now >= deadline:
                link.handle_timeout(now)
        out = link.data_to_send()
        frames = [encode_frame(payload, checksum) for payload in sent.values()]
        position = 0
        while position < len(out):  # only response symbols, DLE ENQ and our own frames
            token = next(
                (t for t in (b"\x10\x06", b"\x10\x15", b"\x10\x05", *frames) if out.startswith(t, position)), None
            )
            assert token is not None, f"the link sent {out[position:].hex()}, not a symbol nor one of our frames"
            position += len(token)
        while (event := link.next_event()) is not df1_framing.NEED_DATA:
            assert isinstance(event, MessageReceived | SendComplete | SendFailed)
            if isinstance(event, SendComplete | SendFailed):
                assert event.handle in sent and event.handle not in settled, "a frame settled twice"
                settled.add(event.handle)


@settings(max_examples=500, deadline=None)
@given(packet=st.binary(max_size=64) | st.binary(min_size=6, max_size=12).map(lambda b: b[:2] + bytes((0x4F,)) + b[3:]))
def test_pccc_reply_decoder_takes_any_packet(packet: bytes) -> None:
    try:
        reply = decode_reply(packet)
    except GatewayError:
        return
    assert isinstance(reply, PcccReply) and reply.cmd & 0x40


# ============================================================================================
# Serial side: drivers and a gateway against a controller that talks nonsense


class GarbageController:
    """A 'controller' on 127.0.0.1 that answers every chunk with random bytes (seeded)."""

    def __init__(self, seed: int, alphabet: bytes | None) -> None:
        self.rng = random.Random(seed)
        self.alphabet = alphabet
        self.received = 0
        self.sent = 0
        self.server: asyncio.Server | None = None

    def noise(self) -> bytes:
        size = self.rng.randint(0, 60)
        if self.alphabet is None:
            return self.rng.randbytes(size)
        return bytes(self.rng.choice(self.alphabet) for _ in range(size))

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        with contextlib.suppress(ConnectionError):
            while data := await reader.read(4096):
                self.received += len(data)
                for _ in range(self.rng.randint(1, 3)):
                    chunk = self.noise()
                    self.sent += len(chunk)
                    writer.write(chunk)
                await writer.drain()
        writer.close()

    async def __aenter__(self) -> GarbageController:
        self.server = await asyncio.start_server(self._serve, HOST, 0)
        return self

    async def __aexit__(self, *exc: object) -> None:
        assert self.server is not None
        self.server.close()
        with contextlib.suppress(Exception):
            await asyncio.wait_for(self.server.wait_closed(), 2)

    @property
    def url(self) -> str:
        assert self.server is not None
        return f"socket://{HOST}:{self.server.sockets[0].getsockname()[1]}"


SLC_GARBAGE = b":;RETIZ0123456789ABCDEF\r\r\r"
DF1_GARBAGE = bytes([0x10, 0x10, 0x10, 0x02, 0x03, 0x06, 0x15, 0x05, 0x00, 0x4F, 0x41, 0x01])


@pytest.mark.parametrize("alphabet", [None, SLC_GARBAGE], ids=["random", "slc-flavoured"])
async def test_slc_driver_never_returns_data_from_garbage(alphabet: bytes | None) -> None:
    async with GarbageController(seed=11, alphabet=alphabet) as controller:
        driver = SlcAsciiDriver(controller.url, timeout=0.03, retries=1, reconnect_min=0.05)
        await driver.start()
        try:
            for n in range(8):
                with pytest.raises(GatewayError):
                    data = await driver.read(2 * n, 2)
                    pytest.fail(f"read returned {data!r} from garbage")
                with pytest.raises(GatewayError):
                    await driver.write_word(2 * n, 1000 + n)
                    pytest.fail("a write was confirmed by garbage")
        finally:
            await driver.close()
        assert controller.sent > 0 and driver.counters.transactions == 0


@pytest.mark.parametrize("checksum", [Checksum.BCC, Checksum.CRC], ids=["bcc", "crc"])
@pytest.mark.parametrize("alphabet", [None, DF1_GARBAGE], ids=["random", "df1-flavoured"])
async def test_df1_driver_never_returns_data_from_garbage(alphabet: bytes | None, checksum: Checksum) -> None:
    async with GarbageController(seed=12, alphabet=alphabet) as controller:
        driver = Df1Driver(controller.url, checksum=checksum, timeout=0.05, retries=1, reconnect_min=0.05)
        await driver.start()
        try:
            for n in range(4):
                read = ProtectedTypedLogicalRead(0x89, 7, n, 0, 2)  # N7:n
                with pytest.raises(GatewayError):
                    reply = await driver.execute(read, "read")
                    pytest.fail(f"read returned {reply!r} from garbage")
                write = ProtectedTypedLogicalWrite(0x89, 7, n, 0, (1000 + n).to_bytes(2, "little"))
                with pytest.raises(GatewayError):
                    await driver.execute(write, "write")
                    pytest.fail("a write was confirmed by garbage")
        finally:
            await driver.close()
        assert controller.sent > 0 and driver.counters.transactions == 0


async def test_gateway_in_front_of_garbage_answers_only_0x0b() -> None:
    async with (
        GarbageController(seed=21, alphabet=SLC_GARBAGE) as slc,
        GarbageController(seed=22, alphabet=DF1_GARBAGE) as df1,
    ):
        text = (
            '[modbus]\nlisten = "127.0.0.1:0"\n\n'
            f'[[link]]\nname = "slc"\nprotocol = "slc-ascii"\nport = "{slc.url}"\nunit = 1\ntimeout = 0.03\n'
            "retries = 1\nstale_after = 0.5\n\n"
            f'[[link]]\nname = "df1"\nprotocol = "df1"\nport = "{df1.url}"\nunit = 2\ntimeout = 0.05\nretries = 1\n'
            'stale_after = 0.5\nchecksum = "bcc"\n\n'
            '[[link.map]]\ntable = "holding"\nstart = 0\naddress = "N7:0"\ncount = 4\n'
        )
        async with Gateway(parse_config(text)) as gw:
            reader, writer = await asyncio.open_connection(HOST, gw.port)
            answers: Counter[bytes] = Counter()
            try:
                deadline = time.monotonic() + 2.5
                tid = 0
                while time.monotonic() < deadline:
                    for unit in (1, 2):
                        tid += 1
                        writer.write(mbap(tid, unit, struct.pack(">BHH", 3, 0, 4)))
                        await writer.drain()
                        header = await reader.readexactly(7)
                        pdu = await reader.readexactly(struct.unpack(">H", header[4:6])[0] - 1)
                        answers[pdu] += 1
                    await asyncio.sleep(0.02)
            finally:
                writer.close()
            assert set(answers) == {bytes((0x83, TARGET_FAILED))}, answers
            assert sum(answers.values()) >= 20
            assert all(unit.driver.counters.transactions == 0 for unit in gw.units)
            assert slc.sent > 0 and df1.sent > 0


# ============================================================================================
# Configuration files: check-config never shows a traceback


def bad_files(directory: Path) -> dict[str, Path]:
    files = {
        "missing": directory / "does-not-exist.toml",
        "directory": directory,
        "empty": directory / "empty.toml",
        "binary": directory / "binary.toml",
        "nul": directory / "nul.toml",
        "not-toml": directory / "not-toml.toml",
        "deeply-nested": directory / "nested.toml",
        "unknown-key": directory / "unknown.toml",
        "wrong-type": directory / "type.toml",
        "tls-file-missing": directory / "tls.toml",
        "too-large": directory / "large.toml",
        "fifo": directory / "fifo.toml",
    }
    link = '[[link]]\nname = "a"\nprotocol = "slc-ascii"\nport = "sim://slc150"\nunit = 1\n'
    files["empty"].write_text("")
    files["binary"].write_bytes(bytes(range(256)) * 4)
    files["nul"].write_text(link + "\0\n")
    files["not-toml"].write_text("[modbus\nlisten = \n")
    files["deeply-nested"].write_text("x = " + "[" * 100000 + "]" * 100000 + "\n")
    files["unknown-key"].write_text("[modbus]\nlisen = \"127.0.0.1:5020\"\n" + link)
    files["wrong-type"].write_text(link.replace("unit = 1", 'unit = "1"'))
    (directory / "cert.pem").write_text("not checked here\n")
    files["tls-file-missing"].write_text('[modbus.tls]\ncert = "cert.pem"\nkey = "nope.key"\n' + link)
    files["too-large"].write_text("# " + "x" * (1 << 20) + "\n" + link)
    os.mkfifo(files["fifo"])
    return files


def test_check_config_bad_files_one_line_no_traceback(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    for name, path in bad_files(tmp_path).items():
        status = cli_main(["check-config", str(path)])
        out, err = capsys.readouterr()
        assert status == 1, (name, status, out, err)
        assert out == "", (name, out)
        lines = err.strip("\n").split("\n")
        assert len(lines) == 1, (name, err)
        assert lines[0].startswith("slc-gateway check-config: "), (name, err)
        assert "Traceback" not in err, (name, err)


def test_check_config_in_a_real_process(tmp_path: Path) -> None:
    files = bad_files(tmp_path)
    for name in ("binary", "deeply-nested", "fifo"):
        result = subprocess.run(
            [sys.executable, "-m", "gateway", "check-config", str(files[name])],
            capture_output=True, text=True, timeout=60, check=False,
        )
        assert result.returncode == 1, (name, result)
        assert result.stdout == "" and result.stderr.count("\n") == 1, (name, result.stderr)
        assert "Traceback" not in result.stderr, (name, result.stderr)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    content=st.binary(max_size=300)
    | st.text(alphabet="[]=\"'.#\n abcdeiklmnoprstuvwxyz0123456789:/", max_size=300).map(str.encode)
)
def test_check_config_fuzz(tmp_path: Path, capsys: pytest.CaptureFixture[str], content: bytes) -> None:
    path = tmp_path / "fuzz.toml"
    path.write_bytes(content)
    status = cli_main(["check-config", str(path)])
    _, err = capsys.readouterr()
    assert status in (0, 1), status
    if status == 1:
        assert err.startswith("slc-gateway check-config: ") and "Traceback" not in err, err



def test_check_config_rejects_tls_files_that_are_not_pem(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Found while writing these tests (fixed in a0be906): check-config only checked that the files
    existed, and `run` then failed with '[SSL] PEM lib (_ssl.c:3905)', naming no file."""
    (tmp_path / "cert.pem").write_text("garbage\n")
    (tmp_path / "key.pem").write_text("garbage\n")
    path = tmp_path / "gateway.toml"
    path.write_text(
        '[modbus.tls]\nlisten = "127.0.0.1:0"\ncert = "cert.pem"\nkey = "key.pem"\n'
        '[[link]]\nname = "a"\nprotocol = "slc-ascii"\nport = "sim://slc150"\nunit = 1\n'
    )
    status = cli_main(["check-config", str(path)])
    _, err = capsys.readouterr()
    assert status == 1
    assert "cert.pem" in err and err.count("\n") == 1, err
