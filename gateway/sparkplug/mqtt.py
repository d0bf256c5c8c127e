"""The edge node's MQTT client (aiomqtt on paho-mqtt, both pinned) and the CPU account of its steps.

:class:`MqttClient` is aiomqtt's client with two changes that read paho's internals (the Sparkplug guide,
"Dependencies"): its keepalive clock starts when its CONNECT is written, and its will (the NDEATH with the
next bdSeq) is taken when the CONNECT is made, after the TCP connection is up; and a pass's QoS 0 messages
are queued together and waited for once.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable, Sequence
from typing import Any, Final

import aiomqtt
from paho.mqtt.client import MQTT_ERR_SUCCESS
from paho.mqtt.client import time_func as paho_clock
from paho.mqtt.enums import _ConnectionState

from gateway.sparkplug.node import Publish

__all__ = ["MQTT_TIMEOUT", "Busy", "MqttClient"]

#: the MQTT operations (connect, subscribe, publish) that take longer than this fail the session
MQTT_TIMEOUT: Final = 10.0


class Busy:
    """The CPU the node's own steps take on the event loop (``time.thread_time``): reading the image,
    building births and DDATA.  The longest step bounds what it adds to a Modbus answer waiting
    behind it.  The MQTT client's work (paho building packets, writing the socket) is not in it."""

    __slots__ = ("longest", "seconds", "steps")

    def __init__(self) -> None:
        self.seconds = 0.0
        self.longest = 0.0
        self.steps = 0

    def add(self, started: float) -> None:
        spent = time.thread_time() - started
        self.seconds += spent
        self.steps += 1
        self.longest = max(self.longest, spent)


class MqttClient(aiomqtt.Client):
    """aiomqtt's client, whose keepalive clock starts when its CONNECT is written, not before.

    paho (the client under aiomqtt) stamps "last message out" when a connect begins, before the TCP
    connection, and its keepalive check (aiomqtt runs it once a second on the loop, the first time as
    soon as the socket is handed to the loop, before the CONNECT is written) closes a connection that
    has had no CONNACK for ``keepalive`` seconds since that stamp.  A connect that spends that long
    before the loop takes the socket over (a busy loop at start-up, a loaded machine: the TCP connect
    runs in a thread, the CONNECT is written by the loop) is closed before its CONNECT ever leaves,
    silently: aiomqtt then waits out its whole ``timeout`` (10 s) for a CONNACK that cannot come, and
    the next attempt takes the next bdSeq.  Here, while the CONNECT still waits in paho's queue, the
    clock is restarted before each check: the keepalive measures the broker's silence after the
    CONNECT, as MQTT 3.1.1 §3.1.2.10 means it; once written, paho's own rule applies unchanged.  (These are
    paho-mqtt 2.2.0's internals and aiomqtt 2.5.1's misc loop: both pinned in pyproject.toml.)"""

    def __init__(self, *args: Any, will_of_connect: Callable[[], Publish], **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._will_of_connect = will_of_connect
        #: the connect thread is making the CONNECT (taking the bdSeq from the loop): not queued in paho yet
        self._making_connect = False

    def _client_connect(self) -> None:
        """aiomqtt's connect (in its thread), with the will set when paho makes the CONNECT packet: after the TCP
        connection is up, so that each CONNECT, and only a CONNECT, takes a bdSeq (paho-mqtt 2.2.0's
        ``reconnect`` calls ``_send_connect`` right after ``_create_socket``)."""
        paho = self._client
        send_connect = paho._send_connect

        def with_will(keepalive: int) -> Any:
            will = self._will_of_connect()
            paho.will_set(will.topic, will.payload, will.qos, will.retain)
            try:
                return send_connect(keepalive)
            finally:
                self._making_connect = False

        paho._send_connect = with_will  # type: ignore[method-assign]
        self._making_connect = True
        try:
            super()._client_connect()
        finally:
            self._making_connect = False
            del paho._send_connect

    async def _misc_loop(self) -> None:
        paho = self._client
        while True:
            if paho._state is _ConnectionState.MQTT_CS_CONNECTING and (self._making_connect or paho.want_write()):
                # the CONNECT is being made (the socket is already the loop's) or not written yet
                with paho._msgtime_mutex:
                    paho._last_msg_out = paho._last_bytes_received = paho_clock()
            if paho.loop_misc() != MQTT_ERR_SUCCESS:
                return
            await asyncio.sleep(1)

    async def publish_in_order(self, messages: Sequence[Publish]) -> None:
        """``messages`` to the broker in their order; returns once they are written to the socket.

        The QoS 0 ones go into paho's queue together, written in one go when the socket takes them, and
        only the last is waited for (aiomqtt's ``publish`` waits for each: a task and a few loop steps
        apiece).  A QoS 1 one (the NDEATH of a clean stop) waits for its PUBACK, as aiomqtt publishes it."""
        last: int | None = None
        for message in messages:
            if message.qos:
                await self.publish(message.topic, message.payload, message.qos, message.retain)
                last = None
                continue
            info = self._client.publish(message.topic, message.payload, 0, message.retain)
            if info.rc != MQTT_ERR_SUCCESS:
                raise aiomqtt.MqttCodeError(info.rc, "Could not publish message")
            last = None if info.is_published() else info.mid
        if last is None:
            return
        written = asyncio.Event()  # set by aiomqtt's on_publish: paho wrote that message (and those before it)
        self._pending_publishes[last] = written
        try:
            async with asyncio.timeout(self.timeout):
                await written.wait()
        except TimeoutError:
            raise aiomqtt.MqttError("Operation timed out") from None
        finally:
            self._pending_publishes.pop(last, None)
