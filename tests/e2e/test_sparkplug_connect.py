"""The edge node's first MQTT CONNECT completes when the event loop is busy while it connects.

The TCP connect runs in a thread (aiomqtt), the CONNECT packet is written by the event loop.  A loop
busy for longer than the keepalive in between (a start-up with many links, a loaded machine) must not
lose that first CONNECT: the keepalive is the broker's silence after the CONNECT (MQTT 3.1.1
§3.1.2.10), not the time the client took to write it.  The session then starts with bdSeq 0, the
first attempt's (Sparkplug 3.0 §5.4), which the independent host application sees in the NBIRTH.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from pathlib import Path
from typing import Any

import aiomqtt
import pytest
from mosquitto_support import HOST, Broker, broker, import_host  # noqa: F401 (the fixture)

from gateway.config.sparkplug import SparkplugConfig
from gateway.sparkplug.driver import SparkplugNode

KEEPALIVE = 5  # the smallest the configuration allows
SparkplugHost = import_host()


def established_to(port: int) -> int:
    """TCP connections in state ESTABLISHED whose remote port is ``port`` (/proc/net/tcp, IPv4)."""
    count = 0
    for line in Path("/proc/net/tcp").read_text().splitlines()[1:]:
        fields = line.split()
        if int(fields[2].split(":")[1], 16) == port and fields[3] == "01":
            count += 1
    return count


def hold_the_loop(port: int, before: int, seconds: float) -> None:
    """Block the event loop (called from it) until a new connection to ``port`` is up, then ``seconds`` more:
    the connect goes on in its thread and reaches the broker; the CONNECT cannot be written meanwhile."""
    deadline = time.monotonic() + 10
    while established_to(port) == before:
        assert time.monotonic() < deadline, "the node's TCP connection to the broker did not come"
        time.sleep(0.01)
    time.sleep(seconds)


async def test_first_connect_survives_a_loop_busy_longer_than_the_keepalive(broker: Broker,  # noqa: F811
                                                                             tmp_path: Path,
                                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    config = SparkplugConfig(broker=f"mqtt://{HOST}:{broker.port}", group_id="plant1", edge_node_id="busy",
                             keepalive=KEEPALIVE, state_file=tmp_path / "bdseq.json", reconnect_min=0.2)
    loop = asyncio.get_running_loop()
    submit = loop.run_in_executor
    connecting = asyncio.Event()

    def spy(executor: Any, func: Any, *args: Any) -> Any:
        if isinstance(getattr(func, "__self__", None), aiomqtt.Client):  # the MQTT client's connect, in a thread
            connecting.set()
        return submit(executor, func, *args)

    async with SparkplugHost(HOST, broker.port) as host:
        before = established_to(broker.port)  # the host's own connection
        monkeypatch.setattr(loop, "run_in_executor", spy)
        node = SparkplugNode(config, [], [])
        task = asyncio.create_task(node.run())
        try:
            await connecting.wait()
            hold_the_loop(broker.port, before, KEEPALIVE + 1)
            nbirth = await host.wait_for(lambda m: m.message_type == "NBIRTH" and m.edge_node_id == "busy", 20)
        finally:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        # the first CONNECT attempt (bdSeq 0) is the session: no attempt was lost
        assert nbirth.metric("bdSeq").value == 0
        assert node.sessions == 1
        await asyncio.sleep(0)
        assert host.violations == [], "\n".join(host.violations)
