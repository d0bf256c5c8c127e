"""bdSeq counts MQTT CONNECT packets, not connection attempts (issue 43, item 6a).

Sparkplug 3.0 §5.4 / §6.4.25 (tck-id-topics-nbirth-bdseq-increment): the bdSeq goes up by one with each
MQTT CONNECT the edge node sends.  A TCP connect the broker refuses sends no CONNECT, so it takes no bdSeq:
after any number of refused attempts, the first session's NBIRTH has bdSeq 0, the next one (after another run
of refused attempts) 1, and the will (the NDEATH the broker publishes when the connection breaks) carries the
same bdSeq as that session's NBIRTH.  Checked by the independent host application (tests/peers).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import socket
from pathlib import Path

from mosquitto_support import HOST, Broker, import_host

from gateway.config.sparkplug import SparkplugConfig
from gateway.sparkplug.driver import SparkplugNode

SparkplugHost = import_host()


def nbirths(host: object) -> list[int]:
    return [m.metric("bdSeq").value for m in host.messages if m.message_type == "NBIRTH"]  # type: ignore[attr-defined]


async def test_refused_attempts_take_no_bdseq_and_the_will_carries_the_nbirths(
        tmp_path: Path) -> None:
    broker = Broker(tmp_path)  # not started yet: its port refuses connections
    state_file = tmp_path / "bdseq.json"
    config = SparkplugConfig(broker=f"mqtt://{HOST}:{broker.port}", group_id="plant1", edge_node_id="gw1",
                             keepalive=5, state_file=state_file, reconnect_min=0.05, reconnect_max=0.05)
    node = SparkplugNode(config, [], [])
    attempts = 0
    target = 5
    enough = asyncio.Event()
    session = node._session

    async def counted() -> None:
        nonlocal attempts
        attempts += 1
        if attempts >= target:
            enough.set()
        await session()

    node._session = counted  # type: ignore[method-assign]
    task = asyncio.create_task(node.run())
    try:
        await asyncio.wait_for(enough.wait(), 30)
        assert attempts >= 5 and node.core.bd_seq is None and not state_file.exists()
        broker.start()
        async with SparkplugHost(HOST, broker.port) as host:
            await host.wait_for(lambda m: m.message_type == "NBIRTH", 20)
            assert nbirths(host) == [0]
            assert json.loads(state_file.read_text())["bdSeq"] == 0
            # the broker goes away; the node's attempts are refused again
            broker.stop()
        target, enough = attempts + 5, asyncio.Event()
        await asyncio.wait_for(enough.wait(), 30)
        broker.start()
        async with SparkplugHost(HOST, broker.port) as host:
            nbirth = await host.wait_for(lambda m: m.message_type == "NBIRTH", 20)
            assert nbirth.metric("bdSeq").value == 1
            # the connection breaks without a DISCONNECT: the broker publishes the will, the NBIRTH's bdSeq
            client = node._client
            assert client is not None
            sock = client._client.socket()
            assert isinstance(sock, socket.socket)
            sock.shutdown(socket.SHUT_RDWR)
            ndeath = await host.wait_for(lambda m: m.message_type == "NDEATH", 20)
            assert ndeath.metric("bdSeq").value == 1
            nbirth = await host.wait_for(lambda m: m.message_type == "NBIRTH" and m.metric("bdSeq").value != 1, 20)
            assert nbirth.metric("bdSeq").value == 2  # one new CONNECT: one more
            await asyncio.sleep(0)
            assert host.violations == [], "\n".join(host.violations)
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
        broker.stop()
