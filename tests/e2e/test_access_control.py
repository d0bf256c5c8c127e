"""End to end: who may read and write, as SCADA sees it.

A real ``Gateway`` (in-process simulated SLC 150s, ``sim://``), real sockets on 127.0.0.1, and
pymodbus clients (plain and TLS) or raw MBAP over a socket where the exact bytes matter:

* ``read_only = true``: every write function answers 0x02 and nothing reaches the controller;
* ``writable`` ranges: writes inside are applied, writes outside (or straddling) answer 0x02;
* ``allow``: a client outside the networks is closed at connect, without a reply byte;
* ``[modbus.tls]``: Modbus/TCP Security with certificates made by the ``openssl`` command;
  with ``client_ca`` a client without a certificate, or with one from another CA, gets nothing;
* ``[metrics]``: ``/metrics`` and ``/healthz`` of the same gateway;
* nothing secret in the log: no private key material, even at DEBUG.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import shutil
import ssl
import struct
import subprocess
import sys
import uuid
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from pymodbus.client import AsyncModbusTcpClient, AsyncModbusTlsClient

from gateway import healthcheck
from gateway.app import Gateway
from gateway.config import parse_config
from gateway.kinds.slc_ascii.sim import SlcAsciiSimulator
from gateway.sim import get_simulator
from tests.net import mbap

HOST = "127.0.0.1"
ILLEGAL_ADDRESS = 0x02
ROLE_OID = "1.3.6.1.4.1.50316.802.1"  # Modbus/TCP Security role extension (MB-TCP-Security-v36, R-21)


pytestmark = pytest.mark.usefixtures("forget_simulators")


def sim_url() -> str:
    return f"sim://slc150?ladder=0&instance={uuid.uuid4().hex}"


def link_toml(unit: int, url: str, **keys: Any) -> str:
    lines = ["[[link]]", f'name = "link-{unit}"', 'protocol = "slc-ascii"', f'port = "{url}"', f"unit = {unit}"]
    lines += [f"{key} = {json.dumps(value)}" for key, value in keys.items()]
    return "\n".join(lines) + "\n"


def modbus_toml(**keys: Any) -> str:
    lines = ["[modbus]"] + ([] if "listen" in keys else ['listen = "127.0.0.1:0"'])
    lines += [f"{key} = {json.dumps(value)}" for key, value in keys.items()]
    return "\n".join(lines) + "\n"


@contextlib.asynccontextmanager
async def tcp_client(port: int) -> AsyncIterator[AsyncModbusTcpClient]:
    client = AsyncModbusTcpClient(HOST, port=port, timeout=3, retries=0)
    assert await client.connect()
    try:
        yield client
    finally:
        client.close()


async def until_ready(client: AsyncModbusTcpClient | AsyncModbusTlsClient, unit: int) -> None:
    """Until a whole scan is cached (the 951-982 block is read last)."""
    async with asyncio.timeout(10):
        while True:
            holding = await client.read_holding_registers(0, count=64, device_id=unit)
            bits = await client.read_discrete_inputs(951, count=32, device_id=unit)
            if not holding.isError() and not bits.isError():
                return
            await asyncio.sleep(0.02)


def code(reply: Any) -> int | None:
    return reply.exception_code if reply.isError() else None


READ_HOLDING_0 = struct.pack(">BHH", 3, 0, 2)


# --------------------------------------------------------------------------------------------
# read_only and writable


async def test_read_only_link_refuses_every_write_with_0x02() -> None:
    url = sim_url()
    sim = get_simulator(url)
    assert isinstance(sim, SlcAsciiSimulator)
    before = bytes(sim.memory)
    config = parse_config(modbus_toml() + link_toml(1, url, read_only=True))
    async with Gateway(config) as gw, tcp_client(gw.port) as client:
        await until_ready(client, 1)
        assert code(await client.write_register(0, 5, device_id=1)) == ILLEGAL_ADDRESS
        assert code(await client.write_registers(0, [1, 2, 3], device_id=1)) == ILLEGAL_ADDRESS
        assert code(await client.write_coil(701, True, device_id=1)) == ILLEGAL_ADDRESS
        assert code(await client.write_coils(701, [True, False], device_id=1)) == ILLEGAL_ADDRESS
        # Reads still work.
        assert code(await client.read_holding_registers(0, count=4, device_id=1)) is None
        assert code(await client.read_coils(701, count=8, device_id=1)) is None
        assert gw.units[0].write_requests == 0
    assert sim.applied_writes == []
    assert bytes(sim.memory) == before


async def test_writable_ranges_allow_inside_and_refuse_outside() -> None:
    url = sim_url()
    sim = get_simulator(url)
    assert isinstance(sim, SlcAsciiSimulator)
    config = parse_config(modbus_toml() + link_toml(1, url, writable=["holding:0-9", "coil:701-708"]))
    async with Gateway(config) as gw, tcp_client(gw.port) as client:
        await until_ready(client, 1)
        # Inside: applied, once.
        assert code(await client.write_register(5, 1234, device_id=1)) is None
        assert code(await client.write_registers(8, [11, 22], device_id=1)) is None
        assert code(await client.write_coil(701, True, device_id=1)) is None
        # Outside, or only partly inside: 0x02, nothing sent.
        assert code(await client.write_register(10, 1, device_id=1)) == ILLEGAL_ADDRESS
        assert code(await client.write_register(40, 1, device_id=1)) == ILLEGAL_ADDRESS  # a preset
        assert code(await client.write_registers(9, [1, 2], device_id=1)) == ILLEGAL_ADDRESS  # 9-10 straddles
        assert code(await client.write_coil(709, True, device_id=1)) == ILLEGAL_ADDRESS
        assert code(await client.write_coils(707, [True, True, True], device_id=1)) == ILLEGAL_ADDRESS
        reply = await client.read_holding_registers(5, count=5, device_id=1)
        assert reply.registers == [1234, 0, 0, 11, 22]
    assert sim.applied_writes == [("word", 10, 1234), ("word", 16, 11), ("word", 18, 22), ("byte", 0xA6, 0x01)]
    assert sim.word(20) == 0 and sim.word(0x50) & 0x7FFF != 1


# --------------------------------------------------------------------------------------------
# allow


async def refused_at_connect(port: int) -> bool:
    """Connect, send a request: True if the server closed without sending a byte."""
    reader, writer = await asyncio.open_connection(HOST, port)
    try:
        with contextlib.suppress(ConnectionError):
            writer.write(mbap(1, 1, READ_HOLDING_0))
            await writer.drain()
        async with asyncio.timeout(2):
            try:
                data = await reader.read(100)
            except ConnectionError:
                data = b""
        return data == b""
    finally:
        writer.close()
        with contextlib.suppress(ConnectionError):
            await writer.wait_closed()


async def test_allow_list_refuses_a_client_outside_it() -> None:
    config = parse_config(modbus_toml(allow=["10.0.0.0/8"], loopback_reads=False) + link_toml(1, sim_url()))
    async with Gateway(config) as gw:
        assert await refused_at_connect(gw.port)
        client = AsyncModbusTcpClient(HOST, port=gw.port, timeout=1, retries=0)
        try:
            await client.connect()
            with contextlib.suppress(Exception):
                reply = await client.read_holding_registers(0, count=1, device_id=1)
                pytest.fail(f"a refused client got a reply: {reply}")
        finally:
            client.close()
        server = gw.servers[0]
        assert server.counters.connections_refused >= 2
        assert server.counters.connections_accepted == 0
        assert server.counters.requests == {}


async def test_allow_list_serves_a_client_inside_it() -> None:
    config = parse_config(modbus_toml(allow=["192.168.0.0/16", "127.0.0.0/8"]) + link_toml(1, sim_url()))
    async with Gateway(config) as gw, tcp_client(gw.port) as client:
        await until_ready(client, 1)
        assert gw.servers[0].counters.connections_refused == 0
        assert not await refused_at_connect(gw.port)


async def test_health_check_works_with_an_allow_list_without_loopback() -> None:
    """Issue 14: the container health check connects from 127.0.0.1; an allow list without
    loopback made the container unhealthy. Loopback outside allow is now let in for reads only."""
    url = sim_url()
    sim = get_simulator(url)
    assert isinstance(sim, SlcAsciiSimulator)
    config = parse_config(modbus_toml(allow=["10.0.0.0/8"]) + link_toml(1, url))
    async with Gateway(config) as gw:
        assert await asyncio.to_thread(healthcheck.check, HOST, gw.port, 1) in (0, 1)
        async with tcp_client(gw.port) as client:
            await until_ready(client, 1)
            for reply in (
                await client.write_register(0, 5, device_id=1),
                await client.write_registers(0, [1, 2], device_id=1),
                await client.write_coil(701, True, device_id=1),
                await client.write_coils(701, [True, False], device_id=1),
            ):
                assert code(reply) == 0x01
        assert gw.units[0].write_requests == 0
    assert sim.applied_writes == []


async def test_adjacent_writable_ranges_are_merged() -> None:
    """Issue 14: FC16 across holding:0-1 and holding:2-3 answered 0x02."""
    url = sim_url()
    sim = get_simulator(url)
    assert isinstance(sim, SlcAsciiSimulator)
    writable = ["holding:2-3", "holding:0-1", "coil:701-702", "coil:703-704"]
    config = parse_config(modbus_toml() + link_toml(1, url, writable=writable))
    async with Gateway(config) as gw, tcp_client(gw.port) as client:
        await until_ready(client, 1)
        assert code(await client.write_registers(0, [11, 22, 33, 44], device_id=1)) is None
        assert code(await client.write_coils(701, [True] * 4, device_id=1)) is None
        assert code(await client.write_registers(3, [1, 2], device_id=1)) == ILLEGAL_ADDRESS  # 4 is outside
        reply = await client.read_holding_registers(0, count=4, device_id=1)
        assert reply.registers == [11, 22, 33, 44]


# --------------------------------------------------------------------------------------------
# TLS


@dataclass
class Pki:
    ca: Path
    server_cert: Path
    server_key: Path
    client_cert: Path
    client_key: Path
    rogue_cert: Path  # a client certificate from another CA
    rogue_key: Path


def openssl(directory: Path, *args: str) -> None:
    subprocess.run(["openssl", *args], cwd=directory, check=True, capture_output=True, timeout=60)


def make_ca(directory: Path, name: str) -> None:
    openssl(directory, "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
            "-keyout", f"{name}.key", "-out", f"{name}.pem", "-days", "2", "-subj", f"/CN={name}")


def make_cert(directory: Path, name: str, ca: str, extensions: str) -> None:
    openssl(directory, "req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
            "-keyout", f"{name}.key", "-out", f"{name}.csr", "-subj", f"/CN={name}")
    (directory / f"{name}.ext").write_text(extensions)
    openssl(directory, "x509", "-req", "-in", f"{name}.csr", "-CA", f"{ca}.pem", "-CAkey", f"{ca}.key",
            "-CAcreateserial", "-out", f"{name}.pem", "-days", "2", "-extfile", f"{name}.ext")


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Pki:
    if shutil.which("openssl") is None:
        pytest.skip("the openssl command is not installed (Debian package openssl)")
    directory = tmp_path_factory.mktemp("pki")
    make_ca(directory, "ca")
    make_ca(directory, "rogue-ca")
    make_cert(directory, "server", "ca", "subjectAltName=IP:127.0.0.1\nextendedKeyUsage=serverAuth\n")
    make_cert(directory, "client", "ca", "extendedKeyUsage=clientAuth\n")
    make_cert(directory, "rogue", "rogue-ca", "extendedKeyUsage=clientAuth\n")
    for role in ("operator", "viewer"):
        make_cert(directory, role, "ca", f"extendedKeyUsage=clientAuth\n{ROLE_OID}=ASN1:UTF8String:{role}\n")
    d = directory
    return Pki(d / "ca.pem", d / "server.pem", d / "server.key", d / "client.pem", d / "client.key",
               d / "rogue.pem", d / "rogue.key")


def tls_toml(pki: Pki, *, client_ca: bool, roles: dict[str, str] | None = None) -> str:
    text = f'\n[modbus.tls]\nlisten = "127.0.0.1:0"\ncert = "{pki.server_cert}"\nkey = "{pki.server_key}"\n'
    if client_ca:
        text += f'client_ca = "{pki.ca}"\n'
    if roles:
        text += "[modbus.tls.roles]\n" + "".join(f"{name} = {json.dumps(r)}\n" for name, r in roles.items())
    return text + "\n"


def client_context(pki: Pki, cert: Path | None = None, key: Path | None = None) -> ssl.SSLContext:
    context = ssl.create_default_context(ssl.Purpose.SERVER_AUTH, cafile=str(pki.ca))
    if cert is not None and key is not None:
        context.load_cert_chain(str(cert), str(key))
    return context


async def tls_exchange(port: int, context: ssl.SSLContext) -> bytes:
    """TLS connect, send one read request, return what came back (b"" when closed or refused)."""
    try:
        reader, writer = await asyncio.open_connection(HOST, port, ssl=context, server_hostname=HOST)
    except (ssl.SSLError, ConnectionError):
        return b""
    try:
        writer.write(mbap(7, 1, READ_HOLDING_0))
        await writer.drain()
        async with asyncio.timeout(3):
            return await reader.read(100)
    except (ssl.SSLError, ConnectionError):
        return b""
    finally:
        writer.close()
        with contextlib.suppress(ssl.SSLError, ConnectionError):
            await writer.wait_closed()


async def test_tls_with_client_certificates(pki: Pki, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level("DEBUG")
    config = parse_config(modbus_toml() + tls_toml(pki, client_ca=True) + link_toml(1, sim_url()))
    async with Gateway(config) as gw:
        tls_port = gw.servers[1].port
        assert gw.servers[1].name == "modbus-tls" and tls_port != gw.port

        client = AsyncModbusTlsClient(
            HOST, port=tls_port, sslctx=client_context(pki, pki.client_cert, pki.client_key), timeout=3, retries=0
        )
        assert await client.connect()
        try:
            await until_ready(client, 1)
            reply = await client.read_holding_registers(0, count=2, device_id=1)
            assert not reply.isError() and reply.registers == [0, 0]
        finally:
            client.close()

        # The same request over raw TLS: an MBAP reply with our transaction id.
        answer = await tls_exchange(tls_port, client_context(pki, pki.client_cert, pki.client_key))
        assert answer == struct.pack(">HHHBBB2H", 7, 0, 7, 1, 3, 4, 0, 0)
        # No client certificate, or one from another CA: refused, not a byte of Modbus.
        assert await tls_exchange(tls_port, client_context(pki)) == b""
        assert await tls_exchange(tls_port, client_context(pki, pki.rogue_cert, pki.rogue_key)) == b""
        assert gw.servers[1].counters.connections_dropped >= 2
        assert gw.servers[1].counters.requests.get(3, 0) >= 3  # only from the clients with a certificate
    assert_no_secrets(caplog.text, pki)


async def test_tls_without_client_ca_serves_any_client(pki: Pki) -> None:
    config = parse_config(modbus_toml() + tls_toml(pki, client_ca=False) + link_toml(1, sim_url()))
    async with Gateway(config) as gw:
        tls_port = gw.servers[1].port
        client = AsyncModbusTlsClient(HOST, port=tls_port, sslctx=client_context(pki), timeout=3, retries=0)
        assert await client.connect()
        try:
            await until_ready(client, 1)
        finally:
            client.close()
        # A plain TCP client speaking Modbus to the TLS port gets nothing back.
        reader, writer = await asyncio.open_connection(HOST, tls_port)
        try:
            writer.write(mbap(1, 1, READ_HOLDING_0))
            await writer.drain()
            async with asyncio.timeout(12):
                data = await reader.read(100)
            assert data == b"" or data[0] == 0x15, data  # closed, or a TLS alert record: no Modbus reply
        finally:
            writer.close()
            with contextlib.suppress(ConnectionError):
                await writer.wait_closed()


async def test_tls_only_configuration_refuses_plain_tcp(pki: Pki) -> None:
    """Issue 14: with TLS and client_ca the plain listener stayed open and took a plain FC6."""
    url = sim_url()
    sim = get_simulator(url)
    assert isinstance(sim, SlcAsciiSimulator)
    config = parse_config(modbus_toml(listen="") + tls_toml(pki, client_ca=True) + link_toml(1, url))
    assert config.warnings() == []
    async with Gateway(config) as gw:
        assert [server.name for server in gw.servers] == ["modbus-tls"]
        tls_port = gw.port
        # Plain Modbus to the TLS port: no Modbus reply (a TLS alert or a close), nothing written.
        reader, writer = await asyncio.open_connection(HOST, tls_port)
        try:
            writer.write(mbap(1, 1, struct.pack(">BHH", 6, 1, 777)))
            await writer.drain()
            async with asyncio.timeout(12):
                data = await reader.read(100)
            assert data == b"" or data[0] == 0x15, data
        finally:
            writer.close()
            with contextlib.suppress(ConnectionError):
                await writer.wait_closed()
        answer = await tls_exchange(tls_port, client_context(pki, pki.client_cert, pki.client_key))
        assert answer[:2] == struct.pack(">H", 7)
    assert sim.applied_writes == []


def test_tls_with_client_ca_beside_a_plain_listener_warns(pki: Pki, tmp_path: Path) -> None:
    path = tmp_path / "gateway.toml"
    path.write_text(modbus_toml(listen="0.0.0.0:0") + tls_toml(pki, client_ca=True) + link_toml(1, "sim://slc150"))
    result = subprocess.run(
        [sys.executable, "-m", "gateway", "check-config", str(path)],
        capture_output=True, text=True, timeout=60, check=False,
    )
    assert result.returncode == 0, result.stderr
    assert "warning: [modbus.tls] requires client certificates, but the plain listener" in result.stderr
    assert 'listen = ""' in result.stderr
    loopback = modbus_toml(listen="127.0.0.1:0") + tls_toml(pki, client_ca=True) + link_toml(1, "sim://slc150")
    assert parse_config(loopback).warnings() == []  # plain on loopback only: for local health checks


async def test_roles_from_certificates_end_to_end(pki: Pki, caplog: pytest.LogCaptureFixture) -> None:
    url = sim_url()
    sim = get_simulator(url)
    assert isinstance(sim, SlcAsciiSimulator)
    roles = {"operator": "read-write", "viewer": "read"}
    config = parse_config(modbus_toml(listen="") + tls_toml(pki, client_ca=True, roles=roles) + link_toml(1, url))
    async with Gateway(config) as gw:
        port = gw.port
        for name, cert, key, can_write in (
            ("viewer", pki.ca.parent / "viewer.pem", pki.ca.parent / "viewer.key", False),
            ("no role", pki.client_cert, pki.client_key, False),
            ("operator", pki.ca.parent / "operator.pem", pki.ca.parent / "operator.key", True),
        ):
            client = AsyncModbusTlsClient(
                HOST, port=port, sslctx=client_context(pki, cert, key), timeout=3, retries=0
            )
            assert await client.connect(), name
            try:
                await until_ready(client, 1)
                writes = [
                    await client.write_register(0, 5, device_id=1),
                    await client.write_registers(0, [6, 7], device_id=1),
                    await client.write_coil(701, True, device_id=1),
                    await client.write_coils(701, [True, False], device_id=1),
                ]
                expected = None if can_write else 0x01
                assert [code(reply) for reply in writes] == [expected] * 4, name
                assert code(await client.read_holding_registers(0, count=2, device_id=1)) is None
            finally:
                client.close()
    assert [w for w in sim.applied_writes if w[0] == "word"] == [("word", 0, 5), ("word", 0, 6), ("word", 2, 7)]


def assert_no_secrets(log_text: str, pki: Pki) -> None:
    assert "PRIVATE KEY" not in log_text
    for key in (pki.server_key, pki.client_key, pki.rogue_key):
        for line in key.read_text().splitlines():
            if line and not line.startswith("-----"):
                assert line not in log_text, f"private key material of {key.name} in the log"


def test_check_config_prints_no_key_material(pki: Pki, tmp_path: Path) -> None:
    path = tmp_path / "gateway.toml"
    path.write_text(modbus_toml() + tls_toml(pki, client_ca=True) + link_toml(1, "sim://slc150"))
    result = subprocess.run(
        [sys.executable, "-m", "gateway", "check-config", str(path)],
        capture_output=True, text=True, timeout=60, check=False,
    )
    assert result.returncode == 0, result.stderr
    assert str(pki.server_key) in result.stdout  # the path, which is not a secret
    assert_no_secrets(result.stdout + result.stderr, pki)


# --------------------------------------------------------------------------------------------
# metrics


async def http_get(port: int, path: str) -> tuple[int, bytes]:
    reader, writer = await asyncio.open_connection(HOST, port)
    try:
        writer.write(f"GET {path} HTTP/1.1\r\nHost: {HOST}:{port}\r\n\r\n".encode())
        await writer.drain()
        async with asyncio.timeout(5):
            raw = await reader.read()
    finally:
        writer.close()
    head, _, body = raw.partition(b"\r\n\r\n")
    return int(head.split(b" ", 2)[1]), body


async def test_metrics_and_healthz_end_to_end() -> None:
    silent = "sim://slc150?drop=1&instance=" + uuid.uuid4().hex
    text = modbus_toml() + '\n[metrics]\nlisten = "127.0.0.1:0"\n\n' + link_toml(1, sim_url())
    text += link_toml(2, silent, timeout=0.05, retries=0, stale_after=0.5)
    async with Gateway(parse_config(text)) as gw, tcp_client(gw.port) as client:
        assert gw.metrics is not None
        await until_ready(client, 1)
        assert code(await client.write_register(0, 42, device_id=1)) is None
        async with asyncio.timeout(5):
            while True:  # the silent controller's link goes down after its first unanswered poll
                status, body = await http_get(gw.metrics.port, "/metrics")
                assert status == 200
                metrics = body.decode()
                if 'slc_gateway_link_up{link="link-2",unit="2"} 0.0' in metrics:
                    break
                await asyncio.sleep(0.05)
        assert 'slc_gateway_link_up{link="link-1",unit="1"} 1.0' in metrics
        assert 'slc_gateway_link_up{link="link-2",unit="2"} 0.0' in metrics
        assert 'slc_gateway_write_requests_total{link="link-1",unit="1"} 1.0' in metrics
        assert 'slc_gateway_modbus_connections{server="modbus"} 1.0' in metrics
        status, body = await http_get(gw.metrics.port, "/healthz")
        document = json.loads(body)
        assert status == 503 and document["status"] != "ok"
        assert document["links"]["link-1"]["up"] is True
        assert document["links"]["link-2"]["up"] is False
        assert "sim://" not in body.decode()  # no port URLs or paths in the public health document
