"""The OPC UA server checked by an independent client: node-opcua's (npm ``node-opcua-client``, pinned with
its lockfile in ``tests/e2e/opcua_client/``), through the None endpoint and Basic256Sha256 SignAndEncrypt
with a user: browsing, reading, subscribing and writing.

The client is installed by ``npm ci`` into that folder (CI: ``.ci/run``).  Without node, npm or the
installed client the test skips LOUDLY, unless ``SLC_GATEWAY_REQUIRE_NODE_OPCUA=1`` (CI) makes that a
failure.  The controllers are the DF1 SLC 5/04 simulator over TCP: expected values are the simulator's
memory (N7:n = n with the ladder frozen), not the gateway's code.
"""

from __future__ import annotations

import asyncio
import json
import os
import shutil
from collections import Counter
from pathlib import Path
from typing import Any

import pytest
from cryptography import x509
from cryptography.hazmat.primitives import serialization

from gateway.app import Gateway
from gateway.config import parse_config
from gateway.modbus.mapping import Table
from gateway.opcua.certs import ensure_certificate
from gateway.unit import Source
from tests.net import free_port
from tests.opcua.plant import Line, link_text, opcua_text

CLIENT_DIR = Path(__file__).parent / "opcua_client"


pytestmark = pytest.mark.usefixtures("forget_simulators")


def node_client() -> str:
    """The node binary, once node-opcua-client is installed (else skip loudly, or fail in CI)."""
    node = shutil.which("node")
    installed = (CLIENT_DIR / "node_modules" / "node-opcua-client" / "package.json").is_file()
    if node is None or not installed:
        missing = "node (Debian nodejs)" if node is None else f"node-opcua-client (cd {CLIENT_DIR} && npm ci)"
        if os.environ.get("SLC_GATEWAY_REQUIRE_NODE_OPCUA") == "1":
            pytest.fail(f"{missing} is not installed and SLC_GATEWAY_REQUIRE_NODE_OPCUA=1")
        pytest.skip(f"NODE-OPCUA CLIENT NOT INSTALLED: {missing}; the OPC UA end-to-end test needs it; set "
                    "SLC_GATEWAY_REQUIRE_NODE_OPCUA=1 to fail instead")
    return node


async def run_client(node: str, **options: Any) -> dict[str, Any]:
    process = await asyncio.create_subprocess_exec(
        node, str(CLIENT_DIR / "client.js"), json.dumps(options), cwd=CLIENT_DIR,
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
    out, err = await asyncio.wait_for(process.communicate(), 120)
    lines = [line for line in out.decode().splitlines() if line.startswith("{")]
    assert lines, f"node-opcua client printed nothing: {err.decode()[-2000:]}"
    result: dict[str, Any] = json.loads(lines[-1])
    return result


def pem_certificate(directory: Path, uri: str) -> tuple[Path, Path]:
    """A client certificate for node-opcua (PEM) and its key."""
    der, key = directory / "cert.der", directory / "key.pem"
    ensure_certificate(der, key, uri)
    pem = directory / "cert.pem"
    pem.write_bytes(x509.load_der_x509_certificate(der.read_bytes()).public_bytes(serialization.Encoding.PEM))
    return pem, key


async def test_node_opcua_browses_reads_subscribes_and_writes(tmp_path: Path) -> None:
    node = node_client()
    press, oven = await Line.start(seed=1), await Line.start(seed=2)
    port = free_port()
    endpoint = f"opc.tcp://127.0.0.1:{port}"
    client_pem, client_key = pem_certificate(tmp_path / "client", "urn:slc-gateway-e2e:node-opcua")
    stranger_pem, stranger_key = pem_certificate(tmp_path / "stranger", "urn:slc-gateway-e2e:stranger")
    (tmp_path / "trusted").mkdir()
    shutil.copy(tmp_path / "client" / "cert.der", tmp_path / "trusted" / "node-opcua.der")
    text = opcua_text(port, tmp_path) + link_text("press", 1, press) + link_text("oven", 2, oven, read_only=True)
    common = {"endpoint": endpoint, "pki": str(tmp_path / "pki")}
    secure = {**common, "security": "SignAndEncrypt", "certificate": str(client_pem),
              "privateKey": str(client_key), "applicationUri": "urn:slc-gateway-e2e:node-opcua"}
    tags = [f"press.N7:{n}" for n in range(8)] + ["press.F8:0", "press.B3:0/0", "press.N7:50",
                                                    "press.status.link_up", "oven.N7:1"]
    try:
        async with Gateway(parse_config(text)) as gw:
            unit = gw.units[0]
            for _ in range(100):  # every tag read once
                if all(not unit.cache.stamps[b] == float("-inf") for b in range(len(unit.plan.blocks))):
                    break
                await asyncio.sleep(0.1)
            # None, anonymous: browse, read, subscribe; a write is refused (anonymous reads only)
            plain = await run_client(node, **common, security="None", steps=[
                {"op": "browse", "node": "Objects"},
                {"op": "browse", "node": "press"},
                {"op": "read", "nodes": tags},
                {"op": "access", "nodes": ["press.N7:1", "press.N7:50", "oven.N7:1"]},
                {"op": "write", "node": "press.N7:1", "type": "Int16", "value": 11},
            ])
            assert "error" not in plain, plain
            objects, press_folder, values, access, refused = plain["steps"]
            assert {"press", "oven"} <= set(objects)
            assert {"N7:0", "F8:0", "B3:0/0", "N7:50", "_Status"} <= set(press_folder)
            for n in range(8):  # equal to the controller's memory and to Modbus at the same moment
                shown = values[f"press.N7:{n}"]
                assert shown["status"] == "Good" and shown["dataType"] == "Int16"
                registers = unit.read_register_bytes(Table.HOLDING, n, 1, Source.PEEK)
                assert shown["value"] == int.from_bytes(registers, "big", signed=True) == press.sim.word("N7", n)
            assert values["press.F8:0"]["dataType"] == "Float"
            assert values["press.B3:0/0"]["dataType"] == "Boolean"
            assert values["press.status.link_up"]["value"] == 1
            assert values["press.N7:0"]["sourceTimestamp"] <= values["press.N7:0"]["serverTimestamp"]
            assert access == {"press.N7:1": 3, "press.N7:50": 1, "oven.N7:1": 1}  # CurrentRead (| CurrentWrite)
            assert refused == "BadNotWritable"
            # SignAndEncrypt with a user who writes: subscribe to N7:6 while writing it
            writer = asyncio.create_task(run_client(node, **secure, user="operator", password="op-secret", steps=[
                {"op": "subscribe", "node": "press.N7:6", "seconds": 3, "publishing": 100},
            ]))
            await asyncio.sleep(1.5)
            written = await run_client(node, **secure, user="operator", password="op-secret", steps=[
                {"op": "write", "node": "press.N7:6", "type": "Int16", "value": -1234},
                {"op": "write", "node": "press.F8:1", "type": "Float", "value": 2.5},
                {"op": "write", "node": "press.N7:7", "type": "Int32", "value": 40000},
                {"op": "write", "node": "press.N7:50", "type": "Int16", "value": 1},
                {"op": "read", "nodes": ["press.N7:6"]},
            ])
            assert "error" not in written, written
            assert written["steps"][:4] == ["Good", "Good", "BadOutOfRange", "BadNotWritable"]
            assert written["steps"][4]["press.N7:6"]["value"] == -1234
            changes = (await writer)["steps"][0]
            assert [c["value"] for c in changes][:1] == [6] and changes[-1]["value"] == -1234
            assert all(c["status"] == "Good" for c in changes)
            # a certificate nobody trusted: refused, and written for an operator to trust
            stranger = await run_client(node, **{**secure, "certificate": str(stranger_pem),
                                                 "privateKey": str(stranger_key),
                                                 "applicationUri": "urn:slc-gateway-e2e:stranger"},
                                        user="operator", password="op-secret", steps=[])
            assert "BadSecurityChecksFailed" in stranger.get("error", ""), stranger
            assert len(list((tmp_path / "rejected").iterdir())) == 1
            # the link stopped: Bad_NoCommunication, through a subscription
            stopped = asyncio.create_task(run_client(node, **common, security="None", steps=[
                {"op": "subscribe", "node": "press.N7:2", "seconds": 7, "publishing": 100},
            ]))
            for _ in range(200):  # the client (a node process) has subscribed
                if gw.opcua is not None and gw.opcua.counts()["monitored_items"] >= 1:
                    break
                await asyncio.sleep(0.05)
            await asyncio.sleep(0.5)
            await press.off()
            await asyncio.sleep(3.0)
            await press.on()
            seen = [c["status"] for c in (await stopped)["steps"][0]]
            assert seen[0] == "Good" and "BadNoCommunication" in seen and seen[-1] == "Good", seen
    finally:
        await press.off()
        await oven.off()
    applied = Counter(entry[1] for entry in press.sim.applied_writes)
    assert applied == {"N7:6": 1, "F8:1": 1}
    assert press.sim.word("N7", 6) == (-1234) & 0xFFFF and press.sim.float_value("F8", 1) == 2.5
