"""The Sparkplug edge node's session core (gateway.sparkplug.node), sans-I/O, with a fake clock.

Expected values are the Sparkplug 3.0 specification's (section in each test), not the code's.
"""

from __future__ import annotations

import json
import math

import pytest

from gateway.sparkplug.history import Change
from gateway.sparkplug.node import Device, EdgeNode, MetricSpec, Publish, Sample
from gateway.sparkplug.payload import Metric, Payload, SparkplugType, decode, encode

GROUP, NODE = "plant1", "gw1"
T0 = 1_700_000_000_000  # a fake UTC clock, ms


def make_node(primary: str | None = None, bd_seq: int | None = None) -> EdgeNode:
    press = Device("press", [
        MetricSpec("N7:0", 2, SparkplugType.Int16, writable=True),
        MetricSpec("F8:0", 3, SparkplugType.Float, writable=True, deadband=0.5),
        MetricSpec("status.link_up", 4, SparkplugType.UInt16),
    ])
    oven = Device("oven", [MetricSpec("B3:0/0", 5, SparkplugType.Boolean, writable=True)])
    return EdgeNode(GROUP, NODE, [press, oven], primary_host_id=primary, bd_seq=bd_seq)


def verbs(messages: list[Publish]) -> list[str]:
    return [m.topic.split("/")[2] + ("/" + m.topic.split("/")[4] if m.topic.count("/") == 4 else "")
            for m in messages]


def seqs(messages: list[Publish]) -> list[int | None]:
    return [decode(m.payload).seq for m in messages]


def with_dbirths(node: EdgeNode, first: list[Publish], now: int = T0) -> list[Publish]:
    """``first`` (an NBIRTH) and the DBIRTHs of the sequence it starts."""
    out = list(first)
    while (dbirth := node.next_birth(now)) is not None:
        out.append(dbirth)
    return out


def online(node: EdgeNode, now: int = T0) -> list[Publish]:
    for index in range(len(node.devices)):
        node.link(index, True, now)
    node.connecting(now)
    return with_dbirths(node, node.connected(now), now)


def test_will_is_ndeath_with_bdseq_qos1_not_retained() -> None:
    # §5.4: will topic spBv1.0/group/NDEATH/node, QoS 1, retain false, bdSeq Int64; §6.4.25: no seq
    node = make_node()
    will = node.connecting(T0)
    assert (will.topic, will.qos, will.retain) == ("spBv1.0/plant1/NDEATH/gw1", 1, False)
    payload = decode(will.payload)
    assert payload.seq is None
    assert [(m.name, m.datatype, m.value) for m in payload.metrics] == [("bdSeq", 4, 0)]


def test_bdseq_increments_per_connect_and_wraps() -> None:
    # tck-id-topics-nbirth-bdseq-increment: starts at 0, +1 per CONNECT; after 255 comes 0 (§6.4.25)
    node = make_node(bd_seq=254)
    values = [decode(node.connecting(T0).payload).metrics[0].value for _ in range(3)]
    assert values == [255, 0, 1]
    assert decode(make_node().connecting(T0).payload).metrics[0].value == 0


def test_births_nbirth_seq0_bdseq_rebirth_then_dbirths() -> None:
    node = make_node(bd_seq=6)
    node.observe(0, 0, Sample(-5, T0 - 10))
    out = online(node)
    assert verbs(out) == ["NBIRTH", "DBIRTH/press", "DBIRTH/oven"]
    assert seqs(out) == [0, 1, 2]  # §4.2.1.1.2 NBIRTH seq 0; +1 per message (§6.4.20)
    assert all(m.qos == 0 and not m.retain for m in out)  # §6.4.19, §6.4.20
    nbirth = {m.name: m for m in decode(out[0].payload).metrics}
    assert nbirth["bdSeq"].value == 7  # the will's (§6.4.19)
    rebirth = nbirth["Node Control/Rebirth"]
    assert (rebirth.datatype, rebirth.value, rebirth.alias) == (11, False, None)  # §5.17: Boolean, false, no alias
    press = decode(out[1].payload).metrics
    n7 = next(m for m in press if m.name == "N7:0")
    assert (n7.alias, n7.datatype, n7.value, n7.timestamp) == (2, 2, 0xFFFFFFFB, T0 - 10)
    # a metric never observed: null, with quality STALE (§6.4.9.1: 500)
    f8 = next(m for m in press if m.name == "F8:0")
    assert f8.is_null and f8.value is None and f8.properties is not None and f8.properties["Quality"] == (3, 500)
    # births list metrics in chronological order (§5.16)
    stamps = [m.timestamp or 0 for m in press]
    assert stamps == sorted(stamps)


def test_seq_wraps_after_255() -> None:
    node = make_node()
    online(node)  # seq 0, 1, 2 used
    got = []
    for k in range(300):
        node.observe(0, 0, Sample(k, T0 + k))
        got.extend(seqs(node.flush(T0 + k)))
    assert got[:3] == [3, 4, 5]
    assert got[252:256] == [255, 0, 1, 2]  # §6.4.5: after 255 comes 0


def test_ddata_only_changes_by_alias_with_read_time() -> None:
    node = make_node()
    node.observe(0, 0, Sample(1, T0))
    online(node)
    assert node.flush(T0 + 1) == []  # nothing changed
    node.observe(0, 0, Sample(1, T0 + 5))  # same value, newer read: not published (§5.16 RBE)
    node.observe(0, 2, Sample(1, T0 + 5))
    node.observe(1, 0, Sample(True, T0 + 7))
    out = node.flush(T0 + 9)
    assert verbs(out) == ["DDATA/press", "DDATA/oven"]
    press = decode(out[0].payload).metrics
    assert [(m.name, m.alias, m.datatype, m.value, m.timestamp) for m in press] == [(None, 4, None, 1, T0 + 5)]
    assert decode(out[0].payload).timestamp == T0 + 9


def test_deadband() -> None:
    node = make_node()
    node.observe(0, 1, Sample(10.0, T0))
    online(node)
    node.observe(0, 1, Sample(10.4, T0 + 1))
    assert node.flush(T0 + 1) == []  # within 0.5 of the last published
    node.observe(0, 1, Sample(10.6, T0 + 2))
    (ddata,) = node.flush(T0 + 2)
    assert decode(ddata.payload).metrics[0].value == pytest.approx(10.6)


def test_stale_is_null_with_quality_then_good_again() -> None:
    node = make_node()
    node.observe(0, 0, Sample(3, T0))
    online(node)
    node.observe(0, 0, Sample(None, T0 + 1, 500, "no fresh data"))
    (ddata,) = node.flush(T0 + 1)
    (metric,) = decode(ddata.payload).metrics
    assert metric.is_null and metric.value is None
    assert metric.properties == {"Quality": (3, 500), "Quality Reason": (12, "no fresh data")}
    node.observe(0, 0, Sample(3, T0 + 2))
    (ddata,) = node.flush(T0 + 2)
    (metric,) = decode(ddata.payload).metrics
    assert (metric.value, metric.is_null, metric.properties) == (3, False, {"Quality": (3, 192)})


def test_link_down_ddeath_and_back_dbirth() -> None:
    node = make_node()
    online(node)
    out = node.link(1, False, T0 + 1)
    assert verbs(out) == ["DDEATH/oven"] and seqs(out) == [3]
    node.observe(1, 0, Sample(True, T0 + 2))
    assert node.flush(T0 + 2) == []  # a dead device publishes nothing
    out = node.link(1, True, T0 + 3)
    assert verbs(out) == ["DBIRTH/oven"] and seqs(out) == [4]
    assert decode(out[0].payload).metrics[0].value is True


def test_no_dbirth_for_a_device_down_at_birth() -> None:
    node = make_node()
    node.link(0, True, T0)
    node.connecting(T0)
    assert verbs(with_dbirths(node, node.connected(T0))) == ["NBIRTH", "DBIRTH/press"]


def rebirth_request(value: bool = True) -> bytes:
    return encode(Payload(T0, (Metric(name="Node Control/Rebirth", datatype=11, value=value),)))


def test_rebirth_republishes_births_same_bdseq() -> None:
    node = make_node()
    online(node)
    node.observe(0, 0, Sample(8, T0 + 1))
    node.flush(T0 + 1)
    out = node.node_command(rebirth_request(), T0 + 2)
    assert verbs(out) == ["NBIRTH"]
    node.observe(0, 0, Sample(9, T0 + 2))
    assert node.flush(T0 + 2) == []  # no DDATA before the last DBIRTH (§6.4.20)
    out = with_dbirths(node, out, T0 + 2)
    assert verbs(out) == ["NBIRTH", "DBIRTH/press", "DBIRTH/oven"]
    assert seqs(out) == [0, 1, 2]
    assert decode(out[0].payload).metrics[0].value == 0  # same bdSeq: no new MQTT session (§5.17)
    assert node.node_command(rebirth_request(False), T0 + 3) == []
    assert node.node_command(b"\xff\xff garbage", T0 + 3) == []
    assert node.refused["bad payload"] == 1


def dcmd(*metrics: Metric) -> bytes:
    return encode(Payload(T0, metrics))


def test_dcmd_by_alias_and_name_and_refusals() -> None:
    node = make_node()
    online(node)
    commands = node.device_command("press", dcmd(
        Metric(alias=2, value=-3, value_type=SparkplugType.Int16),  # by alias, two's complement in 32 bits
        Metric(name="F8:0", datatype=SparkplugType.Float, value=1.5),
        Metric(alias=4, value=0, value_type=SparkplugType.UInt16),  # status: read-only
        Metric(name="N7:99", datatype=SparkplugType.Int16, value=1),  # unknown
        Metric(alias=2, value="x", value_type=SparkplugType.String),  # wrong kind
        Metric(alias=2, is_null=True),
    ))
    assert [(c.device, c.metric, c.value) for c in commands] == [(0, 0, -3), (0, 1, 1.5)]
    assert node.refused == {"read-only metric": 1, "unknown metric": 1, "wrong value type": 1, "no value": 1}
    assert node.device_command("nope", dcmd(Metric(alias=5, value=True, value_type=SparkplugType.Boolean))) == []
    assert node.refused["unknown device"] == 1
    assert node.received["DCMD"] == 2


def test_int16_from_16_bit_twos_complement_too_and_nothing_wider() -> None:
    node = make_node()
    (command,) = node.device_command("press", dcmd(Metric(alias=2, value=0xFFFB, value_type=SparkplugType.UInt32)))
    assert command.value == -5
    for raw in (0x12345, 0xFFFF0000, 0x7FFFFFFF):  # bits past 16 that are not a sign extension
        assert node.device_command("press", dcmd(Metric(alias=2, value=raw, value_type=SparkplugType.UInt32))) == []
    assert node.refused["wrong value type"] == 3


def test_forced_metric_published_even_unchanged() -> None:
    node = make_node()
    node.observe(0, 0, Sample(4, T0))
    online(node)
    node.force(0, 0)
    (ddata,) = node.flush(T0 + 1)
    assert decode(ddata.payload).metrics[0].value == 4
    assert node.flush(T0 + 2) == []


def state(online_: bool, timestamp: int) -> bytes:
    return json.dumps({"online": online_, "timestamp": timestamp}).encode()


def test_primary_host_gates_births_and_offline_ends_session() -> None:
    node = make_node(primary="scada")
    assert ("spBv1.0/STATE/scada", 1) in node.subscriptions()
    assert node.subscriptions()[:2] == [("spBv1.0/plant1/NCMD/gw1", 1), ("spBv1.0/plant1/DCMD/gw1/+", 1)]
    assert online(node) == []  # §5.4 phid-wait: nothing before the host is online
    assert node.node_command(rebirth_request(), T0) == []
    out, disconnect = node.host_state(state(True, 100), T0 + 1)
    assert verbs(out)[0] == "NBIRTH" and not disconnect
    # an older offline (a stale will of an earlier host session) is ignored (§5.5 ...-host-offline-timestamp)
    assert node.host_state(state(False, 99), T0 + 2) == ([], False)
    # offline, not older: NDEATH with this session's bdSeq, then disconnect (§5.5)
    out, disconnect = node.host_state(state(False, 100), T0 + 3)
    assert verbs(out) == ["NDEATH"] and disconnect
    assert decode(out[0].payload).metrics[0].value == 0 and decode(out[0].payload).seq is None
    assert node.host_state(b"{nope", T0 + 4) == ([], False)
    assert node.refused["bad STATE payload"] == 1


def test_offline_state_before_the_births_keeps_waiting() -> None:
    node = make_node(primary="scada")
    online(node)
    assert node.host_state(state(False, 50), T0) == ([], False)  # retained offline: no session to end
    out, disconnect = node.host_state(state(True, 60), T0 + 1)
    assert verbs(out)[0] == "NBIRTH" and not disconnect


def test_state_before_connect_counts_for_the_next_session() -> None:
    node = make_node(primary="scada")
    node.connecting(T0)
    node.host_state(state(True, 5), T0)  # retained STATE arrives with the subscription
    assert verbs(node.connected(T0))[:1] == []  # connected() resets: waits for the STATE again
    out, _ = node.host_state(state(True, 5), T0)  # same timestamp: still valid (>=)
    assert verbs(out)[0] == "NBIRTH"


def test_stopping_publishes_ndeath_only_after_the_births() -> None:
    node = make_node()
    assert node.stopping(T0) == []
    waiting = make_node(primary="scada")
    online(waiting)  # connected, waiting for the primary host: no session yet
    assert waiting.stopping(T0) == []
    online(node)
    (ndeath,) = node.stopping(T0)
    assert ndeath.topic == "spBv1.0/plant1/NDEATH/gw1"


def test_links_changing_during_a_birth_sequence() -> None:
    node = make_node()
    node.link(0, True, T0)
    node.connecting(T0)
    assert verbs(node.connected(T0)) == ["NBIRTH"]
    assert node.link(1, True, T0) == []  # joins the sequence under way
    assert node.link(0, False, T0) == []  # gone before its DBIRTH: none, and no DDEATH for it
    assert verbs(with_dbirths(node, [])) == ["DBIRTH/oven"]
    assert node.next_birth(T0) is None


def test_the_core_is_sans_io() -> None:
    """node.py and payload.py: no asyncio, sockets, MQTT, threads or clock (the caller passes the time)."""
    import ast
    from pathlib import Path

    forbidden = {"asyncio", "socket", "ssl", "selectors", "threading", "time", "datetime", "aiomqtt", "paho"}
    root = Path(__file__).resolve().parents[2] / "gateway" / "sparkplug"
    for name in ("node.py", "payload.py"):
        tree = ast.parse((root / name).read_text(encoding="utf-8"))
        imported = {alias.name.split(".")[0] for node in ast.walk(tree) if isinstance(node, ast.Import)
                    for alias in node.names}
        imported |= {node.module.split(".")[0] for node in ast.walk(tree)
                     if isinstance(node, ast.ImportFrom) and node.module}
        assert not imported & forbidden, (name, imported & forbidden)


def test_every_command_and_refusal_is_counted_by_type_and_reason() -> None:
    """``received`` and ``refused`` are the metrics' ``commands_received{type}`` and
    ``commands_refused{reason}`` counters: each message and each refused metric counts one."""
    node = make_node(primary="scada")
    online(node)
    for _ in range(2):
        node.host_state(state(True, 100), T0)
        node.host_state(b"{nope", T0)
        node.host_state(state(True, 99), T0)  # older than the last online one
        node.node_command(b"\xff\xff", T0)
        node.node_command(encode(Payload(T0, (Metric(name="Node Control/Other", datatype=11, value=True),))), T0)
        node.device_command("nope", dcmd(Metric(alias=5, value=True, value_type=SparkplugType.Boolean)))
        node.device_command("press", b"\xff\xff")
        node.device_command("press", dcmd(
            Metric(name="N7:99", datatype=SparkplugType.Int16, value=1),
            Metric(alias=4, value=0, value_type=SparkplugType.UInt16),
            Metric(alias=2, is_null=True)))
    assert node.received == {"STATE": 6, "NCMD": 4, "DCMD": 6}
    assert node.refused == {"bad STATE payload": 2, "old STATE": 2, "bad payload": 4, "unknown node metric": 2,
                            "unknown device": 2, "unknown metric": 2, "read-only metric": 2, "no value": 2}


def test_a_refused_metric_of_a_dcmd_does_not_stop_the_ones_after_it() -> None:
    node = make_node()
    online(node)
    good = Metric(alias=2, value=7, value_type=SparkplugType.Int16)
    commands = node.device_command("press", dcmd(
        Metric(name="N7:99", datatype=SparkplugType.Int16, value=1), good,  # unknown
        Metric(alias=4, value=0, value_type=SparkplugType.UInt16), good,  # read-only
        Metric(alias=2, is_null=True), good,  # no value
        Metric(alias=2, value="x", value_type=SparkplugType.String), good))  # wrong type
    assert [(c.device, c.metric, c.value) for c in commands] == [(0, 0, 7)] * 4


@pytest.mark.parametrize("payload", [
    {"online": True, "timestamp": True},  # a boolean is not a timestamp (JSON true is no integer)
    {"online": 1, "timestamp": 5},  # online must be a boolean
    {"online": True, "timestamp": 5.5},
    {"online": True},
])
def test_a_state_payload_of_the_wrong_shape_is_refused(payload: dict[str, object]) -> None:
    node = make_node(primary="scada")
    node.connecting(T0)
    node.connected(T0)
    assert node.host_state(json.dumps(payload).encode(), T0) == ([], False)
    assert node.refused == {"bad STATE payload": 1}
    assert node.node_command(rebirth_request(), T0) == []  # the host is not online: still waiting


def test_the_primary_hosts_state_decides_births_and_rebirths() -> None:
    node = make_node(primary="scada")
    # before the MQTT session is up, an online STATE publishes nothing (births come with connected())
    assert node.host_state(state(True, 5), T0) == ([], False)
    node.connecting(T0)
    assert node.connected(T0) == []
    assert node.host_state(state(False, 6), T0) == ([], False)  # offline before the births: keep waiting
    assert node.node_command(rebirth_request(), T0) == []  # no rebirth for a host that is offline
    out, disconnect = node.host_state(state(True, 7), T0)
    assert verbs(out) == ["NBIRTH"] and not disconnect
    assert node.host_state(state(True, 8), T0) == ([], False)  # online again while online: nothing new
    assert verbs(node.node_command(rebirth_request(), T0)) == ["NBIRTH"]  # the host is online: a rebirth


def test_a_node_stopped_once_publishes_no_second_ndeath() -> None:
    node = make_node()
    online(node)
    assert verbs(node.stopping(T0)) == ["NDEATH"]
    assert node.stopping(T0 + 1) == []


def test_every_birth_and_death_carries_its_time() -> None:
    """Payload and metric timestamps (§6.4.5, §6.4.6): the NBIRTH's and NDEATH's bdSeq and the rebirth
    flag at the time of the message; bdSeq with alias 1 in the NBIRTH, none in the NDEATH, the rebirth
    flag none (§5.17; the reading of docs/guide/sparkplug.md)."""
    node = make_node()
    node.link(0, True, T0)
    ndeath = decode(node.connecting(T0 + 1).payload)
    assert ndeath.timestamp == T0 + 1
    assert [(m.name, m.alias, m.timestamp, m.value) for m in ndeath.metrics] == [("bdSeq", None, T0 + 1, 0)]
    (nbirth,) = node.connected(T0 + 2)
    payload = decode(nbirth.payload)
    assert payload.timestamp == T0 + 2
    assert [(m.name, m.alias, m.timestamp) for m in payload.metrics] == [
        ("bdSeq", 1, T0 + 2), ("Node Control/Rebirth", None, T0 + 2)]
    dbirth = node.next_birth(T0 + 3)
    assert dbirth is not None and decode(dbirth.payload).timestamp == T0 + 3
    (ddeath,) = node.link(0, False, T0 + 4)
    assert decode(ddeath.payload).timestamp == T0 + 4 and decode(ddeath.payload).metrics == ()
    (ndeath_publish,) = node.stopping(T0 + 5)
    assert decode(ndeath_publish.payload).timestamp == T0 + 5
    assert decode(ndeath_publish.payload).metrics[0].timestamp == T0 + 5


def test_a_dbirth_metric_not_read_yet_is_null_stale_and_says_so() -> None:
    node = make_node()
    (_nbirth, press, _oven) = online(node, T0 + 7)
    metrics = decode(press.payload).metrics
    assert all(m.is_null and m.timestamp == T0 + 7 for m in metrics)
    assert metrics[0].properties == {"Quality": (3, 500), "Quality Reason": (12, "not read yet")}


def test_a_null_without_a_reason_says_no_value() -> None:
    node = make_node()
    node.observe(0, 0, Sample(3, T0))
    online(node)
    node.observe(0, 0, Sample(None, T0 + 1, 0))
    (ddata,) = node.flush(T0 + 1)
    assert decode(ddata.payload).metrics[0].properties == {"Quality": (3, 0), "Quality Reason": (12, "no value")}


def test_what_counts_as_a_change() -> None:
    """§5.16 report by exception: a value, its quality, or why it is null; NaN stays NaN; deadband only
    when set, and a change of exactly the deadband is not past it."""
    node = make_node()
    for value in (1, 2):
        node.observe(0, 0, Sample(value, T0))
    online(node)

    def published(device: int, metric: int, sample: Sample) -> list[object]:
        node.observe(device, metric, sample)
        return [m.value if not m.is_null else m.properties for out in node.flush(sample.timestamp)
                for m in decode(out.payload).metrics]

    assert published(0, 0, Sample(None, T0 + 1, 500, "a")) == [{"Quality": (3, 500), "Quality Reason": (12, "a")}]
    assert published(0, 0, Sample(None, T0 + 2, 500, "a")) == []  # the same null: nothing
    assert published(0, 0, Sample(None, T0 + 3, 500, "b")) == [{"Quality": (3, 500), "Quality Reason": (12, "b")}]
    assert published(0, 0, Sample(None, T0 + 4, 0, "b")) != []  # the quality changed
    assert published(0, 0, Sample(5, T0 + 5)) == [5]
    assert published(0, 0, Sample(6, T0 + 6)) == [6]  # no deadband: any change
    assert published(0, 0, Sample(6, T0 + 7)) == []
    assert published(0, 1, Sample(10.0, T0 + 8)) == [10.0]
    assert published(0, 1, Sample(10.5, T0 + 9)) == []  # exactly the deadband (0.5): not past it
    assert published(0, 1, Sample(math.nan, T0 + 10)) != []
    assert published(0, 1, Sample(math.nan, T0 + 11)) == []  # NaN again: unchanged
    assert published(0, 1, Sample(10.0, T0 + 12)) == [10.0]  # and back: past any deadband too


def storing_node() -> EdgeNode:
    press = Device("press", [MetricSpec("N7:0", 2, SparkplugType.Int16), MetricSpec("N7:1", 3, SparkplugType.Int16)])
    oven = Device("oven", [MetricSpec("B3:0/0", 5, SparkplugType.Boolean)])
    return EdgeNode(GROUP, NODE, [press, oven], store=True)


def test_a_flush_of_some_devices_leaves_the_others_changes_for_later() -> None:
    node = make_node()
    online(node)
    node.observe(0, 0, Sample(1, T0 + 1))
    node.observe(1, 0, Sample(True, T0 + 1))
    assert verbs(node.flush(T0 + 2, [1])) == ["DDATA/oven"]
    assert verbs(node.flush(T0 + 3)) == ["DDATA/press"]


def test_a_dead_device_does_not_stop_the_flush_of_the_others() -> None:
    node = make_node()
    online(node)
    node.link(0, False, T0 + 1)
    node.observe(0, 0, Sample(1, T0 + 2))
    node.observe(1, 0, Sample(True, T0 + 2))
    assert verbs(node.flush(T0 + 3)) == ["DDATA/oven"]


def test_a_forced_metric_never_read_does_not_stop_the_others() -> None:
    node = make_node()
    online(node)
    node.force(0, 0)  # nothing read: nothing to publish for it
    node.observe(0, 2, Sample(1, T0 + 1))
    (ddata,) = node.flush(T0 + 2)
    # its DBIRTH said null (not read yet): the first good value carries Quality 192
    assert [(m.alias, m.value, m.properties) for m in decode(ddata.payload).metrics] == [(4, 1, {"Quality": (3, 192)})]


def test_birth_metrics_and_ordinary_changes_carry_no_quality() -> None:
    """``Quality`` goes with a null, and 192 with the first good value after one (§6.4.9.1): not with
    every value."""
    node = make_node()
    node.observe(0, 0, Sample(1, T0))
    (_nbirth, press, _oven) = online(node)
    assert decode(press.payload).metrics[0].properties is None
    node.observe(0, 0, Sample(2, T0 + 1))
    (ddata,) = node.flush(T0 + 1)
    assert decode(ddata.payload).metrics[0].properties is None


def test_offline_changes_are_kept_for_the_devices_flushed_with_their_reasons() -> None:
    node = storing_node()
    node.link(0, True, T0)
    node.link(1, True, T0)
    node.observe(0, 0, Sample(None, T0 + 1, 500, "no fresh data"))
    node.observe(1, 0, Sample(True, T0 + 1))
    assert node.flush(T0 + 2, [1]) == []  # not online: kept, not published
    assert node.take_unsent() == [Change("oven", "B3:0/0", T0 + 1, True, 192, "")]
    assert node.flush(T0 + 3) == []
    assert node.take_unsent() == [Change("press", "N7:0", T0 + 1, None, 500, "no fresh data")]


def test_a_dead_device_does_not_stop_the_others_changes_being_kept() -> None:
    node = storing_node()
    node.link(1, True, T0)  # press is down
    node.observe(0, 0, Sample(1, T0 + 1))
    node.observe(1, 0, Sample(True, T0 + 1))
    node.flush(T0 + 2)
    assert [c.device for c in node.take_unsent()] == ["oven"]


def history_node() -> EdgeNode:
    node = storing_node()
    node.link(0, True, T0)
    node.link(1, True, T0)
    node.connecting(T0)
    with_dbirths(node, node.connected(T0))
    return node


def test_history_is_ddata_by_alias_marked_historical_with_original_times() -> None:
    node = history_node()
    changes = [Change("press", "N7:9", T0 - 9, 1, 192), Change("press", "N7:1", T0 - 8, None, 500, "stale"),
               Change("press", "gone", T0 - 7, 1, 192), Change("press", "N7:0", T0 - 6, 4, 192)]
    out = node.historical(0, changes, T0 + 1)
    assert out is not None and verbs([out]) == ["DDATA/press"]
    metrics = decode(out.payload).metrics
    assert [(m.name, m.alias, m.datatype, m.timestamp, m.is_historical) for m in metrics] == [
        (None, 3, None, T0 - 8, True), (None, 2, None, T0 - 6, True)]
    assert metrics[0].properties == {"Quality": (3, 500), "Quality Reason": (12, "stale")}
    assert node.unknown_history == 2  # N7:9 and gone: not metrics of the device


def test_no_history_while_births_are_under_way_or_after_stopping() -> None:
    node = storing_node()
    node.link(0, True, T0)
    node.link(1, True, T0)
    node.connecting(T0)
    node.connected(T0)
    assert node.next_birth(T0) is not None  # press is born, oven not yet
    change = [Change("press", "N7:0", T0 - 6, 4, 192)]
    assert node.historical(0, change, T0) is None
    while node.next_birth(T0) is not None:
        pass
    assert node.historical(0, change, T0) is not None
    node.stopping(T0)
    assert node.historical(0, change, T0) is None


def test_a_lost_session_publishes_nothing_until_the_next() -> None:
    node = make_node(primary="scada")
    online(node)
    node.host_state(state(True, 1), T0)
    node.disconnected(T0 + 1)
    node.observe(0, 0, Sample(7, T0 + 2))
    assert node.flush(T0 + 2) == []
    assert node.host_state(state(True, 2), T0 + 3) == ([], False)  # no session: no births
    assert node.stopping(T0 + 4) == []


def test_a_device_coming_up_in_a_lost_session_gets_no_dbirth() -> None:
    node = make_node()
    online(node)
    node.link(0, False, T0 + 1)
    node.disconnected(T0 + 2)
    assert node.link(0, True, T0 + 3) == []  # its DBIRTH comes with the next session's births
