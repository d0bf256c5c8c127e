"""Store and forward in the session core (gateway.sparkplug.node, gateway.sparkplug.history), sans-I/O, fake clock.

Issue 43, items 2 and 3, and the Sparkplug 3.0 rules they keep: is_historical (§6.4.6), seq one more per
message after the NBIRTH, 255 then 0 (§6.4.22 tck-id-payloads-ddata-seq-inc), births before any DDATA
(tck-id-payloads-ddata-order), bdSeq one per CONNECT (§5.4).
"""

from __future__ import annotations

import json
import math

from gateway.sparkplug.history import Change, Window, sample_text, sample_value
from gateway.sparkplug.node import STALE, Device, EdgeNode, MetricSpec, Publish, Sample
from gateway.sparkplug.payload import SparkplugType, decode

T0 = 1_700_000_000_000
KEEPALIVE_WINDOW = 45_000  # a window of 45 s (the driver: 2 x keepalive + 2 s)


def make_node() -> EdgeNode:
    press = Device("press", [MetricSpec("N7:0", 2, SparkplugType.Int16), MetricSpec("F8:0", 3, SparkplugType.Float)])
    oven = Device("oven", [MetricSpec("B3:0/0", 4, SparkplugType.Boolean)])
    return EdgeNode("plant1", "gw1", [press, oven], store=True, window=KEEPALIVE_WINDOW)


def go_online(node: EdgeNode, now: int) -> list[Publish]:
    node.connecting(now)
    out = node.connected(now)
    while (dbirth := node.next_birth(now)) is not None:
        out.append(dbirth)
    return out


def observe(node: EdgeNode, device: int, metric: int, value: object, at: int) -> None:
    node.observe(device, metric, Sample(value, at))  # type: ignore[arg-type]


def test_offline_changes_are_kept_in_order_with_their_timestamps_and_nothing_is_published() -> None:
    node = make_node()
    node.link(0, True, T0)
    for k in range(3):
        observe(node, 0, 0, k, T0 + k * 1000)
        assert node.flush(T0 + k * 1000 + 50) == []
    kept = node.take_unsent()
    assert [(c.device, c.metric, c.timestamp, c.value) for c in kept] == [
        ("press", "N7:0", T0, 0), ("press", "N7:0", T0 + 1000, 1), ("press", "N7:0", T0 + 2000, 2)]
    assert node.take_unsent() == []


def test_an_unchanged_value_is_not_kept_and_a_dead_device_keeps_nothing() -> None:
    node = make_node()
    node.link(0, True, T0)
    observe(node, 0, 0, 5, T0)
    node.flush(T0)
    observe(node, 0, 0, 5, T0 + 1000)  # same value
    observe(node, 1, 0, True, T0 + 1000)  # oven's link is down
    node.flush(T0 + 1000)
    assert [c.value for c in node.take_unsent()] == [5]


def test_without_store_nothing_is_kept() -> None:
    node = EdgeNode("plant1", "gw1", [Device("press", [MetricSpec("N7:0", 2, SparkplugType.Int16)])])
    node.link(0, True, T0)
    observe(node, 0, 0, 1, T0)
    node.flush(T0)
    assert node.unsent == []


def test_what_was_published_in_the_window_is_kept_when_the_connection_is_found_lost() -> None:
    node = make_node()
    node.link(0, True, T0)
    go_online(node, T0)
    observe(node, 0, 0, 1, T0 + 1_000)
    assert len(node.flush(T0 + 1_000)) == 1  # published at T0 + 1 s: out of the window at the loss
    observe(node, 0, 0, 2, T0 + 60_000)
    assert len(node.flush(T0 + 60_000)) == 1  # published 40 s before the loss: in doubt
    node.disconnected(T0 + 100_000)
    assert [(c.value, c.timestamp) for c in node.take_unsent()] == [(2, T0 + 60_000)]


def test_a_clean_stop_leaves_nothing_in_doubt() -> None:
    node = make_node()
    node.link(0, True, T0)
    go_online(node, T0)
    observe(node, 0, 0, 1, T0 + 1_000)
    node.flush(T0 + 1_000)
    node.stopping(T0 + 2_000)
    node.disconnected()
    assert node.take_unsent() == []


def test_replay_after_the_births_is_ddata_marked_historical_with_original_timestamps_and_the_next_seq() -> None:
    node = make_node()
    node.link(0, True, T0)
    for k in range(3):
        observe(node, 0, 0, k - 1, T0 + k)
        node.flush(T0 + k)
    observe(node, 0, 1, 2.5, T0 + 3)
    node.flush(T0 + 3)
    kept = node.take_unsent()
    assert node.historical(0, kept, T0 + 5) is None  # not online: nothing, no seq taken
    births = go_online(node, T0 + 10)
    assert [decode(m.payload).seq for m in births] == [0, 1]  # NBIRTH, DBIRTH press
    replay = node.historical(0, kept, T0 + 20)
    assert replay is not None and replay.topic == "spBv1.0/plant1/DDATA/gw1/press" and replay.qos == 0
    payload = decode(replay.payload)
    assert payload.seq == 2 and payload.timestamp == T0 + 20
    assert [(m.alias, m.timestamp, m.is_historical) for m in payload.metrics] == [
        (2, T0, True), (2, T0 + 1, True), (2, T0 + 2, True), (3, T0 + 3, True)]
    assert [m.value for m in payload.metrics][1:] == [0, 1, 2.5]
    assert payload.metrics[0].value == 0xFFFFFFFF  # -1 as an Int16 (two's complement, the guide's reading 3)
    # live DDATA after it: the next seq, not historical
    observe(node, 0, 0, 9, T0 + 30)
    (live,) = node.flush(T0 + 30)
    assert decode(live.payload).seq == 3 and not decode(live.payload).metrics[0].is_historical


def test_replay_waits_for_the_births_and_skips_a_dead_device() -> None:
    node = make_node()
    node.link(0, True, T0)
    node.link(1, True, T0)
    node.connecting(T0)
    node.connected(T0)  # NBIRTH out, DBIRTHs under way
    change = Change("oven", "B3:0/0", T0, True, 192)
    assert node.historical(1, [change], T0) is None
    while node.next_birth(T0) is not None:
        pass
    node.link(1, False, T0 + 1)  # DDEATH
    assert node.historical(1, [change], T0 + 2) is None
    assert node.historical(0, [Change("press", "N7:0", T0, 1, 192)], T0 + 2) is not None


def test_a_change_of_a_metric_the_node_no_longer_has_is_counted_not_sent() -> None:
    node = make_node()
    node.link(0, True, T0)
    go_online(node, T0)
    assert node.historical(0, [Change("press", "N7:99", T0, 1, 192)], T0) is None
    assert node.unknown_history == 1


def test_replayed_changes_are_in_the_window_too() -> None:
    node = make_node()
    node.link(0, True, T0)
    go_online(node, T0)
    change = Change("press", "N7:0", T0 - 5_000, 4, 192)
    assert node.historical(0, [change], T0 + 1_000) is not None
    node.disconnected(T0 + 2_000)
    assert node.take_unsent() == [change]


def test_seq_wraps_across_live_and_historical_ddata() -> None:
    node = make_node()
    node.link(0, True, T0)
    go_online(node, T0)  # seq 0, 1
    seqs = []
    for k in range(300):
        if k % 2:
            message = node.historical(0, [Change("press", "N7:0", T0 - k, k, 192)], T0 + k)
        else:
            observe(node, 0, 0, k, T0 + k)
            (message,) = node.flush(T0 + k)
        assert message is not None
        seqs.append(decode(message.payload).seq)
    assert seqs == [(2 + k) % 256 for k in range(300)]


def test_a_null_is_kept_and_replayed_with_its_quality() -> None:
    node = make_node()
    node.link(0, True, T0)
    node.observe(0, 0, Sample(None, T0, STALE, "press: no fresh data"))
    node.flush(T0)
    kept = node.take_unsent()
    go_online(node, T0 + 10)
    replay = node.historical(0, kept, T0 + 20)
    assert replay is not None
    (metric,) = decode(replay.payload).metrics
    assert metric.is_null and metric.is_historical and metric.properties is not None
    assert metric.properties["Quality"][1] == STALE


def test_window_forgets_what_is_older_than_its_span() -> None:
    window = Window(1_000)
    a, b = Change("d", "m", 1, 1, 192), Change("d", "m", 2, 2, 192)
    window.add(0, [a])
    window.add(1_500, [b])  # a is older than the span now
    assert len(window) == 1
    assert window.lost(2_000) == [b]
    assert window.lost(2_000) == []


def test_stored_samples_round_trip_every_kind_of_value() -> None:
    for value in (0, -5, 2**31, 1.5, math.inf, -math.inf, True, False, "text", b"\x00\xff", None):
        change = Change("d", "m", 1, value, 500 if value is None else 192, "why" if value is None else "")
        assert sample_value(sample_text(change)) == (value, change.quality, change.reason)
    got = sample_value(sample_text(Change("d", "m", 1, math.nan, 192)))[0]
    assert isinstance(got, float) and math.isnan(got)


def test_window_holds_what_was_published_exactly_its_span_ago() -> None:
    """"The changes published in the last ``span`` ms": one published exactly ``span`` ms before is in doubt."""
    window = Window(1_000)
    a, b = Change("d", "m", 1, 1, 192), Change("d", "m", 2, 2, 192)
    window.add(0, [a])
    window.add(1_000, [b])
    assert len(window) == 2
    assert window.lost(1_000) == [a, b]
    window.add(0, [a])
    assert window.lost(1_001) == []


def test_stored_samples_are_standard_json() -> None:
    """NaN and the infinities are kept as strings: the store's text is JSON any reader takes."""
    def refuse(constant: str) -> object:
        raise AssertionError(f"{constant} is not JSON")

    for value in (math.nan, math.inf, -math.inf, 1.5):
        text = sample_text(Change("d", "m", 1, value, 192))
        assert json.loads(text, parse_constant=refuse)[1:] == [192, ""]
    assert json.loads(sample_text(Change("d", "m", 1, 1.5, 192)))[0] == 1.5  # a finite float as itself
