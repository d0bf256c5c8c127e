"""The edge node's session rules, sans-I/O: what to publish, with which ``seq`` and ``bdSeq``, and when.

No MQTT, no clock, no asyncio: the driver (``gateway.sparkplug.driver``) passes the time in (``now``:
UTC milliseconds), feeds values and commands in, and publishes the :class:`Publish` records that come
out, in order.  Section numbers are those of the Eclipse Sparkplug 3.0.0 specification.

Session (§5.4 "Edge Node Session Establishment", §5.5 "Edge Node Session Termination"):

* :meth:`EdgeNode.connecting` is called before every MQTT CONNECT: it increments ``bdSeq`` (0..255,
  255 wraps to 0; §6.4.25 "NDEATH", tck-id-topics-nbirth-bdseq-increment) and returns the NDEATH
  to register as the will (QoS 1, not retained; the only metric is ``bdSeq``, Int64, no ``seq``).
  The driver keeps ``bdSeq`` on disk so a restarted process goes on counting.
* :meth:`EdgeNode.connected`: without a primary host, the births at once; with one, nothing until
  that host's STATE says online (§5.4 tck-id-message-flow-edge-node-birth-publish-phid-wait).
* Births: NBIRTH with ``seq`` 0 (§4.2.1.1.2 tck-id-topics-nbirth-seq-num), ``bdSeq`` equal to the
  will's, and ``Node Control/Rebirth`` = false without an alias (§5.17 "Commands"); then a DBIRTH
  per device whose link is up (:meth:`EdgeNode.next_birth`, one at a time, so the driver can let
  the Modbus server answer in between; no DDATA until the last, §6.4.20), each with every metric:
  name, alias, datatype, timestamp, value or ``is_null`` (§5.16 "Data Publish"; §6.4.20 "DBIRTH").
  ``seq`` then goes up by one per message up to 255 and wraps to 0 (§6.4.5 "Payload",
  tck-id-payloads-sequence-num-incrementing).
* A rebirth request (NCMD ``Node Control/Rebirth`` = true) stops data and publishes every birth
  again with the same ``bdSeq`` (§5.17).
* A primary host's offline STATE whose timestamp is not older than the last online one: NDEATH,
  then disconnect (the driver reconnects: a new session, a new ``bdSeq``) (§5.5,
  tck-id-operational-behavior-edge-node-termination-host-offline).

Data (§5.16 "Data Publish", §6.4.22 "DDATA"): each device's DDATA carries the metrics whose value
or quality changed since they were last published (past the metric's deadband), by alias only
(§6.4.6 tck-id-payloads-alias-data-cmd-requirement), in chronological order.  A value that is not
good is published as ``is_null`` with the ``Quality`` property (§6.4.9.1 "Quality Codes": 500 STALE,
0 BAD) and a ``Quality Reason`` string property saying why; the first good value after that carries
``Quality`` 192 (GOOD).  A device whose link goes down gets a DDEATH (§5.7 "Device Session
Termination", tck-id-operational-behavior-device-ddeath); when it comes back, a DBIRTH.

Store and forward (``store``; ``gateway.sparkplug.history``): while the node is not online (no MQTT
session, or its births not out yet), :meth:`EdgeNode.flush` records each live device's changes as
changes (:class:`~gateway.sparkplug.history.Change`) in :attr:`EdgeNode.unsent` instead of publishing them (the
caller stores them); the changes published in the last ``window`` ms are added to them when the
connection is found lost (:meth:`EdgeNode.disconnected`: QoS 0 DDATA handed to the client may be
gone).  Online again, after the NBIRTH and every DBIRTH with the current values,
:meth:`EdgeNode.historical` turns stored changes into DDATA whose metrics carry ``is_historical`` and
their original timestamps (§6.4.6), with the session's ``seq`` (§6.4.22 tck-id-payloads-ddata-seq-inc).
"""

from __future__ import annotations

import json
import math
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Final

from gateway.frozen import frozen
from gateway.sparkplug.history import Change, Window
from gateway.sparkplug.payload import (
    GOOD,
    STALE,
    Metric,
    Payload,
    PayloadError,
    SparkplugType,
    Value,
    decode,
    encode,
    typed,
)

__all__ = [
    "GOOD",
    "NAMESPACE",
    "REBIRTH",
    "STALE",
    "Device",
    "EdgeNode",
    "MetricSpec",
    "Publish",
    "Sample",
    "WriteCommand",
]

#: the topic namespace of Sparkplug B (§4.1.1 "namespace Element")
NAMESPACE: Final = "spBv1.0"
#: the one node command every edge node serves (§5.17 "Commands")
REBIRTH: Final = "Node Control/Rebirth"
BD_SEQ: Final = "bdSeq"
#: the alias of bdSeq in NBIRTH; device metrics are numbered after it (unique across the node, §6.4.6)
BD_SEQ_ALIAS: Final = 1
#: the properties of a metric that is not good (§6.4.8 "PropertySet", §6.4.9.1 "Quality Codes")
QUALITY: Final = "Quality"
QUALITY_REASON: Final = "Quality Reason"


@frozen
class Publish:
    """One MQTT message to publish, in order."""

    topic: str
    payload: bytes
    qos: int = 0
    retain: bool = False


@frozen
class MetricSpec:
    """One metric of a device, as its DBIRTH defines it."""

    name: str
    alias: int
    datatype: SparkplugType
    writable: bool = False
    #: a change no larger than this (absolute) is not published (0: every change)
    deadband: float = 0.0


@frozen
class Sample:
    """A metric's value at ``timestamp`` (UTC ms); ``value`` None: not good, ``quality`` and ``reason`` say why."""

    value: Value | None
    timestamp: int
    quality: int = GOOD
    reason: str = ""


@frozen
class WriteCommand:
    """A write a DCMD asks for: ``value`` (of the metric's datatype) to metric ``metric`` of device ``device``."""

    device: int
    metric: int
    value: Value


@dataclass
class Device:
    """A device (one link) and what the node knows and last published of each of its metrics."""

    name: str
    specs: Sequence[MetricSpec]
    #: the link is up (a device whose link is down is dead: no DBIRTH, no DDATA)
    alive: bool = False
    #: a DBIRTH was published in this session (and no DDEATH since)
    born: bool = False
    current: list[Sample | None] = field(init=False)
    published: list[Sample | None] = field(init=False)
    #: metrics observed since the last flush (only these can have changed)
    pending: set[int] = field(default_factory=set)
    #: metrics to publish at the next flush even if unchanged (a DCMD's outcome)
    forced: set[int] = field(default_factory=set)
    by_alias: dict[int, int] = field(init=False)
    by_name: dict[str, int] = field(init=False)

    def __post_init__(self) -> None:
        self.current = [None] * len(self.specs)
        self.published = [None] * len(self.specs)
        self.by_alias = {spec.alias: i for i, spec in enumerate(self.specs)}
        self.by_name = {spec.name: i for i, spec in enumerate(self.specs)}


def _changed(spec: MetricSpec, new: Sample, old: Sample | None) -> bool:
    if old is None or new.quality != old.quality or (new.value is None) != (old.value is None):
        return True
    if new.value is None or old.value is None:
        return new.reason != old.reason
    a, b = new.value, old.value
    if isinstance(a, float) and isinstance(b, float) and (math.isnan(a) or math.isnan(b)):
        # NaN equals nothing, and is within no deadband of anything: changed unless both are NaN
        return math.isnan(a) != math.isnan(b)
    if spec.deadband > 0 and isinstance(a, int | float) and isinstance(b, int | float) and not isinstance(a, bool):
        return abs(a - b) > spec.deadband
    return a != b


class EdgeNode:
    """The edge node's session, sequence and birth / death rules (the module docstring)."""

    def __init__(self, group_id: str, edge_node_id: str, devices: Sequence[Device], *,
                 primary_host_id: str | None = None, bd_seq: int | None = None, store: bool = False,
                 window: int = 45_000) -> None:
        self.group_id = group_id
        self.edge_node_id = edge_node_id
        self.devices = list(devices)
        self.by_device = {device.name: i for i, device in enumerate(self.devices)}
        self.primary_host_id = primary_host_id
        #: the bdSeq of the last (or current) MQTT session; None before the first
        self.bd_seq = bd_seq
        #: an MQTT session is up
        self.connected_now = False
        #: the births of this session are out (data may flow)
        self.online = False
        #: the primary host is online (always True without one)
        self.host_online = primary_host_id is None
        #: the timestamp of the last online STATE of the primary host (None: none seen)
        self.host_timestamp: int | None = None
        self._seq = 0
        #: the live devices still waiting for their DBIRTH in this birth sequence (no DDATA meanwhile)
        self.unborn: list[int] = []
        #: commands received, by verb (NCMD, DCMD, STATE)
        self.received: Counter[str] = Counter()
        #: commands that changed nothing, by reason
        self.refused: Counter[str] = Counter()
        #: store and forward: record what cannot be published (module docstring)
        self.storing = store
        #: changes not published, for the store (the caller takes them: :meth:`take_unsent`)
        self.unsent: list[Change] = []
        #: the changes published in the last ``window`` ms (2 x keepalive + 2 s): in doubt when the connection is lost
        self.window = Window(window)
        #: stored changes of metrics this node does not have (a store written before a config change)
        self.unknown_history = 0

    # --- topics ------------------------------------------------------------------------------

    def topic(self, verb: str, device: str | None = None) -> str:
        """``spBv1.0/group_id/VERB/edge_node_id[/device_id]`` (§4.1 "Topic Namespace Elements")."""
        base = f"{NAMESPACE}/{self.group_id}/{verb}/{self.edge_node_id}"
        return base if device is None else f"{base}/{device}"

    def subscriptions(self) -> list[tuple[str, int]]:
        """Topics to subscribe before NBIRTH, QoS 1: NCMD (§5.4 tck-id-message-flow-edge-node-ncmd-subscribe),
        every device's DCMD (§5.6 tck-id-message-flow-device-dcmd-subscribe) and the primary host's STATE."""
        topics = [(self.topic("NCMD"), 1), (self.topic("DCMD", "+"), 1)]
        if self.primary_host_id is not None:
            topics.append((self.state_topic, 1))
        return topics

    @property
    def state_topic(self) -> str:
        """``spBv1.0/STATE/<primary_host_id>`` (§4.2.3 "Sparkplug Host Application")."""
        return f"{NAMESPACE}/STATE/{self.primary_host_id}"

    # --- session -----------------------------------------------------------------------------

    def _bd_seq_metric(self, now: int, alias: int | None) -> Metric:
        return Metric(name=BD_SEQ, alias=alias, timestamp=now, datatype=SparkplugType.Int64, value=self.bd_seq or 0)

    def connecting(self, now: int) -> Publish:
        """Before an MQTT CONNECT: the next ``bdSeq`` and the NDEATH will that carries it (§5.4, §6.4.25)."""
        self.bd_seq = 0 if self.bd_seq is None else (self.bd_seq + 1) % 256
        return self._ndeath(now)

    def _ndeath(self, now: int) -> Publish:
        # NDEATH: only bdSeq, no seq (§4.2.1.3 tck-id-topics-ndeath-payload, tck-id-topics-ndeath-seq);
        # will QoS 1, retain false (§5.4 tck-id-message-flow-edge-node-birth-publish-will-message-qos)
        payload = Payload(timestamp=now, metrics=(self._bd_seq_metric(now, None),))
        return Publish(self.topic("NDEATH"), encode(payload), qos=1)

    def connected(self, now: int) -> list[Publish]:
        """The MQTT session is up and subscribed: the births, unless a primary host must be online first."""
        self.connected_now = True
        self.online = False
        self.host_online = self.primary_host_id is None
        for device in self.devices:
            device.born = False
        return self.births(now) if self.host_online else []

    def disconnected(self, now: int | None = None) -> None:
        """The MQTT session is gone (the broker publishes the will), found lost at ``now``: what was published in
        the window before it is in doubt and goes to :attr:`unsent` (with ``store``).  None: ended cleanly."""
        if now is not None and self.storing:
            self.unsent.extend(self.window.lost(now))
        self.window.clear()
        self.connected_now = False
        self.online = False
        self.unborn = []
        for device in self.devices:
            device.born = False

    def stopping(self, now: int) -> list[Publish]:
        """An intentional disconnect: NDEATH first (§5.5 tck-id-operational-behavior-edge-node-intentional-
        disconnect-ndeath), with this session's bdSeq.  None before the births: there is no Sparkplug
        session to end (the reading of :meth:`host_state`), and the clean DISCONNECT withdraws the will."""
        if not self.connected_now or not self.online:
            return []
        self.online = False
        self.unborn = []
        self.window.clear()  # the DISCONNECT follows what was published: nothing in doubt
        return [self._ndeath(now)]

    def _next_seq(self) -> int:
        seq = self._seq
        self._seq = (seq + 1) % 256
        return seq

    def births(self, now: int) -> list[Publish]:
        """The NBIRTH (seq 0); then :meth:`next_birth` gives a DBIRTH per live device, one at a time
        (§5.4, §5.6, §6.4.19, §6.4.20).  No DDATA until the last (§6.4.20: the DBIRTHs come right
        after the NBIRTH, before any DDATA)."""
        self.online = True
        self._seq = 0
        metrics = (
            self._bd_seq_metric(now, BD_SEQ_ALIAS),
            Metric(name=REBIRTH, timestamp=now, datatype=SparkplugType.Boolean, value=False),
        )
        for device in self.devices:
            device.born = False
        self.unborn = [index for index, device in enumerate(self.devices) if device.alive]
        return [Publish(self.topic("NBIRTH"), encode(Payload(now, metrics, self._next_seq())))]

    def next_birth(self, now: int) -> Publish | None:
        """The DBIRTH of the next live device of the birth sequence; None when it is complete."""
        while self.unborn:
            index = self.unborn.pop(0)
            if self.devices[index].alive:
                return self._dbirth(index, now)
        return None

    def _dbirth(self, index: int, now: int) -> Publish:
        device = self.devices[index]
        metrics: list[Metric] = []
        for i, spec in enumerate(device.specs):
            sample = device.current[i] or Sample(None, now, STALE, "not read yet")
            metrics.append(_metric(spec, sample, birth=True))
            device.published[i] = sample
        device.forced.clear()
        device.pending.clear()
        device.born = True
        metrics.sort(key=lambda m: m.timestamp or 0)  # chronological (§5.16)
        payload = Payload(now, tuple(metrics), self._next_seq())
        return Publish(self.topic("DBIRTH", device.name), encode(payload))

    # --- the primary host's STATE ------------------------------------------------------------------

    def host_state(self, payload: bytes, now: int) -> tuple[list[Publish], bool]:
        """A STATE message of the primary host: (messages, disconnect).

        Online (timestamp not older than the last online one): births, if not online yet.  Offline
        and not older, after the births: NDEATH and disconnect (§5.4 tck-id-message-flow-edge-node-
        birth-publish-phid-*, §5.5 tck-id-operational-behavior-edge-node-termination-host-offline
        [-timestamp]); before them, keep waiting.
        """
        self.received["STATE"] += 1
        try:
            state = json.loads(payload.decode("utf-8"))
            online, timestamp = state["online"], state["timestamp"]
            if not isinstance(online, bool) or not isinstance(timestamp, int) or isinstance(timestamp, bool):
                raise TypeError("online must be a boolean and timestamp an integer")
        except (ValueError, KeyError, TypeError, UnicodeDecodeError):
            self.refused["bad STATE payload"] += 1
            return [], False
        if self.host_timestamp is not None and timestamp < self.host_timestamp:
            self.refused["old STATE"] += 1
            return [], False
        if online:
            self.host_timestamp = timestamp
            self.host_online = True
            if self.connected_now and not self.online:
                return self.births(now), False
            return [], False
        self.host_online = False
        if not self.online:
            # No births out yet: there is no Sparkplug session to end (§5.16 "A Sparkplug session
            # begins with an MQTT CONNECT and then the NBIRTH"); stay connected and wait.  A retained
            # offline STATE would otherwise make every new connection end at once.
            return [], False
        return self.stopping(now), True

    # --- commands ------------------------------------------------------------------------------

    def node_command(self, payload: bytes, now: int) -> list[Publish]:
        """An NCMD: ``Node Control/Rebirth`` = true publishes every birth again (§5.17); anything else is refused."""
        self.received["NCMD"] += 1
        try:
            metrics = decode(payload).metrics
        except PayloadError:
            self.refused["bad payload"] += 1
            return []
        rebirth = False
        for metric in metrics:
            if metric.name == REBIRTH and metric.value is True:
                rebirth = True
            else:
                self.refused["unknown node metric"] += 1
        if rebirth and self.connected_now and self.host_online:
            return self.births(now)
        return []

    def device_command(self, device_name: str, payload: bytes) -> list[WriteCommand]:
        """A DCMD to ``device_name``: the writes it asks for; the rest is counted in :attr:`refused`.

        A metric is found by alias, else by name (§5.17: the node is resilient to names that were
        not in the DBIRTH).  Refused, changing nothing: an unknown device or metric, a read-only
        metric, a null or a value of another kind than the metric's datatype.
        """
        self.received["DCMD"] += 1
        index = self.by_device.get(device_name)
        if index is None:
            self.refused["unknown device"] += 1
            return []
        device = self.devices[index]
        try:
            metrics = decode(payload).metrics
        except PayloadError:
            self.refused["bad payload"] += 1
            return []
        commands: list[WriteCommand] = []
        for metric in metrics:
            i = device.by_alias.get(metric.alias) if metric.alias is not None else None
            if i is None and metric.name is not None:
                i = device.by_name.get(metric.name)
            if i is None:
                self.refused["unknown metric"] += 1
                continue
            spec = device.specs[i]
            if not spec.writable:
                self.refused["read-only metric"] += 1
                continue
            if metric.is_null or metric.value is None:
                self.refused["no value"] += 1
                continue
            try:
                value = typed(spec.datatype, metric.value)
            except PayloadError:
                self.refused["wrong value type"] += 1
                continue
            commands.append(WriteCommand(index, i, value))
        return commands

    def force(self, device: int, metric: int) -> None:
        """Publish this metric at the next flush even if unchanged (the outcome of a DCMD)."""
        self.devices[device].forced.add(metric)

    # --- data ------------------------------------------------------------------------------------

    def observe(self, device: int, metric: int, sample: Sample) -> None:
        """The metric's value now (published at the next :meth:`flush` if it changed)."""
        target = self.devices[device]
        target.current[metric] = sample
        target.pending.add(metric)

    def link(self, index: int, up: bool, now: int) -> list[Publish]:
        """The device's link went up (DBIRTH, if the node is online) or down (DDEATH, if born)."""
        device = self.devices[index]
        if device.alive == up:
            return []
        device.alive = up
        if not self.online:
            return []
        if up:
            if self.unborn:  # a birth sequence is under way: it takes this device too
                self.unborn.append(index)
                return []
            return [self._dbirth(index, now)]
        if not device.born:
            return []
        device.born = False
        # DDEATH: timestamp and seq, no metrics (§6.4.26 "DDEATH")
        payload = Payload(now, (), self._next_seq())
        return [Publish(self.topic("DDEATH", device.name), encode(payload))]

    def flush(self, now: int, devices: Sequence[int] | None = None) -> list[Publish]:
        """DDATA of every born device (of ``devices``) with the metrics changed since last published; not
        online, with ``store``: those changes into :attr:`unsent`."""
        if not self.online:
            if self.storing:
                self._keep(devices)
            return []
        if self.unborn:  # the DBIRTHs under way carry the values as they are then
            return []
        out: list[Publish] = []
        published: list[Change] = []
        for index in range(len(self.devices)) if devices is None else devices:
            device = self.devices[index]
            if not device.born:
                continue
            changed: list[Metric] = []
            for i in sorted(device.pending | device.forced):
                spec, sample, old = device.specs[i], device.current[i], device.published[i]
                if sample is None:
                    continue
                if i in device.forced or _changed(spec, sample, old):
                    recovered = old is not None and old.value is None and sample.value is not None
                    changed.append(_metric(spec, sample, birth=False, recovered=recovered))
                    device.published[i] = sample
                    published.append(_change(device.name, spec, sample))
            device.forced.clear()
            device.pending.clear()
            if changed:
                changed.sort(key=lambda m: m.timestamp or 0)  # chronological (§5.16)
                payload = Payload(now, tuple(changed), self._next_seq())
                out.append(Publish(self.topic("DDATA", device.name), encode(payload)))
        if self.storing:
            self.window.add(now, published)
        return out

    def _keep(self, devices: Sequence[int] | None) -> None:
        """Offline: each live device's changes since last published (or kept) into :attr:`unsent`."""
        for index in range(len(self.devices)) if devices is None else devices:
            device = self.devices[index]
            if not device.alive:
                continue
            for i in sorted(device.pending | device.forced):
                spec, sample = device.specs[i], device.current[i]
                if sample is not None and (i in device.forced or _changed(spec, sample, device.published[i])):
                    self.unsent.append(_change(device.name, spec, sample))
                    device.published[i] = sample
            device.forced.clear()
            device.pending.clear()

    def take_unsent(self) -> list[Change]:
        """The changes recorded for the store since the last call."""
        out, self.unsent = self.unsent, []
        return out

    def historical(self, index: int, changes: Sequence[Change], now: int) -> Publish | None:
        """Stored changes of device ``index`` as one DDATA: ``is_historical`` metrics with their original
        timestamps, in the order given (oldest first), the next ``seq``.  None when the device cannot take
        data now (node not online, births under way, device not born) or no change names one of its metrics
        (counted in :attr:`unknown_history`)."""
        device = self.devices[index]
        if not self.online or self.unborn or not device.born:
            return None
        metrics: list[Metric] = []
        for change in changes:
            i = device.by_name.get(change.metric)
            if i is None:
                self.unknown_history += 1
                continue
            sample = Sample(change.value, change.timestamp, change.quality, change.reason)
            metrics.append(_metric(device.specs[i], sample, birth=False, historical=True))
        if not metrics:
            return None
        self.window.add(now, changes)
        payload = Payload(now, tuple(metrics), self._next_seq())
        return Publish(self.topic("DDATA", device.name), encode(payload))


def _change(device: str, spec: MetricSpec, sample: Sample) -> Change:
    return Change(device, spec.name, sample.timestamp, sample.value, sample.quality, sample.reason)


def _metric(spec: MetricSpec, sample: Sample, *, birth: bool, recovered: bool = False,
            historical: bool = False) -> Metric:
    """A metric of a DBIRTH (name, alias, datatype) or of a DDATA (alias only)."""
    properties: Mapping[str, tuple[int, Value]] | None = None
    if sample.value is None:
        properties = {QUALITY: (SparkplugType.Int32, sample.quality),
                      QUALITY_REASON: (SparkplugType.String, sample.reason or "no value")}
    elif recovered:
        properties = {QUALITY: (SparkplugType.Int32, GOOD)}
    return Metric(
        name=spec.name if birth else None,
        alias=spec.alias,
        timestamp=sample.timestamp,
        datatype=spec.datatype if birth else None,  # not in DATA messages (§6.4.6)
        value=sample.value,
        value_type=spec.datatype,
        is_null=sample.value is None,
        properties=properties,
        is_historical=historical,
    )

