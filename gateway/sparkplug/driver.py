"""The edge node on MQTT (aiomqtt): a thin loop around :class:`gateway.sparkplug.node.EdgeNode`.

* Connects with the NDEATH as will (MQTT 3.1.1, clean session, §5.4), subscribes, and publishes
  what the core returns, in order, from one outbox (so ``seq`` goes out in order).  Reconnects
  with a backoff doubling from ``reconnect_min`` to ``reconnect_max``; each connect is a new
  ``bdSeq``, written to ``state_file`` before the CONNECT (so a restarted process goes on from it).
* Values: each unit's cache tells the node of every store and patch (``BlockCache.listeners``);
  ``batch_interval`` later (the other blocks of the poll cycle) the node reads the metrics of
  those blocks as a Modbus read would (``LinkDevice.read``), with the block's read time as their
  timestamp, and the core publishes the changed ones, one DDATA per device.  Every
  ``check_interval`` it also looks at what ages without a store: links up / down, blocks going
  stale; every ``status_interval``, the status block's values.
* DCMD writes go through :meth:`Unit.write_registers` / :meth:`Unit.write_bits`: the same checks
  (``read_only``, ``writable``), queue (in arrival order, at most ``write_queue_per_client`` waiting:
  beyond, refused as busy), ``write_timeout`` and at-most-once rule as a Modbus write request.
  Whatever the outcome, the metric is published again with the value the image holds (confirmed,
  or the controller's).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import os
import struct
import time
from collections import Counter
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any, Final

import aiomqtt

from gateway.clients import Client, audit_write, current_client
from gateway.config.link import LinkBase
from gateway.config.sparkplug import SparkplugConfig
from gateway.errors import ModbusExceptionReply
from gateway.sparkplug.devices import LinkDevice, build_devices
from gateway.sparkplug.forward import Forwarder
from gateway.sparkplug.mqtt import MQTT_TIMEOUT, Busy, MqttClient
from gateway.sparkplug.node import EdgeNode, Publish, WriteCommand
from gateway.sparkplug.payload import SparkplugType
from gateway.sparkplug.store import ChangeStore, store_path
from gateway.unit import Unit

__all__ = ["SparkplugNode", "load_bd_seq", "save_bd_seq", "window_ms"]

log = logging.getLogger("gateway.sparkplug")

#: messages handed to the MQTT client at once, at most: paho writes them in one loop step (40-60 µs of
#: CPU each on the 2-core bench machine), so this bounds that step; a birth sequence queues one per device
_BATCH: Final = 4


def window_ms(keepalive: int) -> int:
    """How long published DDATA stays in doubt (ms): the time paho takes to find a silent connection lost.

    The issue asked for 1.5 x keepalive, the broker's limit (MQTT 3.1.1 §3.1.2.10).  The client finds the loss
    later: it sends PINGREQ after ``keepalive`` without a packet from the broker and gives up ``keepalive``
    after that, checked once a second, so up to 2 x keepalive + 1 s after the last packet received, which
    can be any time before the cut (measured: tests/e2e/test_sparkplug_store_silent.py)."""
    return (2 * keepalive + 2) * 1000


def load_bd_seq(path: Path) -> int | None:
    """The bdSeq of the last session kept in ``path`` (None: no file, or not one we wrote)."""
    try:
        value = json.loads(path.read_text(encoding="utf-8"))["bdSeq"]
    except FileNotFoundError:
        return None
    except (OSError, ValueError, KeyError, TypeError) as exc:
        log.warning("sparkplug: %s is not a bdSeq state file (%s): starting bdSeq at 0", path, exc)
        return None
    return value if isinstance(value, int) and 0 <= value <= 255 else None


def save_bd_seq(path: Path, bd_seq: int) -> None:
    """Keep ``bd_seq`` in ``path`` (written to a temporary file, synced, then renamed over it)."""
    temporary = path.with_name(path.name + ".tmp")
    with open(temporary, "w", encoding="utf-8") as out:
        out.write(json.dumps({"bdSeq": bd_seq}) + "\n")
        out.flush()
        os.fsync(out.fileno())
    os.replace(temporary, path)


class _HostOffline(Exception):
    """The primary host went offline: this session ends (§5.5)."""


class SparkplugNode:
    """The gateway as a Sparkplug edge node (``[sparkplug]``); ``run()`` until cancelled."""

    def __init__(self, config: SparkplugConfig, links: Sequence[LinkBase], units: Sequence[Unit[Any, Any]]) -> None:
        self.config = config
        self.devices: list[LinkDevice] = build_devices(links, units, demand=config.demand)
        self.core = EdgeNode(config.group_id, config.edge_node_id, [d.device for d in self.devices],
                             primary_host_id=config.primary_host_id, bd_seq=load_bd_seq(config.state_file),
                             store=config.store, window=window_ms(config.keepalive))
        #: store and forward (``[sparkplug] store``): the unsent changes on disk and their replay
        self.forward = Forwarder(
            self.core, ChangeStore(store_path(config.state_file), max_bytes=int(config.store_max_mb * 1e6),
                                   max_age=int(config.store_max_age * 1000)),
            replay_rate=config.replay_rate, now_ms=self._now_ms) if config.store else None
        #: DCMD writes the controller refused or that failed (also counted in ``core.refused``)
        self.write_failures = 0
        #: messages handed to the broker, by message type (NBIRTH, DDATA, ...)
        self.sent: Counter[str] = Counter()
        #: CPU of the node's own steps on the loop (reading the image, building DDATA)
        self.busy = Busy()
        #: MQTT sessions established
        self.sessions = 0
        self._client: aiomqtt.Client | None = None
        self._outbox: asyncio.Queue[Publish] = asyncio.Queue()
        #: set while no pass of the node (over the devices, a step each) is under way: the sender waits
        #: for it, so a pass's messages go to the MQTT client together
        self._idle = asyncio.Event()
        self._idle.set()
        self._passes = 0
        self._wake = asyncio.Event()
        #: per device: blocks stored or patched since the last pass, with their read time (None: a patch)
        self._dirty: list[dict[int, float | None]] = [{} for _ in self.devices]
        #: DCMD writes under way (each a task, as each Modbus write request is)
        self._writing: set[asyncio.Task[None]] = set()
        self._who = Client(f"sparkplug DCMD via {config.broker}")
        self._offset = 0.0  # wall seconds - loop seconds
        self._loop: asyncio.AbstractEventLoop | None = None  # set by run(): the connect thread calls into it
        self._state_error = False  # the state file could not be written (logged once)
        #: per device: the listener this node added to its unit's cache (removed by :meth:`detach`)
        self._listeners = [self._listener(index) for index in range(len(self.devices))]
        for device, listener in zip(self.devices, self._listeners, strict=True):
            device.unit.cache.listeners.append(listener)

    @property
    def session_state(self) -> str:
        """``disconnected``, ``connected`` (waiting for the primary host) or ``online`` (births published)."""
        if not self.core.connected_now:
            return "disconnected"
        return "online" if self.core.online else "connected"

    def _listener(self, index: int) -> Any:
        dirty = self._dirty[index]
        wake = self._wake

        def stored(block: int, now: float | None) -> None:
            dirty[block] = now
            wake.set()

        return stored

    # --- time --------------------------------------------------------------------------------

    def _now_ms(self) -> int:
        return int(time.time() * 1000)

    def _wall_ms(self, loop_time: float) -> int:
        """A loop time as UTC milliseconds."""
        return int((loop_time + self._offset) * 1000)

    # --- the session -------------------------------------------------------------------------

    async def run(self) -> None:
        loop = asyncio.get_running_loop()
        self._loop = loop
        self._offset = time.time() - loop.time()
        delay = self.config.reconnect_min
        current_client.set(self._who)  # the DCMD writes' client, for the write queue and the audit log
        async with asyncio.TaskGroup() as group:  # for the life of the node: values are watched (and stored) offline
            if self.forward is not None:
                await self.forward.open()
                group.create_task(self.forward.keep())
            group.create_task(self._watch())
            await self._sessions(delay)

    async def _sessions(self, delay: float) -> None:
        down_logged = False
        while True:
            sessions = self.sessions
            lost: int | None = None  # when a session that was up was found lost (its window is in doubt)
            try:
                await self._session()
            except aiomqtt.MqttError as exc:
                if self.sessions > sessions:  # it was up: lost (logged once, then retried quietly)
                    lost = self._now_ms()
                    log.warning("sparkplug: MQTT session with %s lost (%s); reconnecting", self.config.broker, exc)
                    delay, down_logged = self.config.reconnect_min, False
                elif not down_logged:
                    log.warning("sparkplug: cannot connect to %s (%s); retrying every %g s, backing off to %g s",
                                self.config.broker, exc, self.config.reconnect_min, self.config.reconnect_max)
                    down_logged = True
            except _HostOffline:
                log.info("sparkplug: primary host %s went offline: NDEATH published, reconnecting",
                         self.config.primary_host_id)
                delay = self.config.reconnect_min
            self.core.disconnected(lost)
            await asyncio.sleep(delay)
            if self.sessions == sessions:
                delay = min(self.config.reconnect_max, delay * 2)

    def _connect_packet_will(self) -> Publish:
        """In the MQTT client's connect thread, once the TCP (and TLS) connection is up and its CONNECT is being
        made: the next ``bdSeq`` and its NDEATH, the CONNECT's will.  Sparkplug 3.0 §5.4 / §6.4.25
        (tck-id-topics-nbirth-bdseq-increment) counts MQTT CONNECT packets: an attempt refused before
        its CONNECT takes none.  ``bdSeq`` is kept in ``state_file`` before the CONNECT leaves (fsync here, in
        the thread: the event loop answers meanwhile)."""
        if self._loop is None:
            raise OSError("the edge node is not running")
        future = asyncio.run_coroutine_threadsafe(self._next_will(), self._loop)
        try:
            will = future.result(MQTT_TIMEOUT)
        except TimeoutError:
            future.cancel()
            raise OSError("the event loop did not take the next bdSeq in time") from None
        bd_seq = self.core.bd_seq or 0
        try:
            save_bd_seq(self.config.state_file, bd_seq)
            self._state_error = False
        except OSError as exc:
            if not self._state_error:
                self._state_error = True
                log.error("sparkplug: cannot keep bdSeq in %s (%s): a restart would reuse bdSeq %d; make its "
                          "directory writable or set [sparkplug] state_file", self.config.state_file, exc, bd_seq)
        return will

    async def _next_will(self) -> Publish:
        return self.core.connecting(self._now_ms())

    async def _session(self) -> None:
        config = self.config
        host, port = config.address
        client = MqttClient(
            host, port, will_of_connect=self._connect_packet_will,
            identifier=config.client_id or f"slc-gateway-{config.group_id}-{config.edge_node_id}",
            username=config.username, password=config.password,
            clean_session=True, keepalive=config.keepalive, protocol=aiomqtt.ProtocolVersion.V311,
            tls_context=config.ssl_context(), timeout=MQTT_TIMEOUT,
        )
        async with client:
            self._client = client
            self.sessions += 1
            try:
                for topic, qos in self.core.subscriptions():
                    await client.subscribe(topic, qos)
                log.info("sparkplug: connected to %s as %s/%s (bdSeq %d)%s", config.broker, config.group_id,
                         config.edge_node_id, self.core.bd_seq or 0,
                         f", waiting for primary host {config.primary_host_id}" if config.primary_host_id else "")
                self._drain_outbox()
                await self._links(asyncio.get_running_loop().time())  # who is alive before the births
                self._send(self.core.connected(self._now_ms()))
                await self._dbirths()
                async with asyncio.TaskGroup() as group:
                    group.create_task(self._sender(client))
                    if self.forward is not None:
                        await self.forward.session_up()
                        group.create_task(self.forward.replay(self._send, self._drained))
                    await self._receive(client)
                    raise aiomqtt.MqttError("the broker closed the session")
            except* _HostOffline:
                await self._flush_outbox(client)
                raise _HostOffline from None
            except* aiomqtt.MqttError as group_error:
                raise group_error.exceptions[0] from None
            finally:
                self._client = None

    def detach(self) -> None:
        """Stop hearing the units' caches (a node replaced after a config reload)."""
        for device, listener in zip(self.devices, self._listeners, strict=True):
            with contextlib.suppress(ValueError):
                device.unit.cache.listeners.remove(listener)

    async def close(self) -> None:
        """A clean stop: DCMD writes in flight finish (as Modbus requests in flight do), then the NDEATH
        after what is queued (§5.5), then the MQTT DISCONNECT (when ``run`` is cancelled)."""
        if self._writing:
            _, late = await asyncio.wait(set(self._writing), timeout=max(d.unit.write_timeout for d in self.devices))
            for task in late:
                task.cancel()  # its write, if queued, stays queued: applied at most once (Unit._queue_write)
        if self._client is not None and self.config.ndeath_on_stop:
            self._send(self.core.stopping(self._now_ms()))  # the core publishes nothing after it
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(2):
                    await self._outbox.join()
        if self.forward is not None:
            await self.forward.close()  # what is left of the unsent changes: committed

    # --- outgoing ------------------------------------------------------------------------------

    def _send(self, messages: list[Publish]) -> None:
        for message in messages:
            self._outbox.put_nowait(message)

    async def _drained(self) -> None:
        """Everything queued so far is written to the socket, and no pass is under way."""
        await self._outbox.join()
        await self._idle.wait()

    def _drain_outbox(self) -> None:
        """Messages of a session that ended are not sent in the next one."""
        while not self._outbox.empty():
            self._outbox.get_nowait()
            self._outbox.task_done()

    @contextlib.contextmanager
    def _pass(self) -> Iterator[None]:
        """A pass over the devices, one step each: its messages are sent together when it ends."""
        self._passes += 1
        self._idle.clear()
        try:
            yield
        finally:
            self._passes -= 1
            if not self._passes:
                self._idle.set()

    async def _sender(self, client: MqttClient) -> None:
        """The outbox to the broker, in order: what a pass queued, in one go (at most ``_BATCH``)."""
        while True:
            batch = [await self._outbox.get()]
            try:
                await self._idle.wait()
                while len(batch) < _BATCH and not self._outbox.empty():
                    batch.append(self._outbox.get_nowait())
                await client.publish_in_order(batch)
                for message in batch:
                    self.sent[message.topic.split("/")[2]] += 1
            finally:
                for _ in batch:
                    self._outbox.task_done()

    async def _flush_outbox(self, client: aiomqtt.Client) -> None:
        with contextlib.suppress(aiomqtt.MqttError, TimeoutError):
            async with asyncio.timeout(2):
                while not self._outbox.empty():
                    message = self._outbox.get_nowait()
                    self._outbox.task_done()
                    await client.publish(message.topic, message.payload, message.qos, message.retain)
                    self.sent[message.topic.split("/")[2]] += 1

    # --- incoming ------------------------------------------------------------------------------

    async def _receive(self, client: aiomqtt.Client) -> None:
        core = self.core
        ncmd, dcmd_prefix = core.topic("NCMD"), core.topic("DCMD", "")
        async for message in client.messages:
            topic = message.topic.value
            payload = message.payload if isinstance(message.payload, bytes) else b""
            if topic == ncmd:
                self._send(core.node_command(payload, self._now_ms()))
                await self._dbirths()
            elif topic.startswith(dcmd_prefix):
                device = topic[len(dcmd_prefix):]
                for command in core.device_command(device, payload):
                    # one task per write, created in arrival order: each is queued on its link's
                    # write queue in its first step, so they are queued (and applied) in that order
                    task = asyncio.create_task(self._write(command))
                    self._writing.add(task)
                    task.add_done_callback(self._writing.discard)
                if core.refused:
                    log.debug("sparkplug: DCMD to %s: refused so far %s", device, dict(core.refused))
            elif core.primary_host_id is not None and topic == core.state_topic:
                messages, disconnect = core.host_state(payload, self._now_ms())
                self._send(messages)
                if disconnect:
                    raise _HostOffline
                await self._dbirths()

    # --- values ------------------------------------------------------------------------------

    async def _watch(self) -> None:
        """Publish what changed: after a store / patch (the stores of ``batch_interval`` together, one
        DDATA per device), and every ``check_interval`` what ages without a store.  One device at a
        time, the Modbus server's answers in between."""
        loop = asyncio.get_running_loop()
        interval, batch = self.config.check_interval, self.config.batch_interval
        next_check = next_status = loop.time()
        while True:
            timeout = max(0.0, next_check - loop.time())
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(timeout):
                    await self._wake.wait()
                    if batch:
                        await asyncio.sleep(batch)
            self._wake.clear()
            now = loop.time()
            if now >= next_check:
                next_check = now + interval
                status = now >= next_status
                if status:
                    next_status = now + self.config.status_interval
                with self._pass():
                    await self._links(now)
                    await self._check(now, status)
            with self._pass():
                for index in range(len(self.devices)):
                    if self._dirty[index]:
                        started = time.thread_time()
                        # a store means the controller answered: the device is judged up now, not at the
                        # next check, or the changes until then would be neither published nor kept
                        self._link(index, now)
                        self._changed(index, now)
                        self._send(self.core.flush(self._wall_ms(now), (index,)))
                        self.busy.add(started)
                        await asyncio.sleep(0)  # one device at a time: Modbus answers go in between

    async def _links(self, now: float) -> None:
        """Links gone down (DDEATH) or come back (DBIRTH, with its values as they are now), one device a step."""
        for index, device in enumerate(self.devices):
            if device.unit.verdict(now).up == device.device.alive:
                continue
            await asyncio.sleep(0)
            started = time.thread_time()
            self._link(index, now)
            self.busy.add(started)

    def _link(self, index: int, now: float) -> None:
        """Device ``index``'s link as the verdict has it at ``now``: DBIRTH (with its values as they are now) or
        DDEATH when it changed (the core decides what is published)."""
        device = self.devices[index]
        up = device.unit.verdict(now).up
        if up == device.device.alive:
            return
        if up and self.core.online and not self.core.unborn:
            self._refresh(now, index)
        self._send(self.core.link(index, up, self._wall_ms(now)))

    async def _dbirths(self) -> None:
        """The DBIRTHs of a birth sequence, one device a step, each with its values as they are now."""
        loop = asyncio.get_running_loop()
        with self._pass():
            while self.core.unborn:
                await asyncio.sleep(0)
                started = time.thread_time()
                now = loop.time()
                self._refresh(now, self.core.unborn[0])
                message = self.core.next_birth(self._wall_ms(now))
                if message is not None:
                    self._send([message])
                self.busy.add(started)

    def _refresh(self, now: float, only: int | None = None) -> None:
        """Every metric (of device ``only``) as it is now, for the births."""
        stamp = self._wall_ms(now)
        for index, device in enumerate(self.devices):
            if only is not None and index != only:
                continue
            for run in device.runs:
                for metric, sample in device.read(run, self._read_time(device, run.block, stamp), failed_at=stamp,
                                                  everything=True):
                    self.core.observe(index, metric, sample)
            for metric, sample in device.status_samples(now, stamp):
                self.core.observe(index, metric, sample)

    def _read_time(self, device: LinkDevice, block: int, default: int) -> int:
        """The block's last read time as UTC ms (``default`` if it was never read)."""
        read = device.unit.cache.stamps[block]
        return default if math.isinf(read) else self._wall_ms(read)

    async def _check(self, now: float, status: bool) -> None:
        """What changes without a store: values going stale (or coming back); with ``status``, the
        status block's values."""
        stamp = self._wall_ms(now)
        for index, device in enumerate(self.devices):
            await asyncio.sleep(0)
            started = time.thread_time()
            for run in device.runs:
                for metric, sample in device.read(run, self._read_time(device, run.block, stamp), failed_at=stamp):
                    self.core.observe(index, metric, sample)
            if status:
                for metric, sample in device.status_samples(now, stamp):
                    self.core.observe(index, metric, sample)
            if not self._dirty[index]:
                self._send(self.core.flush(stamp, (index,)))
            self.busy.add(started)

    def _changed(self, index: int, now: float) -> None:
        device = self.devices[index]
        dirty = self._dirty[index]
        blocks = list(dirty.items())
        dirty.clear()
        found = self._wall_ms(now)
        for block, read_time in blocks:
            stamp = found if read_time is None or math.isinf(read_time) else self._wall_ms(read_time)
            for run in device.by_block.get(block, ()):
                for metric, sample in device.read(run, stamp, failed_at=found):
                    self.core.observe(index, metric, sample)

    # --- writes ------------------------------------------------------------------------------

    async def _write(self, command: WriteCommand) -> None:
        device = self.devices[command.device]
        point = device.points[command.metric]
        spec = device.device.specs[command.metric]
        unit = device.unit
        bits = spec.datatype is SparkplugType.Boolean
        try:
            if bits:
                await unit.write_bits(point.address, [bool(command.value)])
            else:
                await unit.write_registers(point.address, _registers(point.type, point.low_first, command.value))
        except (ModbusExceptionReply, ValueError, OverflowError, struct.error) as exc:
            self.write_failures += 1
            self.core.refused["write failed"] += 1
            log.warning("sparkplug: DCMD %s/%s = %r not applied: %s", device.name, spec.name, command.value, exc)
            outcome = f"0x{exc.code:02X} {exc}" if isinstance(exc, ModbusExceptionReply) else f"refused: {exc}"
        else:
            outcome = "ok"
        audit_write(unit.unit_id, 15 if bits else 16, point.table.value, point.address,
                    1 if bits else point.width, f"{outcome} (DCMD {spec.name} = {command.value!r})")
        # published again whatever the outcome: the confirmed value, or the controller's
        loop_now = asyncio.get_running_loop().time()
        self._changed(command.device, loop_now)  # the patched block: its other metrics keep their read time
        self.core.observe(command.device, command.metric, device.sample(command.metric, self._wall_ms(loop_now)))
        self.core.force(command.device, command.metric)
        self._send(self.core.flush(self._wall_ms(loop_now), (command.device,)))


def _registers(kind: str, low_first: bool, value: object) -> list[int]:
    """The registers a Modbus write of ``value`` as ``kind`` sends (ValueError: out of range)."""
    if kind in ("int16", "uint16"):
        if not isinstance(value, int):
            raise ValueError(f"{value!r} is not an integer")
        low, high = (-32768, 32767) if kind == "int16" else (0, 65535)
        if not low <= value <= high:
            raise ValueError(f"{value} is outside {kind} ({low}..{high})")
        return [value & 0xFFFF]
    fmt = {"int32": ">i", "uint32": ">I", "float32": ">f"}[kind]
    raw = struct.pack(fmt, value)
    words = [int.from_bytes(raw[0:2], "big"), int.from_bytes(raw[2:4], "big")]
    return words[::-1] if low_first else words
