"""The gateway as a Sparkplug B edge node, checked by an independent host application on a real broker.

Debian's mosquitto runs on a free loopback port (``mosquitto_support``); the host application is
``tests/peers/sparkplug_host.py``, written from the Sparkplug 3.0 specification by another
engineer who did not read ``gateway/sparkplug``.  It records every rule a message breaks in
``violations`` (births before data, aliases as born, ``seq`` continuity, NDEATH ``bdSeq`` equal to
the NBIRTH's, qualities, QoS and retain flags ...): every test ends with that list empty.

The controllers are the DF1 SLC 5/04 simulator served over TCP (``serve_tcp``, as a serial device
server would), so that a test can take a line away (``close_tcp``) and give it back.  Expected
values come from the simulator's memory and its documented initial table (N7:n = n with the
ladder frozen), not from the gateway's code.
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
import time
import urllib.request
import uuid
from collections import Counter
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import pytest
from mosquitto_support import HOST, Broker, broker, import_host  # noqa: F401 (the fixture)

from gateway.app import Gateway
from gateway.config import parse_config
from tests.switched_line import Line

GROUP, NODE = "plant1", "gw1"
FAULTS = {"corrupt": 10, "drop": 15, "withhold_ack": 10, "duplicate": 10, "noise": 10}
SparkplugHost = import_host()


pytestmark = pytest.mark.usefixtures("forget_simulators")


def link_text(name: str, unit: int, line: Line, **keys: Any) -> str:
    settings = {"timeout": 0.05, "stale_after": 1.0, "down_after_failures": 3, "down_after_seconds": 1.0,
                "write_timeout": 3.0, **keys}
    text = f'[[link]]\nname = "{name}"\nprotocol = "df1"\nport = "{line.url}"\nunit = {unit}\n'
    text += "".join(f"{k} = {str(v).lower() if isinstance(v, bool) else v}\n" for k, v in settings.items())
    for table, start, address, count, kind in (
        ("holding", 0, "N7:0", 8, "int16"),
        ("holding", 100, "F8:0", 2, "float32"),
        ("coil", 0, "B3:0/0", 4, "bool"),
        ("input", 0, "N7:50", 2, "int16"),
        ("holding", 300, "N10:100", 2, "int16"),  # past the end of N10: the controller refuses it
    ):
        text += (f'[[link.map]]\ntable = "{table}"\nstart = {start}\naddress = "{address}"\ncount = {count}\n'
                 f'type = "{kind}"\n')
    return text


def config_text(broker_port: int, state_file: Path, links: str, **sparkplug: Any) -> str:
    options = {"check_interval": 0.1, "status_interval": 0.2, "reconnect_min": 0.2, "reconnect_max": 1.0,
               "keepalive": 5, **sparkplug}
    text = (f'[modbus]\nlisten = "127.0.0.1:0"\n\n[sparkplug]\nbroker = "mqtt://{HOST}:{broker_port}"\n'
            f'group_id = "{GROUP}"\nedge_node_id = "{NODE}"\nstate_file = "{state_file}"\n')
    text += "".join(f"{k} = {v!r}\n".replace("'", '"') for k, v in options.items())
    return text + "\n" + links


@dataclass
class Plant:
    broker: Broker
    host: Any
    press: Line
    oven: Line
    state_file: Path
    gateway: Gateway | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def config(self, **sparkplug: Any) -> Any:
        links = link_text("press", 1, self.press) + link_text("oven", 2, self.oven, read_only=True)
        return parse_config(config_text(self.broker.port, self.state_file, links, **sparkplug))

    async def wait(self, predicate: Callable[[Any], bool], seconds: float = 10.0, since: int = 0) -> Any:
        return await self.host.wait_for(predicate, seconds, since=since)


def kind(verb: str, device: str | None = None) -> Callable[[Any], bool]:
    return lambda m: m.message_type == verb and (device is None or m.device_id == device)


@pytest.fixture
async def plant(broker: Broker, tmp_path: Path) -> AsyncIterator[Plant]:  # noqa: F811
    press, oven = await Line.start(seed=1), await Line.start(seed=2)
    try:
        async with SparkplugHost(HOST, broker.port) as host:
            yield Plant(broker, host, press, oven, tmp_path / "bdseq.json")
            assert host.violations == [], "\n".join(host.violations)
    finally:
        await press.off()
        await oven.off()


class Absent(NamedTuple):
    value: Any = None
    is_null: Any = None
    quality: Any = None


def value(plant: Plant, device: str, metric: str) -> Any:
    """The host's latest (value, is_null, quality) of a metric; all None before its device's birth."""
    return host_value(plant.host, device, metric)


def host_value(host: Any, device: str, metric: str) -> Any:
    try:
        return host.value(GROUP, NODE, device, metric)
    except KeyError:
        return Absent()


async def test_births_data_rebirth_and_ndeath_pass_the_host(plant: Plant) -> None:
    async with Gateway(plant.config()) as gw:
        nbirth = await plant.wait(kind("NBIRTH"))
        assert nbirth.qos == 0 and not nbirth.retain
        await plant.wait(kind("DBIRTH", "press"))
        await plant.wait(kind("DBIRTH", "oven"))
        # the DF1 initial table (docs/develop/controller-variants.md): N7:n = n; past the end of N10: BAD (0)
        await plant.wait(lambda m: value(plant, "press", "N7:3").value == 3, 5)
        assert value(plant, "press", "N7:3") == (3, False, None)
        await plant.wait(lambda m: value(plant, "press", "N10:100").quality == 0, 5)
        assert value(plant, "press", "N10:100") == (None, True, 0)
        assert value(plant, "press", "status.link_up").value == 1
        # data flows (the status block's counters change every poll), then a rebirth on command
        await plant.wait(kind("DDATA", "press"), since=nbirth.index)
        count = len(plant.host.messages)
        await plant.host.send_rebirth(GROUP, NODE)
        reborn = await plant.wait(kind("NBIRTH"), since=count)
        assert reborn.metric("bdSeq").value == nbirth.metric("bdSeq").value  # same session (5.17)
        await plant.wait(kind("DBIRTH", "press"), since=reborn.index)
        await plant.wait(kind("DBIRTH", "oven"), since=reborn.index)
        assert gw.sparkplug is not None and gw.sparkplug.core.received["NCMD"] == 1
    ndeath = await plant.wait(kind("NDEATH"), since=count)
    assert ndeath.metric("bdSeq").value == nbirth.metric("bdSeq").value
    assert not plant.host.node_online(GROUP, NODE)


async def test_link_down_is_ddeath_and_its_return_a_dbirth(plant: Plant) -> None:
    async with Gateway(plant.config()):
        await plant.wait(kind("DBIRTH", "oven"))
        count = len(plant.host.messages)
        await plant.oven.off()
        await plant.wait(kind("DDEATH", "oven"), since=count)
        assert not plant.host.device_online(GROUP, NODE, "oven")
        assert plant.host.device_online(GROUP, NODE, "press")
        count = len(plant.host.messages)
        await plant.oven.on()
        await plant.wait(kind("DBIRTH", "oven"), since=count)
        assert plant.host.device_online(GROUP, NODE, "oven")
        await plant.wait(lambda m: value(plant, "oven", "N7:2").value == 2, 5)


async def test_stale_values_are_null_with_quality_stale(plant: Plant, broker: Broker) -> None:  # noqa: F811
    links = (link_text("press", 1, plant.press, down_after_failures=1000, down_after_seconds=600, stale_after=0.5)
             + link_text("oven", 2, plant.oven))
    async with Gateway(parse_config(config_text(broker.port, plant.state_file, links))):
        await plant.wait(lambda m: value(plant, "press", "N7:1").value == 1, 10)
        # the link stays up (no down verdict for 1000 failures or 600 s), its values age
        sim = plant.press.sim
        quiet = sim.options
        sim.options = dataclasses.replace(quiet, lose_in=1)  # the controller hears nothing, answers nothing
        await plant.wait(lambda m: value(plant, "press", "N7:1").is_null, 10)
        stale = value(plant, "press", "N7:1")
        assert stale.value is None and stale.quality == 500  # STALE (6.4.9.1)
        assert plant.host.device_online(GROUP, NODE, "press")
        sim.options = quiet
        await plant.wait(lambda m: value(plant, "press", "N7:1") == (1, False, 192), 10)


async def test_dcmd_write_applied_once_under_line_faults(broker: Broker, tmp_path: Path) -> None:  # noqa: F811
    press, oven = await Line.start(seed=7, **FAULTS), await Line.start(seed=8)
    try:
        async with SparkplugHost(HOST, broker.port) as host:
            plant = Plant(broker, host, press, oven, tmp_path / "bdseq.json")
            async with Gateway(plant.config()):
                await plant.wait(lambda m: value(plant, "press", "N7:5").value == 5, 15)
                writes = [("N7:5", 1234, "Int16"), ("N7:6", -2, "Int16"), ("F8:1", 2.5, "Float"),
                          ("B3:0/1", True, "Boolean")]
                for metric, new, datatype in writes:
                    await host.send_dcmd(GROUP, NODE, "press", metric, new, datatype)
                for metric, new, _ in writes:
                    await plant.wait(lambda m, metric=metric, new=new: value(plant, "press", metric).value == new, 15)
            assert host.violations == [], "\n".join(host.violations)
    finally:
        await press.off()
        await oven.off()
    sim = press.sim
    assert sim.word("N7", 5) == 1234 and sim.word("N7", 6) == 0xFFFE
    assert sim.float_value("F8", 1) == 2.5
    assert sim.word("B3", 0) & 0b10
    applied = Counter(entry[1] for entry in sim.applied_writes)
    # each DCMD applied exactly once, whatever the line lost or repeated
    assert applied["N7:5"] == 1 and applied["N7:6"] == 1 and applied["F8:1"] == 1
    assert applied["B3:0"] == 1


async def test_dcmds_that_cannot_be_applied_change_nothing(plant: Plant) -> None:
    async with Gateway(plant.config()) as gw:
        await plant.wait(lambda m: value(plant, "press", "N7:0").value == 0, 10)
        await plant.wait(lambda m: value(plant, "oven", "N7:0").value == 0, 10)
        node = gw.sparkplug
        assert node is not None
        await plant.host.send_dcmd(GROUP, NODE, "press", "N7:50", 9, "Int16")  # input: read-only
        await plant.host.send_dcmd(GROUP, NODE, "press", "status.errors", 9, "UInt16")  # the status block
        await plant.host.send_dcmd(GROUP, NODE, "press", "N7:999", 9, "Int16")  # not a metric (by name)
        await plant.host.send_dcmd(GROUP, NODE, "oven", "N7:1", 9, "Int16")  # a read_only link
        await plant.host.send_dcmd(GROUP, NODE, "nowhere", "N7:1", 9, "Int16")  # no such device
        count = len(plant.host.messages)
        await plant.host.send_dcmd(GROUP, NODE, "press", "N10:100", 9, "Int16")  # the controller refuses
        # the refused write is logged, counted, and the metric published again with the controller's value
        await plant.wait(lambda m: m.message_type == "DDATA" and m.metric("N10:100") is not None, 10, since=count)
        assert value(plant, "press", "N10:100").is_null
        for _ in range(50):
            if node.core.received["DCMD"] == 6 and node.write_failures == 1:
                break
            await asyncio.sleep(0.05)
        assert node.core.received["DCMD"] == 6
        assert node.core.refused == {"read-only metric": 3, "unknown metric": 1, "unknown device": 1,
                                     "write failed": 1}
        assert node.write_failures == 1
    assert plant.press.sim.applied_writes == [] and plant.oven.sim.applied_writes == []
    assert plant.press.sim.word("N7", 50) == 50 and plant.oven.sim.word("N7", 1) == 1


async def test_bdseq_new_per_session_and_kept_across_restarts(plant: Plant) -> None:
    async with Gateway(plant.config()):
        first = (await plant.wait(kind("NBIRTH"))).metric("bdSeq").value
    async with Gateway(plant.config()):
        count = len(plant.host.messages)
        second = (await plant.wait(kind("NBIRTH"), since=count)).metric("bdSeq").value
    assert second == (first + 1) % 256
    assert plant.state_file.exists()


async def test_reconnects_after_the_broker_comes_back_with_a_new_bdseq(broker: Broker, tmp_path: Path) -> None:  # noqa: F811
    press, oven = await Line.start(seed=3), await Line.start(seed=4)
    state_file = tmp_path / "bdseq.json"
    try:
        links = link_text("press", 1, press) + link_text("oven", 2, oven)
        async with Gateway(parse_config(config_text(broker.port, state_file, links))) as gw:
            async with SparkplugHost(HOST, broker.port, rebirth_unknown=True) as host:
                await host.send_rebirth(GROUP, NODE)
                before = (await host.wait_for(kind("NBIRTH"), 10)).metric("bdSeq").value
                assert host.violations == []
            broker.stop()
            broker.start()
            async with SparkplugHost(HOST, broker.port, rebirth_unknown=True) as host:
                await host.send_rebirth(GROUP, NODE)
                after = (await host.wait_for(kind("NBIRTH"), 15)).metric("bdSeq").value
                await host.wait_for(kind("DBIRTH", "press"), 10)
                assert host.violations == [], "\n".join(host.violations)
            assert gw.sparkplug is not None and gw.sparkplug.sessions >= 2
        assert after == (before + 1) % 256
    finally:
        await press.off()
        await oven.off()


async def test_primary_host_state_gates_the_births(broker: Broker, tmp_path: Path) -> None:  # noqa: F811
    press, oven = await Line.start(seed=5), await Line.start(seed=6)
    try:
        async with SparkplugHost(HOST, broker.port, primary_host_id="scada") as host:
            plant = Plant(broker, host, press, oven, tmp_path / "bdseq.json")
            async with Gateway(plant.config(primary_host_id="scada")) as gw:
                assert gw.sparkplug is not None
                await asyncio.sleep(1.5)
                assert not any(m.message_type == "NBIRTH" for m in host.messages)  # 5.4: wait for the host
                assert gw.sparkplug.session_state == "connected"
                await host.publish_state(True)
                first = await plant.wait(kind("NBIRTH"))
                await plant.wait(kind("DBIRTH", "press"), since=first.index)
                await host.publish_state(False)  # 5.5: the node goes offline with its host
                death = await plant.wait(kind("NDEATH"), since=first.index)
                assert death.metric("bdSeq").value == first.metric("bdSeq").value
                await asyncio.sleep(1.0)
                assert not any(m.message_type == "NBIRTH" for m in host.messages[death.index:])
                await host.publish_state(True)
                second = await plant.wait(kind("NBIRTH"), since=death.index)
                assert second.metric("bdSeq").value == (first.metric("bdSeq").value + 1) % 256
            assert host.violations == [], "\n".join(host.violations)
    finally:
        await press.off()
        await oven.off()


def fetch(port: int, path: str) -> str:
    with urllib.request.urlopen(f"http://{HOST}:{port}{path}", timeout=5) as reply:
        text: str = reply.read().decode()
        return text


async def test_status_api_and_metrics_report_the_session(plant: Plant) -> None:
    text = config_text(plant.broker.port, plant.state_file,
                       link_text("press", 1, plant.press) + link_text("oven", 2, plant.oven))
    text = text.replace("[sparkplug]", '[metrics]\nlisten = "127.0.0.1:0"\n\n[sparkplug]', 1)
    async with Gateway(parse_config(text)) as gw:
        await plant.wait(kind("DBIRTH", "oven"))
        await plant.host.send_dcmd(GROUP, NODE, "press", "N7:50", 9, "Int16")  # read-only: refused
        assert gw.metrics is not None and gw.sparkplug is not None
        for _ in range(50):
            if gw.sparkplug.core.refused:
                break
            await asyncio.sleep(0.05)
        status = json.loads(await asyncio.to_thread(fetch, gw.metrics.port, "/api/status"))["sparkplug"]
        metrics = await asyncio.to_thread(fetch, gw.metrics.port, "/metrics")
    assert status["state"] == "online" and status["group_id"] == GROUP and status["edge_node_id"] == NODE
    assert status["devices_online"] == 2 and status["sessions"] == 1
    assert status["published_by_type"]["NBIRTH"] == 1 and status["published_by_type"]["DBIRTH"] == 2
    assert status["commands_by_type"] == {"DCMD": 1} and status["refused_by_reason"] == {"read-only metric": 1}
    assert 'slc_gateway_sparkplug_session{state="online"} 1.0' in metrics
    assert 'slc_gateway_sparkplug_messages_published_total{type="NBIRTH"} 1.0' in metrics
    assert 'slc_gateway_sparkplug_commands_received_total{type="DCMD"} 1.0' in metrics
    assert 'slc_gateway_sparkplug_commands_refused_total{reason="read-only metric"} 1.0' in metrics
    assert "slc_gateway_sparkplug_devices_online 2.0" in metrics


async def test_a_refused_write_republishes_the_controllers_value(broker: Broker, tmp_path: Path) -> None:  # noqa: F811
    # An SLC 150's presets hold 0-9999 (the manual's range, export-tags: "901.PRE ... (0-9999)"):
    # 12000 is refused before anything is sent (as a Modbus write of it is, 0x03).
    link = (f'[[link]]\nname = "slc"\nprotocol = "slc-ascii"\nport = "sim://slc150?ladder=0&instance={uuid.uuid4().hex}"'
            "\nunit = 1\n")
    async with SparkplugHost(HOST, broker.port) as host:
        async with Gateway(parse_config(config_text(broker.port, tmp_path / "bdseq.json", link))) as gw:
            await host.wait_for(kind("DBIRTH", "slc"), 10)
            await host.wait_for(lambda m: host_value(host, "slc", "901.PRE").value is not None, 10)
            before = host_value(host, "slc", "901.PRE").value
            count = len(host.messages)
            await host.send_dcmd(GROUP, NODE, "slc", "901.PRE", 12000, "UInt16")
            republished = await host.wait_for(
                lambda m: m.message_type == "DDATA" and m.metric("901.PRE") is not None, 10, since=count)
            assert republished.metric("901.PRE").value == before  # the controller's value, published again
            assert gw.sparkplug is not None and gw.sparkplug.write_failures == 1
            assert gw.sparkplug.core.refused == {"write failed": 1}
            await host.send_dcmd(GROUP, NODE, "slc", "902.PRE", 1234, "UInt16")
            await host.wait_for(lambda m: host_value(host, "slc", "902.PRE").value == 1234, 10)
        assert host.violations == [], "\n".join(host.violations)


async def test_deadband_and_read_time_stamps(plant: Plant, broker: Broker) -> None:  # noqa: F811
    links = (link_text("press", 1, plant.press).replace('address = "F8:0"\ncount = 2\ntype = "float32"\n',
                                                        'address = "F8:0"\ncount = 2\ntype = "float32"\n'
                                                        "deadband = 0.5\n")
             + link_text("oven", 2, plant.oven))
    assert "deadband = 0.5" in links
    sim = plant.press.sim
    sim.set_float("F8", 0, 1.0)
    async with Gateway(parse_config(config_text(broker.port, plant.state_file, links))):
        await plant.wait(lambda m: value(plant, "press", "F8:0").value == 1.0, 10)
        count = len(plant.host.messages)
        sim.set_float("F8", 0, 1.25)  # within the deadband of the last published 1.0: not published
        changed_at = time.time() * 1000
        sim.set_word("N7", 2, 77)  # published: no deadband on N7
        ddata = await plant.wait(lambda m: m.message_type == "DDATA" and m.metric("N7:2") is not None, 10,
                                 since=count)
        # the metric's timestamp is its read time: before the message was made, after the change
        stamp = ddata.metric("N7:2").timestamp
        assert stamp is not None and ddata.payload.timestamp is not None
        assert changed_at - 50 <= stamp <= ddata.payload.timestamp  # 50 ms: the loop clock against the wall
        await asyncio.sleep(1.0)
        assert value(plant, "press", "F8:0").value == 1.0
        sim.set_float("F8", 0, 1.75)  # 0.75 from the last published: published
        await plant.wait(lambda m: value(plant, "press", "F8:0").value == 1.75, 10)
