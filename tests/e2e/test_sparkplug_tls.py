"""``[sparkplug]`` over mqtts:// with a client certificate, a username and a password, against mosquitto.

mosquitto listens twice: TLS with client certificates and a password file (the gateway's), and
plain on loopback for the independent host application (which speaks plain MQTT). Certificates
are made here with ``openssl`` (a CA, a server certificate for 127.0.0.1, a client certificate).
"""

from __future__ import annotations

import asyncio
import shutil
import subprocess
import uuid
from pathlib import Path

import pytest
from mosquitto_support import HOST, RUN_AS, Broker, import_host, mosquitto_path

from gateway.app import Gateway
from gateway.config import parse_config
from tests.net import free_port

SparkplugHost = import_host()


def openssl(directory: Path, *arguments: str) -> None:
    subprocess.run(["openssl", *arguments], cwd=directory, check=True, capture_output=True, timeout=30)


def certificates(directory: Path) -> None:
    if shutil.which("openssl") is None:
        pytest.skip("OPENSSL NOT INSTALLED: needed to make the test certificates")
    key = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes"]
    openssl(directory, "req", "-x509", *key, "-keyout", "ca.key", "-out", "ca.pem", "-days", "2", "-subj", "/CN=ca")
    (directory / "server.ext").write_text("subjectAltName=IP:127.0.0.1\nextendedKeyUsage=serverAuth\n")
    (directory / "client.ext").write_text("extendedKeyUsage=clientAuth\n")
    for name in ("server", "client"):
        openssl(directory, "req", *key, "-keyout", f"{name}.key", "-out", f"{name}.csr", "-subj", f"/CN={name}")
        openssl(directory, "x509", "-req", "-in", f"{name}.csr", "-CA", "ca.pem", "-CAkey", "ca.key",
                "-CAcreateserial", "-days", "2", "-out", f"{name}.pem", "-extfile", f"{name}.ext")


@pytest.fixture
def tls_broker(tmp_path: Path) -> Broker:
    mosquitto_path()
    passwd = shutil.which("mosquitto_passwd")
    if passwd is None:
        pytest.skip("MOSQUITTO_PASSWD NOT INSTALLED (Debian package mosquitto): needed for the password file")
    certificates(tmp_path)
    subprocess.run([passwd, "-b", "-c", str(tmp_path / "passwd"), "gw1", "s3cret"], check=True, timeout=30)
    broker = Broker(tmp_path)
    tls_port = free_port()
    broker.config.write_text(
        f"{RUN_AS}per_listener_settings true\npersistence false\n"
        f"log_dest file {broker.log}\n"
        f"listener {broker.port} {HOST}\nallow_anonymous true\n"
        f"listener {tls_port} {HOST}\nallow_anonymous false\npassword_file {tmp_path / 'passwd'}\n"
        f"cafile {tmp_path / 'ca.pem'}\ncertfile {tmp_path / 'server.pem'}\nkeyfile {tmp_path / 'server.key'}\n"
        "require_certificate true\n",
        encoding="utf-8",
    )
    broker.tls_port = tls_port  # type: ignore[attr-defined]
    return broker


def gateway_config(directory: Path, port: int, password: str) -> str:
    return (
        f'[modbus]\nlisten = "127.0.0.1:0"\n\n[sparkplug]\nbroker = "mqtts://{HOST}:{port}"\n'
        f'group_id = "plant1"\nedge_node_id = "tls"\nusername = "gw1"\npassword = "{password}"\n'
        f'ca = "{directory / "ca.pem"}"\ncert = "{directory / "client.pem"}"\nkey = "{directory / "client.key"}"\n'
        f'state_file = "{directory / "bdseq.json"}"\nreconnect_min = 0.2\nreconnect_max = 0.5\n\n'
        f'[[link]]\nname = "press"\nprotocol = "slc-ascii"\nport = "sim://slc150?instance={uuid.uuid4().hex}"\n'
        "unit = 1\n"
    )


async def test_mqtts_with_certificate_and_password(tls_broker: Broker, tmp_path: Path) -> None:
    tls_broker.start()
    try:
        async with SparkplugHost(HOST, tls_broker.port) as host:
            port = tls_broker.tls_port  # type: ignore[attr-defined]
            async with Gateway(parse_config(gateway_config(tmp_path, port, "s3cret"))) as gw:
                nbirth = await host.wait_for(lambda m: m.message_type == "NBIRTH" and m.edge_node_id == "tls", 15)
                await host.wait_for(lambda m: m.message_type == "DBIRTH" and m.device_id == "press", 10,
                                    since=nbirth.index)
                assert gw.sparkplug is not None and gw.sparkplug.session_state == "online"
            # a wrong password: no session, and nothing published
            count = len(host.messages)
            async with Gateway(parse_config(gateway_config(tmp_path, port, "wrong"))) as gw:
                await asyncio.sleep(1.5)
                assert gw.sparkplug is not None and gw.sparkplug.session_state == "disconnected"
                assert gw.sparkplug.sessions == 0
            assert not [m for m in host.messages[count:] if m.edge_node_id == "tls"]
            assert host.violations == [], "\n".join(host.violations)
    finally:
        tls_broker.stop()
