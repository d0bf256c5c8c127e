"""[opcua] in the config (validation, check-config's warning, the password hash command) and the server on
/api/status and /metrics."""

from __future__ import annotations

import subprocess
import sys
import urllib.request
from pathlib import Path

import pytest

from gateway.app import Gateway
from gateway.config import parse_config
from gateway.errors import ConfigError
from gateway.opcua.passwords import verify_password
from gateway.sim import reset_simulators
from tests.net import free_port
from tests.opcua.plant import Line, link_text, opcua_text

LINK = ('[[link]]\nname = "press"\nprotocol = "df1"\nport = "sim://slc504"\nunit = 1\n'
        '[[link.map]]\ntable = "holding"\nstart = 0\naddress = "N7:0"\ncount = 4\n')
WRITER = '[[opcua.user]]\nname = "op"\nrole = "write"\npassword_hash = "scrypt$16384$8$1$00$00"\n'


def test_check_config_warns_of_the_none_endpoint_with_writers_off_loopback() -> None:
    open_to_all = parse_config('[opcua]\nlisten = "opc.tcp://0.0.0.0:4840"\n' + WRITER + LINK)
    assert any("[opcua] offers the None endpoint" in w for w in open_to_all.warnings())
    loopback = parse_config('[opcua]\nlisten = "opc.tcp://127.0.0.1:4840"\n' + WRITER + LINK)
    assert not any("[opcua]" in w for w in loopback.warnings())
    encrypted = parse_config('[opcua]\nlisten = "opc.tcp://0.0.0.0:4840"\n'
                             'security = ["Basic256Sha256-SignAndEncrypt"]\n' + WRITER + LINK)
    assert not any("[opcua]" in w for w in encrypted.warnings())
    readers = parse_config('[opcua]\nlisten = "opc.tcp://0.0.0.0:4840"\n' + LINK)
    assert not any("[opcua]" in w for w in readers.warnings())
    described = open_to_all.describe()
    assert "[opcua]" in described and "[[opcua.user]]" in described and 'password_hash = "***"' in described


@pytest.mark.parametrize(("section", "why"), [
    ('listen = "tcp://0.0.0.0:4840"', "opc.tcp://host:port"),
    ('security = ["Aes256"]', "security"),
    ('anonymous = "write"', "anonymous"),
    ('[[opcua.user]]\nname = "op"\npassword_hash = "hunter2"', "hash-password"),
    (WRITER + WRITER, "given twice"),
])
def test_bad_sections_are_refused(section: str, why: str) -> None:
    with pytest.raises(ConfigError, match=why):
        parse_config("[opcua]\n" + section + "\n" + LINK)


def test_hash_password_reads_standard_input_and_never_prints_the_password() -> None:
    done = subprocess.run([sys.executable, "-m", "gateway", "hash-password"], input="correct horse\n",
                          capture_output=True, text=True, check=True, timeout=60)
    stored = done.stdout.strip()
    assert stored.startswith("scrypt$") and "correct horse" not in done.stdout
    assert verify_password("correct horse", stored) and not verify_password("correct horse!", stored)
    parse_config('[opcua]\n[[opcua.user]]\nname = "op"\npassword_hash = "' + stored + '"\n' + LINK)
    empty = subprocess.run([sys.executable, "-m", "gateway", "hash-password"], input="", capture_output=True,
                           text=True, timeout=60)
    assert empty.returncode == 1


async def test_status_and_metrics_show_the_server(tmp_path: Path) -> None:
    press = await Line.start(seed=3)
    port = free_port()
    text = opcua_text(port, tmp_path, security=["None"]).replace(
        "[opcua]", '[metrics]\nlisten = "127.0.0.1:0"\n\n[opcua]', 1) + link_text("press", 1, press)
    try:
        async with Gateway(parse_config(text)) as gw:
            from asyncua import Client

            async with Client(f"opc.tcp://127.0.0.1:{port}") as client:
                await client.create_subscription(100, None)
                assert gw.metrics is not None
                base = f"http://127.0.0.1:{gw.metrics.port}"
                status = await _get(base + "/api/status")
                metrics = await _get(base + "/metrics")
    finally:
        await press.off()
        reset_simulators()
    import json

    opcua = json.loads(status)["opcua"]
    assert opcua["sessions"] == 1 and opcua["subscriptions"] == 1 and opcua["rejected_logins"] == 0
    assert opcua["listen"] == f"opc.tcp://127.0.0.1:{port}"
    assert "slc_gateway_opcua_sessions 1.0" in metrics
    assert "slc_gateway_opcua_subscriptions 1.0" in metrics
    for family in ("monitored_items", "data_changes_total", "rejected_logins_total", "writes_total"):
        assert f"slc_gateway_opcua_{family}" in metrics


async def _get(url: str) -> str:
    import asyncio

    def fetch() -> str:
        with urllib.request.urlopen(url, timeout=10) as response:
            body: bytes = response.read()
            return body.decode()

    return await asyncio.to_thread(fetch)


async def test_sigterm_closes_the_sessions_and_the_process_exits(tmp_path: Path) -> None:
    """``slc-gateway run`` with [opcua] and a client in session: SIGTERM ends the process with status 0 within a
    few seconds, the client's connection closed by the server, the endpoint gone."""
    import asyncio
    import os
    import signal

    from asyncua import Client

    press = await Line.start(seed=4)
    port = free_port()
    config = tmp_path / "gateway.toml"
    config.write_text(opcua_text(port, tmp_path, security=["None"]) + link_text("press", 1, press), encoding="utf-8")
    log_file = tmp_path / "gateway.log"
    with log_file.open("wb") as out:  # a file: a pipe nobody reads would fill and block the gateway's log
        process = await asyncio.create_subprocess_exec(sys.executable, "-m", "gateway", "run", str(config),
                                                       stdout=asyncio.subprocess.DEVNULL, stderr=out)
    try:
        client = Client(f"opc.tcp://127.0.0.1:{port}", timeout=5)
        for _ in range(200):  # the address space is built after the Modbus listener
            try:
                await client.connect()
                break
            except (TimeoutError, OSError):
                await asyncio.sleep(0.1)
        else:
            pytest.fail("the OPC UA endpoint did not come up")
        subscription = await client.create_subscription(100, None)
        assert subscription.subscription_id
        os.kill(process.pid, signal.SIGTERM)
        status = await asyncio.wait_for(process.wait(), 15)
        assert status == 0
        with pytest.raises((ConnectionError, OSError, asyncio.TimeoutError)):
            await Client(f"opc.tcp://127.0.0.1:{port}", timeout=2).connect()
        assert "opcua: server stopped" in log_file.read_text(encoding="utf-8")
        with pytest.raises(Exception):  # noqa: B017 (the server closed this session's connection)
            await client.get_namespace_array()
    finally:
        if process.returncode is None:
            process.kill()
            await process.wait()
        await press.off()
        reset_simulators()
