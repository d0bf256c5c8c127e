"""The edge node's MQTT loop (``gateway.sparkplug.driver``), on a broker stand-in: what a session queued and
could not send is not sent in the next session.

Sparkplug 3.0 §5.4/§5.7: a new session begins with its NBIRTH (the next bdSeq) and the births of its
devices; a DDATA of the session before it, published in the new one ahead of the NBIRTH, carries a
``seq`` of a session the host has already closed.  The gateway here is real (a simulated SLC 5/04
polled over its link); only the MQTT client is replaced, by one whose first connection takes no
message (a broker that stopped reading) until it is lost.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import sqlite3
import uuid
from functools import partial
from pathlib import Path
from typing import Any

import aiomqtt
import pytest

import gateway.sparkplug.driver as driver_module
from gateway.app import Gateway
from gateway.config import parse_config
from gateway.sim import get_simulator, reset_simulators
from gateway.sparkplug.driver import SparkplugNode
from gateway.sparkplug.node import Publish
from gateway.sparkplug.store import store_path
from tests.waiting import until


def verb(message: Publish) -> str:
    return message.topic.split("/")[2]


class Broker:
    """The MQTT connections the node made; the first takes no message until it is lost."""

    def __init__(self) -> None:
        self.sessions: list[Session] = []
        #: what the node queued, with the number of the session it was queued in (1, 2 ...)
        self.queued: list[tuple[int, Publish]] = []


class Session:
    """A stand-in for ``_MqttClient``: one connection to :class:`Broker`."""

    def __init__(self, broker: Broker) -> None:
        self.number = len(broker.sessions) + 1
        broker.sessions.append(self)
        self.published: list[Publish] = []
        self.lost = asyncio.Event()

    async def __aenter__(self) -> Session:
        return self

    async def __aexit__(self, *exc: object) -> None:
        return None

    async def subscribe(self, topic: str, qos: int) -> None:
        return None

    async def publish_in_order(self, messages: list[Publish]) -> None:
        if self.number == 1:  # the broker stopped reading: nothing is written
            await asyncio.Event().wait()
        self.published.extend(messages)

    async def publish(self, topic: str, payload: bytes, qos: int = 0, retain: bool = False) -> None:
        self.published.append(Publish(topic, payload, qos, retain))

    @property
    def messages(self) -> Any:
        async def incoming() -> Any:
            await self.lost.wait()
            raise aiomqtt.MqttError("the connection was lost")
            yield  # an async generator

        return incoming()


@pytest.fixture
def broker(monkeypatch: pytest.MonkeyPatch) -> Broker:
    broker = Broker()
    monkeypatch.setattr(driver_module, "MqttClient", lambda *args, **kwargs: Session(broker))
    send = SparkplugNode._send

    def recording(node: SparkplugNode, messages: list[Publish]) -> None:
        broker.queued.extend((len(broker.sessions), message) for message in messages)
        send(node, messages)

    monkeypatch.setattr(SparkplugNode, "_send", recording)
    return broker


def press_config(url: str, tmp_path: Path, *, check_interval: float, timeout: float) -> Any:
    """A gateway polling one SLC 5/04 (``url``, N7:0-1) with ``[sparkplug]`` to a broker the test stands in for."""
    return parse_config(f"""
[modbus]
listen = "127.0.0.1:0"

[sparkplug]
broker = "mqtt://127.0.0.1:1"
group_id = "plant"
edge_node_id = "gw"
state_file = "{tmp_path / 'bdseq.json'}"
check_interval = {check_interval}
reconnect_min = 0.05
reconnect_max = 0.1

[[link]]
name = "press"
protocol = "df1"
port = "{url}"
unit = 1
timeout = {timeout}
[[link.map]]
table = "holding"
start = 0
address = "N7:0"
count = 2
""")


async def test_what_a_lost_session_queued_is_not_published_in_the_next_one(broker: Broker, tmp_path: Path) -> None:
    url = f"sim://slc504?ladder=0&instance={uuid.uuid4().hex}"
    config = press_config(url, tmp_path, check_interval=0.05, timeout=0.05)
    sim = get_simulator(url)
    try:
        async with asyncio.timeout(20), Gateway(config):
            await until(lambda: any(n == 1 and verb(m) == "DBIRTH" for n, m in broker.queued), 10,
                        what="the press born in the first session")
            sim.set_word("N7", 0, 1234)
            await until(lambda: any(n == 1 and verb(m) == "DDATA" for n, m in broker.queued), 10,
                        what="a DDATA queued in the first session")
            assert broker.sessions[0].published == []  # the broker took none of it
            # The sender took what was queued so far as one batch and is stuck writing it: a change now
            # stays in the outbox (the old session's message the next session must not send).
            sim.set_word("N7", 0, 5678)
            await until(lambda: sum(n == 1 and verb(m) == "DDATA" for n, m in broker.queued) >= 2, 10,
                        what="a second DDATA queued in the first session, behind the stuck batch")
            broker.sessions[0].lost.set()
            await until(lambda: len(broker.sessions) >= 2 and any(
                verb(m) == "DDATA" for m in broker.sessions[1].published), 10, what="the second session's data")
            second = broker.sessions[1].published
            assert verb(second[0]) == "NBIRTH"
            first_session = [m for n, m in broker.queued if n == 1]
            assert not [m for m in second if any(m is old for old in first_session)]
            assert [verb(m) for m in second[:2]] == ["NBIRTH", "DBIRTH"]
    finally:
        reset_simulators()


class RefusingBroker:
    """A stand-in for ``_MqttClient`` whose broker is away: every connection is refused."""

    def __init__(self, *args: object, **kwargs: object) -> None:
        return None

    async def __aenter__(self) -> RefusingBroker:
        raise aiomqtt.MqttError("[Errno 111] Connection refused")

    async def __aexit__(self, *exc: object) -> None:
        return None


def stored_values(path: Path, metric: str) -> list[int]:
    """The values of ``metric`` committed to the store file, oldest first (a reader beside the node's writer: WAL)."""
    if not path.exists():
        return []
    with contextlib.closing(sqlite3.connect(path)) as db:
        try:
            rows = db.execute("SELECT sample FROM change WHERE metric = ? ORDER BY id", (metric,)).fetchall()
        except sqlite3.OperationalError:  # the node has not created its table yet
            return []
    return [json.loads(sample)[0] for (sample,) in rows]


def kept(path: Path, metric: str, value: int) -> bool:
    return value in stored_values(path, metric)


async def test_a_change_is_kept_as_soon_as_its_link_answers_not_at_the_next_check(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """Issue 43: a gateway started while the broker is away stores every change from the first answer of a
    link on.  The node judged a link up only at its periodic check (``check_interval``), and until then kept
    no change of it: each value the controller had before that check but the last was lost (a restart in
    the middle of an outage lost the first writes made after it)."""
    monkeypatch.setattr(driver_module, "MqttClient", RefusingBroker)
    # every answer 0.3 s late: the node's first check (at its start) comes before the link's first answer,
    # and with check_interval = 60 there is no other in this test
    url = f"sim://slc504?ladder=0&delay=0.3&instance={uuid.uuid4().hex}"
    config = press_config(url, tmp_path, check_interval=60, timeout=2)
    store = store_path(tmp_path / "bdseq.json")
    sim = get_simulator(url)
    try:
        async with asyncio.timeout(30), Gateway(config):
            for value in (11, 12, 13):
                sim.set_word("N7", 0, value)
                await until(partial(kept, store, "N7:0", value), 8, what=f"N7:0 = {value} kept in the store")
        assert stored_values(store, "N7:0")[-3:] == [11, 12, 13]
    finally:
        reset_simulators()
