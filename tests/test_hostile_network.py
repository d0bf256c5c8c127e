"""Issue 14, the network edge: slots that cannot be held, bounded logs, roles from certificates.

The Modbus server over real sockets on loopback, with the dict backend of test_modbus_server,
under the attacks of issue 14 at bounded loads: slowloris, silent TLS connections at the
handshake budget, one host taking every slot, a pipelining client that resets, bad headers in a
loop, and TLS clients whose certificates carry a Modbus role (MB-TCP-Security OID
1.3.6.1.4.1.50316.802.1, made with the openssl command).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import shutil
import socket
import ssl
import struct
import subprocess
from collections.abc import AsyncIterator, Sequence
from pathlib import Path

import pytest
from modbus.test_server import (
    DictBackend,
    _client_context,
    _make_certificates,
    close_writer,
    closed_by_peer,
    connect,
    frame,
    read_reply,
    read_request,
    wait_until,
)

from gateway.clients import current_client
from gateway.logutil import RepeatLog, redact_url
from gateway.modbus.admission import RolePolicy, role_from_certificate
from gateway.modbus.server import ModbusTcpServer, make_tls_context

HOST = "127.0.0.1"
UNIT = 1


@contextlib.asynccontextmanager
async def serving(backend: DictBackend, **options: object) -> AsyncIterator[ModbusTcpServer]:
    modbus = ModbusTcpServer(backend, HOST, 0, **options)  # type: ignore[arg-type]
    await modbus.start()
    try:
        yield modbus
    finally:
        await modbus.close()


async def served(modbus: ModbusTcpServer, tid: int = 7, ssl_context: ssl.SSLContext | None = None) -> bool:
    """Whether a well-behaved client connects and gets its read answered (within 2 s)."""
    try:
        reader, writer = await connect(modbus, ssl_context)
    except (OSError, ssl.SSLError):
        return False
    try:
        writer.write(read_request(tid, 3, 0, 1))
        return (await read_reply(reader))[0] == tid
    except (OSError, ssl.SSLError, asyncio.IncompleteReadError, TimeoutError):
        return False
    finally:
        await close_writer(writer)


# -- slowloris ----------------------------------------------------------------------------


async def _slowloris(port: int, stop: asyncio.Event, period: float, source: str = HOST) -> int:
    """Hold a connection by sending one byte of a frame every ``period`` s; reconnect when closed."""
    opened = 0
    request = read_request(1, 3, 0, 1)
    while not stop.is_set():
        try:
            reader, writer = await asyncio.open_connection(HOST, port, local_addr=(source, 0))
        except OSError:
            await asyncio.sleep(0.05)
            continue
        opened += 1
        try:
            for byte in request * 100:
                writer.write(bytes([byte]))
                await writer.drain()
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(period):
                        if await reader.read(1) == b"":
                            break
                        await stop.wait()
                if stop.is_set():
                    break
        except OSError:
            pass
        finally:
            writer.transport.abort()
    return opened


async def test_slowloris_at_max_connections_leaves_room_for_a_good_client() -> None:
    backend = DictBackend()
    # idle_timeout far above the byte period: only the frame timeout or eviction frees a slot.
    async with serving(backend, max_connections=4, idle_timeout=30.0, frame_timeout=1.0) as modbus:
        stop = asyncio.Event()
        attackers = [asyncio.create_task(_slowloris(modbus.port, stop, 0.3)) for _ in range(4)]
        try:
            await wait_until(lambda: modbus.connection_count == 4)
            await asyncio.sleep(0.5)
            results = []
            for tid in range(5):
                results.append(await served(modbus, tid))
                await asyncio.sleep(0.3)
            assert all(results), results
        finally:
            stop.set()
            await asyncio.gather(*attackers)
        assert modbus.admission.evicted >= 1


async def test_a_frame_trickled_one_byte_at_a_time_is_closed_after_frame_timeout() -> None:
    backend = DictBackend()
    async with serving(backend, idle_timeout=30.0, frame_timeout=0.5) as modbus:
        reader, writer = await connect(modbus)
        started = asyncio.get_running_loop().time()
        closed = False
        for byte in read_request(1, 3, 0, 1)[:-1]:
            writer.write(bytes([byte]))
            if await closed_by_peer(reader, within=0.2):
                closed = True
                break
        await close_writer(writer)
        assert closed
        assert asyncio.get_running_loop().time() - started < 2.0
        assert modbus.counters.connections_dropped == 1
        # A frame that arrives in pieces within the timeout is served.
        reader, writer = await connect(modbus)
        request = read_request(2, 3, 0, 1)
        writer.write(request[:5])
        await asyncio.sleep(0.3)
        writer.write(request[5:])
        assert (await read_reply(reader))[0] == 2
        await close_writer(writer)


async def test_a_polling_client_is_never_evicted() -> None:
    backend = DictBackend()
    async with serving(backend, max_connections=2, idle_timeout=30.0) as modbus:
        readers_writers = [await connect(modbus) for _ in range(2)]
        for tid, (reader, writer) in enumerate(readers_writers):
            writer.write(read_request(tid, 3, 0, 1))
            assert (await read_reply(reader))[0] == tid
        assert not await served(modbus, 9)  # both slots in use: refused, nobody evicted
        assert modbus.admission.evicted == 0
        for tid, (reader, writer) in enumerate(readers_writers):
            writer.write(read_request(tid, 3, 0, 1))
            assert (await read_reply(reader))[0] == tid
            await close_writer(writer)


# -- one host taking every slot ------------------------------------------------------------


async def test_per_address_cap_refuses_one_host_and_serves_another(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, logger="gateway.modbus.server")
    backend = DictBackend()
    async with serving(backend, max_connections=8, max_connections_per_address=2, log_interval=0.5) as modbus:
        kept = [await asyncio.open_connection(HOST, modbus.port, local_addr=("127.0.0.2", 0)) for _ in range(2)]
        for _ in range(5):
            reader, writer = await asyncio.open_connection(HOST, modbus.port, local_addr=("127.0.0.2", 0))
            assert await closed_by_peer(reader)
            writer.transport.abort()
        assert await served(modbus)  # 127.0.0.1 is another host
        assert modbus.counters.connections_refused == 5
        await asyncio.sleep(0.7)  # the interval ends: one summary line
        lines = [r.getMessage() for r in caplog.records if "max_connections_per_address" in r.getMessage()]
        assert len(lines) == 2, lines
        assert "refused connection from 127.0.0.2" in lines[0]
        assert "4 more in the last 0.5 s, from 127.0.0.2 (4)" in lines[1]
        for _, writer in kept:
            writer.transport.abort()


# -- TLS handshake exhaustion ---------------------------------------------------------------


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Path:
    if shutil.which("openssl") is None:
        pytest.skip("the openssl command is not installed (Debian package openssl): TLS tests cannot run")
    directory = tmp_path_factory.mktemp("pki")
    _make_certificates(directory)
    for name, role in (("operator", "operator"), ("viewer", "viewer"), ("stranger", "janitor")):
        _client_certificate(directory, name, f"{role_extension(role)}\n")
    _client_certificate(directory, "printable", "1.3.6.1.4.1.50316.802.1=ASN1:PRINTABLESTRING:operator\n")
    return directory


def role_extension(role: str) -> str:
    return f"extendedKeyUsage=clientAuth\n1.3.6.1.4.1.50316.802.1=ASN1:UTF8String:{role}"


def _client_certificate(directory: Path, name: str, extensions: str) -> None:
    (directory / f"{name}.ext").write_text(extensions)
    run = ["openssl", "req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes"]
    subprocess.run(
        [*run, "-keyout", f"{name}.key", "-out", f"{name}.csr", "-subj", f"/O=plant/CN={name}"],
        cwd=directory, check=True, capture_output=True, timeout=30,
    )
    subprocess.run(
        ["openssl", "x509", "-req", "-in", f"{name}.csr", "-CA", "ca.pem", "-CAkey", "ca.key", "-CAcreateserial",
         "-days", "2", "-out", f"{name}.pem", "-extfile", f"{name}.ext"],
        cwd=directory, check=True, capture_output=True, timeout=30,
    )


def tls_context(pki: Path) -> ssl.SSLContext:
    return make_tls_context(pki / "server.pem", pki / "server.key", client_ca=str(pki / "ca.pem"))


async def _silent(port: int, stop: asyncio.Event, count: int) -> None:
    """Keep ``count`` TCP connections open to the TLS port, saying nothing; reopen closed ones."""

    async def one() -> None:
        while not stop.is_set():
            try:
                reader, writer = await asyncio.open_connection(HOST, port, local_addr=("127.0.0.3", 0))
            except OSError:
                await asyncio.sleep(0.02)
                continue
            with contextlib.suppress(TimeoutError, OSError):
                async with asyncio.timeout(5):
                    await asyncio.wait(
                        [asyncio.ensure_future(reader.read(1)), asyncio.ensure_future(stop.wait())],
                        return_when=asyncio.FIRST_COMPLETED,
                    )
            writer.transport.abort()

    await asyncio.gather(*(one() for _ in range(count)))


async def test_silent_tls_connections_do_not_keep_a_certified_client_out(pki: Path) -> None:
    backend = DictBackend()
    async with serving(
        backend, ssl_context=tls_context(pki), max_connections=4, max_handshakes=4, handshake_timeout=1.0
    ) as modbus:
        stop = asyncio.Event()
        attack = asyncio.create_task(_silent(modbus.port, stop, 16))
        try:
            await wait_until(lambda: modbus.admission.handshaking == 4)
            results = [await served(modbus, tid, _client_context(pki)) for tid in range(6)]
            assert all(results), results
        finally:
            stop.set()
            await attack
        assert modbus.admission.evicted >= 1


async def test_handshake_timeout_is_its_own(pki: Path) -> None:
    backend = DictBackend()
    async with serving(backend, ssl_context=tls_context(pki), idle_timeout=30.0, handshake_timeout=0.3) as modbus:
        reader, writer = await asyncio.open_connection(HOST, modbus.port)
        assert await closed_by_peer(reader, within=2.0)
        await close_writer(writer)
        await wait_until(lambda: modbus.connection_count == 0)


# -- roles from certificates ------------------------------------------------------------------


def _der(pki: Path, name: str) -> bytes:
    return ssl.PEM_cert_to_DER_cert((pki / f"{name}.pem").read_text())


def test_role_is_read_from_the_certificate_extension(pki: Path) -> None:
    assert role_from_certificate(_der(pki, "operator")) == "operator"
    assert role_from_certificate(_der(pki, "viewer")) == "viewer"
    assert role_from_certificate(_der(pki, "client")) is None  # no role extension
    with pytest.raises(ValueError, match="UTF8String"):
        role_from_certificate(_der(pki, "printable"))
    der = _der(pki, "operator")
    for cut in (1, 10, len(der) // 2, len(der) - 1):
        with pytest.raises(ValueError):
            role_from_certificate(der[:cut])


class AuditBackend(DictBackend):
    """Records which client each write came from (the name the write path's audit log prints)."""

    def __init__(self) -> None:
        super().__init__()
        self.writers: list[str | None] = []

    def _note(self) -> None:
        client = current_client.get()
        self.writers.append(None if client is None else client.name)

    async def write_registers(self, unit: int, address: int, values: Sequence[int]) -> None:
        self._note()
        await super().write_registers(unit, address, values)

    async def write_coils(self, unit: int, address: int, values: Sequence[bool]) -> None:
        self._note()
        await super().write_coils(unit, address, values)


WRITES = {
    0x05: bytes([0x05, 0, 1, 0xFF, 0]),
    0x06: bytes([0x06, 0, 1, 0, 9]),
    0x0F: bytes([0x0F, 0, 1, 0, 2, 1, 3]),
    0x10: bytes([0x10, 0, 1, 0, 1, 2, 0, 9]),
    0x16: bytes([0x16, 0, 1, 0xFF, 0xFF, 0, 0]),
    0x17: bytes([0x17, 0, 0, 0, 1, 0, 1, 0, 1, 2, 0, 9]),
}


async def _ask(reader: asyncio.StreamReader, writer: asyncio.StreamWriter, tid: int, pdu: bytes) -> bytes:
    writer.write(frame(tid, pdu))
    got_tid, _, reply = await read_reply(reader)
    assert got_tid == tid
    return reply


@pytest.mark.parametrize("name", ["viewer", "client", "stranger", "printable"])
async def test_certificate_without_write_rights_gets_0x01_on_every_write_and_can_read(pki: Path, name: str) -> None:
    backend = AuditBackend()
    roles = RolePolicy({"operator": "read-write", "viewer": "read"}, default="read")
    async with serving(backend, ssl_context=tls_context(pki), roles=roles) as modbus:
        reader, writer = await connect(modbus, _client_context(pki, name))
        try:
            for tid, (function_code, pdu) in enumerate(WRITES.items()):
                assert await _ask(reader, writer, tid, pdu) == bytes([function_code | 0x80, 0x01])
            assert await _ask(reader, writer, 99, bytes([3, 0, 1, 0, 1])) == bytes([3, 2, 0, 0])
        finally:
            await close_writer(writer)
    assert backend.writers == []
    assert backend.holding == {} and backend.coils == {}


async def test_operator_certificate_writes_and_the_write_path_knows_who(pki: Path) -> None:
    backend = AuditBackend()
    roles = RolePolicy({"operator": "read-write", "viewer": "read"}, default="read")
    async with serving(backend, ssl_context=tls_context(pki), roles=roles) as modbus:
        reader, writer = await connect(modbus, _client_context(pki, "operator"))
        try:
            assert await _ask(reader, writer, 1, WRITES[0x06]) == WRITES[0x06]
            assert await _ask(reader, writer, 2, WRITES[0x0F]) == WRITES[0x0F][:5]
        finally:
            await close_writer(writer)
    assert backend.holding == {1: 9}
    assert len(backend.writers) == 2
    client = backend.writers[0]
    assert client is not None and client.startswith("O=plant,CN=operator (127.0.0.1:")
    assert client.endswith(", role operator)")


async def test_tls_client_is_named_by_its_certificate_without_roles(pki: Path) -> None:
    backend = AuditBackend()
    async with serving(backend, ssl_context=tls_context(pki)) as modbus:
        reader, writer = await connect(modbus, _client_context(pki, "viewer"))
        try:
            assert await _ask(reader, writer, 1, WRITES[0x06]) == WRITES[0x06]  # no roles: may write
        finally:
            await close_writer(writer)
    client = backend.writers[0]
    assert client is not None and client.startswith("O=plant,CN=viewer (") and client.endswith(", role viewer)")


async def test_plain_tcp_client_identity_is_its_address() -> None:
    backend = AuditBackend()
    async with serving(backend) as modbus:
        reader, writer = await connect(modbus)
        try:
            assert await _ask(reader, writer, 1, WRITES[0x06]) == WRITES[0x06]
        finally:
            await close_writer(writer)
    client = backend.writers[0]
    assert client is not None and client.startswith("127.0.0.1:") and "CN=" not in client


# -- bounded logs ---------------------------------------------------------------------------


def _pipeline_and_reset(port: int, requests: bytes) -> None:
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 2048)
    sock.connect((HOST, port))
    sock.settimeout(5)
    with contextlib.suppress(OSError):
        sock.sendall(requests)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    sock.close()  # RST


async def test_pipelining_client_that_resets_does_not_flood_the_log(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.DEBUG)
    backend = DictBackend()
    unknown_unit = b"".join(read_request(tid & 0xFFFF, 3, 0, 1, unit=99) for tid in range(20000))
    async with serving(backend) as modbus:
        for _ in range(5):
            await asyncio.to_thread(_pipeline_and_reset, modbus.port, unknown_unit)
            await asyncio.sleep(0.2)
        await wait_until(lambda: modbus.connection_count == 0)
    warnings = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert not [r for r in warnings if "socket.send() raised exception" in r.getMessage()]
    assert len(warnings) <= 5, [r.getMessage() for r in warnings]


async def test_bad_headers_in_a_loop_log_one_line_per_interval(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger="gateway.modbus.server")
    backend = DictBackend()
    async with serving(backend, log_interval=0.5) as modbus:
        for tid in range(30):
            reader, writer = await connect(modbus)
            writer.write(frame(tid, bytes([3, 0, 0, 0, 1]), protocol=7))
            assert await closed_by_peer(reader)
            await close_writer(writer)
        await asyncio.sleep(0.7)
    lines = [r.getMessage() for r in caplog.records if "MBAP" in r.getMessage()]
    assert len(lines) == 2, lines  # the first, then one summary with the count and the address
    assert "bad MBAP header (protocol id 7, length 6)" in lines[0]
    assert lines[1] == "modbus: bad MBAP headers: 29 more in the last 0.5 s, from 127.0.0.1 (29)"


async def test_failed_tls_handshakes_are_summarised(pki: Path, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger="gateway.modbus.server")
    backend = DictBackend()
    async with serving(backend, ssl_context=tls_context(pki), log_interval=0.5) as modbus:
        for _ in range(10):
            reader, writer = await asyncio.open_connection(HOST, modbus.port)
            writer.write(b"GET / HTTP/1.0\r\n\r\n")  # not TLS
            assert await closed_by_peer(reader)
            await close_writer(writer)
        await asyncio.sleep(0.7)
    handshake_lines = [r.getMessage() for r in caplog.records if "TLS handshake" in r.getMessage()]
    assert len(handshake_lines) == 2, handshake_lines  # the first, then one summary
    assert "9 more" in handshake_lines[1]


def test_repeat_log_counts_per_cause_and_interval(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO)
    now = [0.0]
    log = RepeatLog(logging.getLogger("test.repeat"), 10.0, clock=lambda: now[0], schedule=lambda *_: None)
    assert log.log(logging.WARNING, "a", "10.0.0.1", "first a")
    assert not log.log(logging.WARNING, "a", "10.0.0.1", "second a")
    assert log.log(logging.WARNING, "b", None, "first b")
    for index in range(20):
        log.log(logging.WARNING, "a", f"10.0.0.{index}", "more a")
    now[0] = 10.5
    log.flush()
    messages = [r.getMessage() for r in caplog.records]
    assert messages[:2] == [
        "first a (repeats are summarised every 10 s)",
        "first b (repeats are summarised every 10 s)",
    ]
    assert messages[2].startswith("a: 21 more in the last 10 s, from 10.0.0.1 (2), ")
    assert "and 12 other addresses (12)" in messages[2]
    assert len(messages) == 3  # b had no repeats: no summary
    assert log.log(logging.WARNING, "a", None, "a again")  # a new interval logs at once


def test_redact_url() -> None:
    assert redact_url("socket://user:secret@10.0.0.5:4001") == "socket://***@10.0.0.5:4001"
    text = "link x: rfc2217://admin:pw@host:2217?timeout=1 down"
    assert redact_url(text) == "link x: rfc2217://***@host:2217?timeout=1 down"
    assert redact_url("socket://10.0.0.5:4001") == "socket://10.0.0.5:4001"


async def test_partial_frame_behind_the_in_flight_limit_is_not_timed() -> None:
    """The frame clock stops while the server does not read (requests in flight at the limit)."""
    backend = DictBackend()
    backend.write_gate = asyncio.Event()
    async with serving(backend, idle_timeout=30.0, frame_timeout=0.3, max_in_flight_per_connection=2) as modbus:
        reader, writer = await connect(modbus)
        write = frame(1, WRITES[0x06])
        writer.write(write + frame(2, WRITES[0x06]) + read_request(3, 3, 0, 1)[:4])  # 2 writes wait
        await asyncio.sleep(1.0)  # beyond frame_timeout while the server is not reading
        assert modbus.counters.connections_dropped == 0
        writer.write(read_request(3, 3, 0, 1)[4:])
        backend.write_gate.set()
        tids = sorted([(await read_reply(reader))[0] for _ in range(3)])
        assert tids == [1, 2, 3]
        await close_writer(writer)


def test_handshake_eviction_picks_the_host_with_the_most_handshakes() -> None:
    from gateway.modbus.admission import Admission

    class FakeSlot:
        def __init__(self) -> None:
            self.evicted = ""

        def stalled_since(self) -> float | None:
            return 0.0

        def evict(self, reason: str) -> None:
            self.evicted = reason

    admission = Admission("t", max_connections=10, max_handshakes=3)
    good = FakeSlot()
    assert admission.admit(good, ("10.0.0.1", 1), handshake_started=0.0)  # the oldest
    attackers = [FakeSlot() for _ in range(20)]
    for index, slot in enumerate(attackers):
        assert admission.admit(slot, ("10.0.0.66", index), handshake_started=1.0 + index)
    assert good.evicted == ""  # the attacker's churn only ever aborts its own handshakes
    assert sum(1 for slot in attackers if slot.evicted) == 18
    assert admission.handshaking == 3 and admission.evicted == 18
    assert admission.handshake_done(good, ("10.0.0.1", 1))
    assert admission.established == 1 and admission.handshaking == 2


def test_slot_eviction_picks_a_stalled_connection_of_the_busiest_host() -> None:
    from gateway.modbus.admission import Admission

    class FakeSlot:
        def __init__(self, since: float | None) -> None:
            self.since = since
            self.evicted = ""

        def stalled_since(self) -> float | None:
            return self.since

        def evict(self, reason: str) -> None:
            self.evicted = reason

    admission = Admission("t", max_connections=4)
    polling = FakeSlot(None)  # completed requests, no partial frame: never evicted
    newcomer = FakeSlot(0.0)  # connected first, no request yet
    assert admission.admit(polling, ("10.0.0.2", 1))
    assert admission.admit(newcomer, ("10.0.0.1", 1))
    attackers = [FakeSlot(1.0 + index) for index in range(10)]
    for index, slot in enumerate(attackers):
        assert admission.admit(slot, ("10.0.0.66", index))
    assert polling.evicted == "" and newcomer.evicted == ""
    assert sum(1 for slot in attackers if slot.evicted) == 8
    everyone_busy = Admission("t", max_connections=1)
    assert everyone_busy.admit(FakeSlot(None), ("10.0.0.2", 1))
    assert not everyone_busy.admit(FakeSlot(0.0), ("10.0.0.3", 1))  # nobody stalled: refused
    assert everyone_busy.refused == 1
