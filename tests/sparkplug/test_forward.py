"""Store and forward on the event loop (gateway.sparkplug.forward): the replay against a real store file.

A node replaced by a config reload closes its store while its session's replay may be between two store
calls (a DDATA handed to the MQTT client, its rows not yet removed).  The replay must end there: a store
call after the close raised "the store is not open" through the node's task group and stopped the gateway
(seen in a run of tests/e2e/test_sparkplug_reload.py under load).
"""

from __future__ import annotations

import asyncio
from pathlib import Path

from gateway.sparkplug.forward import Forwarder
from gateway.sparkplug.history import Change
from gateway.sparkplug.node import Device, EdgeNode, MetricSpec, Publish
from gateway.sparkplug.payload import SparkplugType
from gateway.sparkplug.store import ChangeStore

T0 = 1_700_000_000_000


def online_node() -> EdgeNode:
    node = EdgeNode("plant1", "gw1", [Device("press", [MetricSpec("N7:0", 2, SparkplugType.Int16)])], store=True)
    node.link(0, True, T0)
    node.connecting(T0)
    node.connected(T0)
    while node.next_birth(T0) is not None:
        pass
    return node


async def test_a_replay_between_two_store_calls_ends_quietly_when_the_store_is_closed(tmp_path: Path) -> None:
    store = ChangeStore(tmp_path / "s.sqlite", max_bytes=10**8, max_age=86_400_000)
    forward = Forwarder(online_node(), store, replay_rate=1000.0, now_ms=lambda: T0)
    await forward.open()
    store.add([Change("press", "N7:0", T0 - 1000, 5, 192)], T0)
    sent: list[Publish] = []
    handed = asyncio.Event()
    release = asyncio.Event()

    async def drained() -> None:
        if sent:  # the historical DDATA is with the MQTT client: the rows are removed next
            handed.set()
            await release.wait()

    replay = asyncio.create_task(forward.replay(sent.extend, drained))
    await asyncio.wait_for(handed.wait(), 5)
    await forward.close()  # the node is replaced: its store closes
    release.set()
    await asyncio.wait_for(replay, 5)  # ended, no "the store is not open"
    assert len(sent) == 1
