"""``python -m gateway.healthcheck`` (the image's HEALTHCHECK) against a running gateway on 127.0.0.1."""

from __future__ import annotations

import asyncio
import socket
import subprocess
import sys
from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from gateway.app import Gateway
from gateway.config import parse_config
from gateway.healthcheck import POLICY_LINK, POLICY_SERVING, check
from gateway.healthcheck import run_healthcheck as main

ROOT = Path(__file__).resolve().parents[2]
HOST = "127.0.0.1"

CONFIG = """
[modbus]
listen = "127.0.0.1:0"

[[link]]
name = "answers"
protocol = "slc-ascii"
port = "sim://slc150?ladder=0&instance=healthcheck-up"
unit = 1

[[link]]
name = "silent"
protocol = "slc-ascii"
port = "sim://slc150?drop=1&instance=healthcheck-silent"
unit = 2
timeout = 0.05
retries = 0
"""


pytestmark = pytest.mark.usefixtures("forget_simulators")


@pytest.fixture
async def gateway() -> AsyncIterator[Gateway]:
    async with Gateway(parse_config(CONFIG)) as gw:
        # Wait until unit 1 answered and unit 2 timed out (the status block shows both).
        async with asyncio.timeout(5):
            while True:
                up = await asyncio.to_thread(check, HOST, gw.port, 1)
                down = await asyncio.to_thread(check, HOST, gw.port, 2)
                if (up, down) == (1, 0):
                    break
                await asyncio.sleep(0.02)
        yield gw


def closed_port() -> int:
    with socket.socket() as sock:
        sock.bind((HOST, 0))
        port: int = sock.getsockname()[1]
    return port


async def run_main(*argv: str) -> int:
    return await asyncio.to_thread(main, list(argv))


async def test_healthy_when_the_status_block_answers(gateway: Gateway, capsys: pytest.CaptureFixture[str]) -> None:
    assert await run_main(f"{HOST}:{gateway.port}") == 0
    assert capsys.readouterr().out == f"healthy: {HOST}:{gateway.port} unit 1: link up; {POLICY_SERVING}\n"
    assert await run_main(f"{HOST}:{gateway.port}", "1", "--require-link") == 0
    assert capsys.readouterr().out == f"healthy: {HOST}:{gateway.port} unit 1: link up; {POLICY_LINK}\n"


async def test_a_silent_controller_is_healthy_unless_the_link_is_required(
    gateway: Gateway, capsys: pytest.CaptureFixture[str]
) -> None:
    """Each policy says which it applied: the default one passes with the link down, --require-link fails."""
    assert await run_main(f"{HOST}:{gateway.port}", "2") == 0
    out = capsys.readouterr().out
    assert "link down" in out and "policy serving" in out and "--require-link" in out
    assert await run_main(f"{HOST}:{gateway.port}", "2", "--require-link") == 1
    err = capsys.readouterr().err
    assert "link down" in err and POLICY_LINK in err


async def test_unhealthy_on_exception_reply_or_no_server(gateway: Gateway, capsys: pytest.CaptureFixture[str]) -> None:
    assert await run_main(f"{HOST}:{gateway.port}", "9") == 1  # unknown unit: exception 0x0A
    assert "exception 0x0A" in capsys.readouterr().err
    assert await run_main(f"{HOST}:{closed_port()}", "1", "--timeout", "1") == 1
    err = capsys.readouterr().err
    assert err.startswith("unhealthy:") and POLICY_SERVING in err


async def test_unhealthy_when_the_server_never_answers(capsys: pytest.CaptureFixture[str]) -> None:
    """A listener that accepts but never replies (a hung process): fails after --timeout."""

    async def hang(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        await reader.read()  # never answer; until the client gives up
        writer.close()

    server = await asyncio.start_server(hang, HOST, 0)
    port = server.sockets[0].getsockname()[1]
    async with server:
        assert await run_main(f"{HOST}:{port}", "1", "--timeout", "0.3") == 1
    assert "timed out" in capsys.readouterr().err


def test_arguments_are_checked() -> None:
    with pytest.raises(SystemExit) as exc:
        main(["localhost"])  # no port
    assert exc.value.code == 2
    with pytest.raises(SystemExit):
        main([f"{HOST}:5020", "300"])  # unit out of range


async def test_runs_as_a_module(gateway: Gateway) -> None:
    process = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "gateway.healthcheck", f"{HOST}:{gateway.port}", "1",
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
    )
    async with asyncio.timeout(30):
        stdout, stderr = await process.communicate()
    assert process.returncode == 0, stderr
    assert stdout.decode().startswith("healthy:")
