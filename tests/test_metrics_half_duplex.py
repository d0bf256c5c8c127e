"""Per-station metrics of a DF1 half-duplex line, scraped from /metrics of a running gateway (issue #12).

Three SLC stations on one line behind a TCP device server (the multi-drop simulator), station 3
absent: its polls go unanswered, it is demoted; stations 1 and 2 answer.  The numbers come from
each unit's driver (its ``metrics()`` hook) as ``slc_gateway_link_<key>`` families.
"""

from __future__ import annotations

import asyncio
import logging
import math
from typing import Any

import pytest

from gateway.app import Gateway
from gateway.config import parse_config
from gateway.kinds.df1.sim.df1_multidrop import LineOptions, MultidropLine
from gateway.metrics import _driver_families
from gateway.protocols.df1.framing import Checksum
from gateway.sim.serve import close_tcp, serve_tcp
from tests.test_metrics import HOST, get, samples, value


def station(name: str, unit: int, port: str, number: int) -> str:
    return f"""
[[link]]
name = "{name}"
protocol = "df1"
port = "{port}"
unit = {unit}
duplex = "half"
station = {number}
checksum = "bcc"
timeout = 0.5
poll_timeout = 0.05
ack_timeout = 0.05
poll_interval = 0.05
slow_poll_interval = 5.0
demote_after = 2
fast_interval = 0.05

[[link.map]]
table = "holding"
start = 0
address = "N7:0"
count = 4
"""


async def test_station_metrics_are_scraped_per_unit() -> None:
    sim = MultidropLine(LineOptions(checksum=Checksum.BCC, stations=(1, 2, 3), dead=frozenset({3})))
    server = await serve_tcp(sim, HOST, 0)
    port = f"socket://{HOST}:{server.sockets[0].getsockname()[1]}"
    text = ('[modbus]\nlisten = "127.0.0.1:0"\n\n[metrics]\nlisten = "127.0.0.1:0"\n'
            + station("s1", 1, port, 1) + station("s2", 2, port, 2) + station("s3", 3, port, 3))
    try:
        async with Gateway(parse_config(text)) as gateway:
            assert gateway.metrics is not None
            found: dict[str, Any] = {}
            async with asyncio.timeout(10):
                while True:
                    found = samples((await get(gateway.metrics.port, "/metrics")).body.decode())
                    if ("slc_gateway_link_demotions_total" in found
                            and value(found, "slc_gateway_link_demotions_total", link="s3", unit="3") >= 1
                            and value(found, "slc_gateway_link_data_age_seconds", link="s1", unit="1") < 5):
                        break
                    await asyncio.sleep(0.1)
    finally:
        await close_tcp(server)
    live = [{"link": "s1", "unit": "1"}, {"link": "s2", "unit": "2"}]
    dead = {"link": "s3", "unit": "3"}
    for labels in live:
        assert value(found, "slc_gateway_link_polls_total", **labels) > 0
        assert value(found, "slc_gateway_link_messages_sent_total", **labels) > 0
        assert value(found, "slc_gateway_link_messages_received_total", **labels) > 0
        assert value(found, "slc_gateway_link_demotions_total", **labels) == 0
        assert value(found, "slc_gateway_link_active", **labels) == 1
        assert 0 <= value(found, "slc_gateway_link_data_age_seconds", **labels) < 5
        assert value(found, "slc_gateway_link_slave_messages_total", **labels) == 0
    assert value(found, "slc_gateway_link_demotions_total", **dead) >= 1
    assert value(found, "slc_gateway_link_active", **dead) == 0
    assert value(found, "slc_gateway_link_messages_received_total", **dead) == 0
    assert math.isinf(value(found, "slc_gateway_link_data_age_seconds", **dead))  # never answered
    assert value(found, "slc_gateway_link_timeouts_total", **dead) > 0
    for name in ("eots", "retries", "read_retries", "bad_frames", "duplicates", "slave_writes", "slave_refused"):
        assert f"slc_gateway_link_{name}_total" in found, name
    # the static families are still there, one sample per link
    assert len(found["slc_gateway_link_up"]) == 3


class _Driver:
    def __init__(self, numbers: object) -> None:
        self.numbers = numbers

    def metrics(self) -> object:
        if isinstance(self.numbers, Exception):
            raise self.numbers
        return self.numbers


class _Unit:
    def __init__(self, name: str, numbers: object) -> None:
        self.name = name
        self.unit_id = 7
        self.driver = _Driver(numbers)


def test_driver_hook_names_kinds_and_bad_keys(caplog: pytest.LogCaptureFixture) -> None:
    units: list[Any] = [
        _Unit("a", {"polls": 3, "active": 1, "data_age": -1.0, "Bad-Key": 1, "text": "x", "up": 1}),
        _Unit("b", RuntimeError("boom")),
        _Unit("c", {"polls": 5}),
    ]
    with caplog.at_level(logging.WARNING, logger="gateway.metrics"):
        families = {f.name: f for f in _driver_families(units, {"slc_gateway_link_up"})}
        _driver_families(units, {"slc_gateway_link_up"})  # warned once per link and key
    assert set(families) == {"slc_gateway_link_polls", "slc_gateway_link_active", "slc_gateway_link_data_age_seconds"}
    assert families["slc_gateway_link_polls"].type == "counter"
    assert families["slc_gateway_link_active"].type == "gauge"
    assert [(s.labels["link"], s.value) for s in families["slc_gateway_link_polls"].samples] == [("a", 3), ("c", 5)]
    assert math.isinf(families["slc_gateway_link_data_age_seconds"].samples[0].value)
    messages = [r.getMessage() for r in caplog.records]
    assert len(messages) == 4, messages  # Bad-Key, text, up (shadows link_up), b's failure
    assert any("boom" in m for m in messages) and any("shadow" in m for m in messages)
