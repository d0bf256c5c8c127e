"""A reload re-reads the access rules and the TLS material; the connections already open stay.

Certificates are made by the ``openssl`` command (the helpers of ``test_access_control``); a
renewed certificate is copied over the files the config names, as certbot or an operator would,
so the config file itself does not change.
"""

from __future__ import annotations

import asyncio
import contextlib
import shutil
import ssl
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
from test_access_control import (
    HOST,
    READ_HOLDING_0,
    link_toml,
    make_ca,
    make_cert,
    mbap,
    modbus_toml,
    sim_url,
)

from gateway.app import Gateway
from gateway.reload import ConfigSource

SERVER_EXTENSIONS = "subjectAltName=IP:127.0.0.1\nextendedKeyUsage=serverAuth\n"


@pytest.fixture(scope="module")
def certificates(tmp_path_factory: pytest.TempPathFactory) -> Path:
    if shutil.which("openssl") is None:
        pytest.skip("the openssl command is not installed (Debian package openssl)")
    directory = tmp_path_factory.mktemp("pki")
    make_ca(directory, "ca")
    make_cert(directory, "first", "ca", SERVER_EXTENSIONS)
    make_cert(directory, "renewed", "ca", SERVER_EXTENSIONS)
    return directory


@contextlib.asynccontextmanager
async def tls_connection(port: int, ca: Path) -> AsyncIterator[tuple[asyncio.StreamReader, asyncio.StreamWriter]]:
    context = ssl.create_default_context(ssl.Purpose.SERVER_AUTH, cafile=str(ca))
    reader, writer = await asyncio.open_connection(HOST, port, ssl=context, server_hostname=HOST)
    try:
        yield reader, writer
    finally:
        writer.close()
        with contextlib.suppress(ssl.SSLError, ConnectionError):
            await writer.wait_closed()


def server_name(writer: asyncio.StreamWriter) -> str:
    """The CN of the certificate the gateway presented."""
    subject = writer.get_extra_info("peercert")["subject"]
    return str(dict(pair[0] for pair in subject)["commonName"])


async def read_once(reader: asyncio.StreamReader, writer: asyncio.StreamWriter, tid: int) -> bytes:
    """FC3 of holding 0-1 on unit 1: the reply (b"" when the gateway closed the connection)."""
    try:
        writer.write(mbap(tid, 1, READ_HOLDING_0))
        await writer.drain()
        async with asyncio.timeout(5):
            return await reader.read(100)
    except ConnectionError:  # refused: aborted by the gateway
        return b""


async def served(reader: asyncio.StreamReader, writer: asyncio.StreamWriter, tid: int) -> bool:
    """Whether unit 1 answers a read with its registers (after its first poll)."""
    async with asyncio.timeout(10):
        while True:
            reply = await read_once(reader, writer, tid)
            if reply[:2] == tid.to_bytes(2, "big") and reply[7:8] == b"\x03":
                return True
            if not reply:
                return False
            await asyncio.sleep(0.05)


async def test_renewed_tls_material_and_a_new_allow_list_apply_to_new_connections(
    certificates: Path, tmp_path: Path
) -> None:
    cert, key = tmp_path / "server.pem", tmp_path / "server.key"
    shutil.copy(certificates / "first.pem", cert)
    shutil.copy(certificates / "first.key", key)
    tls = f'[modbus.tls]\nlisten = "127.0.0.1:0"\ncert = "{cert}"\nkey = "{key}"\n\n'
    file = tmp_path / "gateway.toml"
    file.write_text(modbus_toml(allow=["127.0.0.0/8"], loopback_reads=False) + tls + link_toml(1, sim_url()))
    source = ConfigSource(file)
    loaded = source.load()
    ca = certificates / "ca.pem"
    async with Gateway(loaded.config, source, loaded.sha256) as gw:
        plain_port, tls_port = gw.servers[0].port, gw.servers[1].port
        async with tls_connection(tls_port, ca) as (old_reader, old_writer):
            assert server_name(old_writer) == "first"
            assert await served(old_reader, old_writer, 1)
            plain_reader, plain_writer = await asyncio.open_connection(HOST, plain_port)
            assert await served(plain_reader, plain_writer, 2)

            # renewed on disk: the config file is the same, the material is read again
            shutil.copy(certificates / "renewed.pem", cert)
            shutil.copy(certificates / "renewed.key", key)
            assert await gw.reload()
            assert gw.config_status.restart_needed == ()
            async with tls_connection(tls_port, ca) as (new_reader, new_writer):
                assert server_name(new_writer) == "renewed"
                assert await served(new_reader, new_writer, 3)
            assert await served(old_reader, old_writer, 4)  # the old connection, still open, on the old session

            # loopback out of the allow list: new connections are refused, those open stay
            file.write_text(file.read_text().replace('allow = ["127.0.0.0/8"]', 'allow = ["10.0.0.0/8"]'))
            assert await gw.reload()
            refused_reader, refused_writer = await asyncio.open_connection(HOST, plain_port)
            assert await read_once(refused_reader, refused_writer, 5) == b""
            refused_writer.close()
            assert await served(plain_reader, plain_writer, 6)
            assert await served(old_reader, old_writer, 7)
            plain_writer.close()
    assert gw.servers[0].counters.connections_refused == 1
