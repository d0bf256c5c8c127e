"""Self-tests of the Sparkplug 3.0 test host (sparkplug_host.py) against a real mosquitto.

Each broker test starts Debian's /usr/sbin/mosquitto on a free loopback port and plays scripted edge
nodes over a small MQTT 3.1.1 client written here on asyncio streams (so a node can drop its TCP
connection without DISCONNECT and have the broker publish its Will NDEATH).  Payloads are built with
the host's own encoder; the expected violations are stated here from the specification's rules.

Without mosquitto the broker tests skip, unless SLC_GATEWAY_REQUIRE_MOSQUITTO=1 makes that a failure.
"""
from __future__ import annotations

import asyncio
import contextlib
import importlib
import importlib.util
import json
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

from sparkplug_host import (
    Checker,
    DataType,
    DecodeError,
    Message,
    Metric,
    Payload,
    SparkplugHost,
    decode_payload,
    decode_varint,
    encode_payload,
    encode_varint,
    interpret,
    make_metric,
    now_ms,
)
from tests.net import free_port

MOSQUITTO = "/usr/sbin/mosquitto"
HOST_PY = Path(__file__).resolve().parent / "sparkplug_host.py"
WAIT = 5.0


# ------------------------------------------------------------------------------------------------
# mosquitto
# ------------------------------------------------------------------------------------------------

@pytest.fixture
def broker(tmp_path: Path) -> Iterator[int]:
    """A mosquitto on 127.0.0.1:<free port>; yields the port."""
    missing = []
    if not os.access(MOSQUITTO, os.X_OK):
        missing.append(f"{MOSQUITTO} is not installed (Debian package mosquitto)")
    if importlib.util.find_spec("aiomqtt") is None:
        missing.append("the Python package aiomqtt is not installed (pip install aiomqtt==2.5.1)")
    if missing:
        reason = "; ".join(missing)
        if os.environ.get("SLC_GATEWAY_REQUIRE_MOSQUITTO") == "1":
            pytest.fail(f"{reason}, and SLC_GATEWAY_REQUIRE_MOSQUITTO=1")
        pytest.skip(f"{reason}; set SLC_GATEWAY_REQUIRE_MOSQUITTO=1 to fail instead")
    port = free_port()
    conf = tmp_path / "mosquitto.conf"
    conf.write_text(f"listener {port} 127.0.0.1\nallow_anonymous true\npersistence false\n"
                    f"log_dest file {tmp_path / 'mosquitto.log'}\n")
    proc = subprocess.Popen([MOSQUITTO, "-c", str(conf)], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 10
        while True:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
                break
            except OSError:
                if proc.poll() is not None or time.monotonic() > deadline:
                    err = proc.stderr.read().decode(errors="replace") if proc.stderr else ""
                    pytest.fail(f"mosquitto did not start on port {port}: {err}")
                time.sleep(0.05)
        yield port
    finally:
        proc.terminate()
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


# ------------------------------------------------------------------------------------------------
# a scripted edge node on a minimal MQTT 3.1.1 client
# ------------------------------------------------------------------------------------------------

def _mqtt_str(text: str) -> bytes:
    raw = text.encode("utf-8")
    return len(raw).to_bytes(2, "big") + raw


def _packet(first: int, body: bytes) -> bytes:
    length, rl = len(body), bytearray()
    while True:
        byte = length % 128
        length //= 128
        rl.append(byte | (0x80 if length else 0))
        if not length:
            return bytes([first]) + bytes(rl) + body


class RawMqtt:
    """CONNECT (with a Will), SUBSCRIBE QoS 0, PUBLISH QoS 0, and drop the TCP connection at will."""

    def __init__(self) -> None:
        self.reader: asyncio.StreamReader
        self.writer: asyncio.StreamWriter
        self.inbox: asyncio.Queue[tuple[str, bytes]] = asyncio.Queue()
        self._task: asyncio.Task[None] | None = None
        self._suback = asyncio.Event()

    async def connect(self, port: int, client_id: str, will: tuple[str, bytes, int, bool] | None) -> None:
        self.reader, self.writer = await asyncio.open_connection("127.0.0.1", port)
        flags = 0x02  # clean session (5.4: all Sparkplug clients)
        payload = _mqtt_str(client_id)
        if will is not None:
            topic, message, qos, retain = will
            flags |= 0x04 | (qos << 3) | (0x20 if retain else 0)
            payload += _mqtt_str(topic) + len(message).to_bytes(2, "big") + message
        self.writer.write(_packet(0x10, _mqtt_str("MQTT") + bytes([4, flags]) + (60).to_bytes(2, "big") + payload))
        await self.writer.drain()
        head = await asyncio.wait_for(self.reader.readexactly(4), WAIT)
        assert head[0] == 0x20 and head[3] == 0, f"CONNACK refused: {head.hex()}"
        self._task = asyncio.create_task(self._read())

    async def _read_packet(self) -> tuple[int, bytes]:
        first = (await self.reader.readexactly(1))[0]
        length, shift = 0, 0
        while True:
            byte = (await self.reader.readexactly(1))[0]
            length |= (byte & 0x7F) << shift
            shift += 7
            if not byte & 0x80:
                break
        return first, await self.reader.readexactly(length)

    async def _read(self) -> None:
        with contextlib.suppress(asyncio.IncompleteReadError, ConnectionError):
            while True:
                first, body = await self._read_packet()
                if first >> 4 == 3:  # PUBLISH (QoS 0: no packet id)
                    tlen = int.from_bytes(body[:2], "big")
                    await self.inbox.put((body[2:2 + tlen].decode(), body[2 + tlen:]))
                elif first >> 4 == 9:
                    self._suback.set()

    async def subscribe(self, topic: str) -> None:
        self._suback.clear()
        self.writer.write(_packet(0x82, (1).to_bytes(2, "big") + _mqtt_str(topic) + b"\x00"))
        await self.writer.drain()
        await asyncio.wait_for(self._suback.wait(), WAIT)

    async def publish(self, topic: str, payload: bytes, *, retain: bool = False) -> None:
        self.writer.write(_packet(0x30 | (1 if retain else 0), _mqtt_str(topic) + payload))
        await self.writer.drain()

    async def receive(self, wait: float = WAIT) -> tuple[str, bytes]:
        return await asyncio.wait_for(self.inbox.get(), wait)

    async def drop(self) -> None:
        """Lose the connection without DISCONNECT: the broker publishes the Will."""
        self.writer.transport.abort()
        await self._stop()

    async def disconnect(self) -> None:
        self.writer.write(b"\xe0\x00")
        await self.writer.drain()
        self.writer.close()
        await self._stop()

    async def _stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task


class Edge:
    """A scripted Sparkplug edge node: it numbers its messages itself unless told a seq."""

    def __init__(self, group: str, node: str) -> None:
        self.group, self.node = group, node
        self.mqtt = RawMqtt()
        self.seq = -1

    def topic(self, mtype: str, device: str | None = None) -> str:
        return f"spBv1.0/{self.group}/{mtype}/{self.node}" + (f"/{device}" if device else "")

    async def connect(self, port: int, will_bdseq: int) -> None:
        death = encode_payload(Payload(timestamp=now_ms(), metrics=[make_metric("bdSeq", "Int64", will_bdseq)]))
        # Will: NDEATH, QoS 1, not retained (5.4)
        await self.mqtt.connect(port, f"edge-{self.node}", (self.topic("NDEATH"), death, 1, False))
        await self.mqtt.subscribe(self.topic("NCMD"))
        await self.mqtt.subscribe(self.topic("DCMD") + "/+")

    async def send(self, mtype: str, device: str | None, metrics: list[Metric], *, seq: int | None = None,
                   retain: bool = False) -> None:
        if seq is None:
            seq = 0 if mtype == "NBIRTH" else (self.seq + 1) % 256
        self.seq = seq
        payload = Payload(timestamp=now_ms(), metrics=metrics, seq=seq)
        await self.mqtt.publish(self.topic(mtype, device), encode_payload(payload), retain=retain)

    async def nbirth(self, bdseq: int, extra: list[Metric] | None = None, **kw: Any) -> None:
        ts = now_ms()
        metrics = [make_metric("bdSeq", "Int64", bdseq, timestamp=ts),
                   make_metric("Node Control/Rebirth", "Boolean", False, timestamp=ts),
                   *(extra or [])]
        await self.send("NBIRTH", None, metrics, **kw)


def m(name: str | None, dt: str, value: Any = None, **kw: Any) -> Metric:
    kw.setdefault("timestamp", now_ms())
    return make_metric(name, dt, value, **kw)


def dbirth_metrics() -> list[Metric]:
    """Device 'plc': aliases 1..3 as a gateway using aliases would declare them."""
    return [m("N7:0", "Int16", -3, alias=1), m("N7:1", "UInt16", 65535, alias=2),
            m("F8:0", "Float", 1.5, alias=3), m("B3:0/0", "Boolean", True)]


@contextlib.asynccontextmanager
async def edge(port: int, group: str, node: str, will_bdseq: int) -> AsyncIterator[Edge]:
    e = Edge(group, node)
    await e.connect(port, will_bdseq)
    try:
        yield e
    finally:
        if not e.mqtt.writer.is_closing():
            e.mqtt.writer.transport.abort()
        await e.mqtt._stop()


def is_type(mtype: str, node: str | None = None, device: str | None = None) -> Any:
    def pred(msg: Message) -> bool:
        return (msg.message_type == mtype and (node is None or msg.edge_node_id == node)
                and (device is None or msg.device_id == device))
    return pred


# ------------------------------------------------------------------------------------------------
# codec (no broker): the specification's own examples (6.4.17) and the protobuf wire format
# ------------------------------------------------------------------------------------------------

def test_varint_round_trip_and_limits() -> None:
    for value in (0, 1, 127, 128, 300, 2**32 - 1, 2**63, 2**64 - 1):
        data = encode_varint(value)
        assert decode_varint(data, 0) == (value, len(data))
    assert encode_varint(300) == bytes([0xAC, 0x02])  # the protobuf documentation's example
    with pytest.raises(DecodeError):
        decode_varint(b"\xff" * 11, 0)
    with pytest.raises(DecodeError):
        decode_varint(b"\x80", 0)


@pytest.mark.parametrize(("datatype", "data", "values"), [
    (DataType.Int16Array, [0xD0, 0x8A, 0x30, 0x75], [-30000, 30000]),
    (DataType.Int32Array, [0xFF, 0xFF, 0xFF, 0xFF, 0xFA, 0xAF, 0xCB, 0x12], [-1, 315338746]),
    (DataType.UInt8Array, [0x17, 0xFA], [23, 250]),
    (DataType.UInt16Array, [0x1E, 0x00, 0x88, 0xCC], [30, 52360]),
    (DataType.UInt32Array, [0x34, 0, 0, 0, 0x49, 0xFB, 0x55, 0xC4], [52, 3293969225]),
    (DataType.UInt64Array, [0x34, 0, 0, 0, 0, 0, 0, 0, 0xD9, 0x9E, 0x02, 0xD1, 0xB2, 0x76, 0x37, 0xE4],
     [52, 16444743074749521625]),
    (DataType.Int64Array, [0xCE, 0x06, 0x72, 0xAC, 0x18, 0x9C, 0xBA, 0xC4, 0xC4, 0xBA, 0x9C, 0x18, 0xAC, 0x72,
                           0x06, 0xCE], [-4270929666821191986, -3601064768563266876]),
    (DataType.BooleanArray, [0x0C, 0, 0, 0, 0x34, 0xD0],
     [False, False, True, True, False, True, False, False, True, True, False, True]),
    (DataType.StringArray, [0x41, 0x42, 0x43, 0x00, 0x68, 0x65, 0x6C, 0x6C, 0x6F, 0x00], ["ABC", "hello"]),
])
def test_array_examples_of_6_4_17(datatype: DataType, data: list[int], values: list[Any]) -> None:
    # (the Int8Array and FloatArray examples of 3.0.0 are misprinted: 0xEF is -17, and the float bytes
    # are big-endian; they are left out)
    assert interpret(datatype, "bytes_value", bytes(data)) == values
    assert make_metric("a", datatype, values).raw == bytes(data)  # the 'do not care' bits encoded as 0


@pytest.mark.parametrize(("datatype", "raw", "value"), [
    (DataType.Int16, 0xFFFE, -2), (DataType.Int16, 0xFFFFFFFE, -2), (DataType.Int16, 0x7FFF, 32767),
    (DataType.Int16, 0x8000, -32768), (DataType.Int8, 0xFFFFFF80, -128), (DataType.Int8, 0x7F, 127),
    (DataType.Int32, 0xFFFFFFFF, -1), (DataType.UInt16, 0xFFFF, 65535), (DataType.UInt32, 0xFFFFFFFF, 2**32 - 1),
])
def test_signed_ints_in_uint32_read_both_forms(datatype: DataType, raw: int, value: int) -> None:
    assert interpret(datatype, "int_value", raw) == value


@pytest.mark.parametrize(("datatype", "raw"), [
    (DataType.Int16, 0x12345), (DataType.Int16, 0xFFFF7FFF), (DataType.UInt16, 0x10000), (DataType.Int8, 0x1FF),
])
def test_ints_out_of_both_forms_are_refused(datatype: DataType, raw: int) -> None:
    with pytest.raises(ValueError):
        interpret(datatype, "int_value", raw)


def test_payload_bytes_by_hand() -> None:
    """Field numbers and wire types of sparkplug_b.proto, spelled out byte by byte."""
    p = Payload(timestamp=1, seq=2, metrics=[make_metric("a", "Int16", -2, alias=5, timestamp=3)])
    metric = (b"\x0a\x01a" + b"\x10\x05" + b"\x18\x03" + b"\x20\x02"  # name 1, alias 2, timestamp 3, datatype 4
              + b"\x50\xfe\xff\xff\xff\x0f")  # int_value 10: -2 sign-extended to 32 bits
    assert encode_payload(p) == b"\x08\x01" + b"\x12" + bytes([len(metric)]) + metric + b"\x18\x02"
    back = decode_payload(encode_payload(p))
    assert (back.timestamp, back.seq, back.metrics[0].value, back.metrics[0].alias) == (1, 2, -2, 5)
    # a float 12 (fixed32), a double 13 (fixed64), is_null 7, a Quality property
    p2 = Payload(metrics=[make_metric("f", "Float", 1.5), make_metric("d", "Double", -0.25),
                          make_metric("n", "Int32", None, is_null=True, quality=0)])
    got = decode_payload(encode_payload(p2)).metrics
    assert [x.value for x in got] == [1.5, -0.25, None]
    assert got[2].is_null and got[2].quality == 0
    assert b"\x65\x00\x00\xc0\x3f" in encode_payload(p2)  # float 1.5 little-endian after tag 12<<3|5


def _google_payload_class() -> Any:
    """Payload/Metric/PropertySet/PropertyValue of sparkplug_b.proto (6.4.1) as descriptors for Google's
    protobuf runtime: a second, independent codec to compare the hand-written one with."""
    pb = pytest.importorskip("google.protobuf", reason="the 'protobuf' package is not installed; the "
                             "cross-check against Google's protobuf runtime is optional (pip install protobuf)")
    del pb
    descriptor_pb2 = importlib.import_module("google.protobuf.descriptor_pb2")
    descriptor_pool = importlib.import_module("google.protobuf.descriptor_pool")
    message_factory = importlib.import_module("google.protobuf.message_factory")

    f = descriptor_pb2.FieldDescriptorProto
    fdp = descriptor_pb2.FileDescriptorProto(name="sparkplug_b_check.proto", package="sp", syntax="proto2")

    def message(name: str, fields: list[tuple[str, int, int, str | None, bool]], oneof: bool = False) -> None:
        msg = fdp.message_type.add(name=name)
        if oneof:
            msg.oneof_decl.add(name="value")
        for fname, number, ftype, type_name, in_oneof in fields:
            fd = msg.field.add(name=fname, number=number, type=ftype,
                               label=f.LABEL_REPEATED if fname in ("metrics", "keys", "values") else f.LABEL_OPTIONAL)
            if type_name:
                fd.type_name = type_name
            if in_oneof:
                fd.oneof_index = 0

    values = [("int_value", f.TYPE_UINT32), ("long_value", f.TYPE_UINT64), ("float_value", f.TYPE_FLOAT),
              ("double_value", f.TYPE_DOUBLE), ("boolean_value", f.TYPE_BOOL), ("string_value", f.TYPE_STRING)]
    message("PropertyValue", [("type", 1, f.TYPE_UINT32, None, False), ("is_null", 2, f.TYPE_BOOL, None, False),
                              *[(n, 3 + i, t, None, True) for i, (n, t) in enumerate(values)],
                              ("propertyset_value", 9, f.TYPE_MESSAGE, ".sp.PropertySet", True)], oneof=True)
    message("PropertySet", [("keys", 1, f.TYPE_STRING, None, False),
                            ("values", 2, f.TYPE_MESSAGE, ".sp.PropertyValue", False)])
    message("Metric", [("name", 1, f.TYPE_STRING, None, False), ("alias", 2, f.TYPE_UINT64, None, False),
                       ("timestamp", 3, f.TYPE_UINT64, None, False), ("datatype", 4, f.TYPE_UINT32, None, False),
                       ("is_historical", 5, f.TYPE_BOOL, None, False), ("is_transient", 6, f.TYPE_BOOL, None, False),
                       ("is_null", 7, f.TYPE_BOOL, None, False),
                       ("properties", 9, f.TYPE_MESSAGE, ".sp.PropertySet", False),
                       *[(n, 10 + i, t, None, True) for i, (n, t) in enumerate(values)],
                       ("bytes_value", 16, f.TYPE_BYTES, None, True)], oneof=True)
    message("Payload", [("timestamp", 1, f.TYPE_UINT64, None, False),
                        ("metrics", 2, f.TYPE_MESSAGE, ".sp.Metric", False), ("seq", 3, f.TYPE_UINT64, None, False),
                        ("uuid", 4, f.TYPE_STRING, None, False), ("body", 5, f.TYPE_BYTES, None, False)])
    pool = descriptor_pool.DescriptorPool()
    pool.Add(fdp)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName("sp.Payload"))


def test_codec_agrees_with_googles_protobuf_runtime() -> None:
    google_payload = _google_payload_class()
    ours = Payload(timestamp=1_700_000_000_123, seq=255, uuid="u", metrics=[
        make_metric("i16", "Int16", -2, alias=1, timestamp=5), make_metric("u32", "UInt32", 2**32 - 1, alias=2**40),
        make_metric("i64", "Int64", -1), make_metric("f", "Float", -1.25), make_metric("d", "Double", 1e300),
        make_metric("b", "Boolean", True), make_metric("s", "String", "żółw"), make_metric("by", "Bytes", b"\0\1"),
        make_metric("n", "Int32", None, is_null=True, quality=500)])
    data = encode_payload(ours)
    g = google_payload.FromString(data)
    assert g.SerializeToString() == data  # same bytes: field order and encodings agree
    assert (g.timestamp, g.seq, g.uuid) == (1_700_000_000_123, 255, "u")
    got = [(x.name, x.WhichOneof("value"), getattr(x, x.WhichOneof("value")) if x.WhichOneof("value") else None)
           for x in g.metrics]
    assert got == [("i16", "int_value", 0xFFFFFFFE), ("u32", "int_value", 2**32 - 1), ("i64", "long_value", 2**64 - 1),
                   ("f", "float_value", -1.25), ("d", "double_value", 1e300), ("b", "boolean_value", True),
                   ("s", "string_value", "żółw"), ("by", "bytes_value", b"\0\1"), ("n", None, None)]
    assert g.metrics[1].alias == 2**40 and g.metrics[8].is_null
    assert list(g.metrics[8].properties.keys) == ["Quality"] and g.metrics[8].properties.values[0].int_value == 500
    # and what Google's runtime writes, ours reads (a negative int32 cast as a protobuf library would)
    g2 = google_payload(timestamp=7, seq=0)
    g2.metrics.add(name="x", datatype=2, int_value=(-300) & 0xFFFFFFFF, timestamp=8)
    back = decode_payload(g2.SerializeToString())
    assert (back.timestamp, back.seq, back.metrics[0].value) == (7, 0, -300)


@pytest.mark.parametrize("data", [b"\x12\x05\x0a", b"\x0b", b"\x08", b"\x12\x02\x0a\x05"])
def test_truncated_or_invalid_wire_data_is_refused(data: bytes) -> None:
    with pytest.raises(DecodeError):
        decode_payload(data)


# ------------------------------------------------------------------------------------------------
# the checks, fed directly (no broker)
# ------------------------------------------------------------------------------------------------

def _feed(c: Checker, topic: str, p: Payload, qos: int = 0, retain: bool = False) -> Message:
    return c.feed(topic, encode_payload(p), qos=qos, retain=retain)


def _nbirth(bdseq: int = 0, extra: list[Metric] | None = None, seq: int = 0) -> Payload:
    return Payload(timestamp=now_ms(), seq=seq, metrics=[m("bdSeq", "Int64", bdseq),
                                                         m("Node Control/Rebirth", "Boolean", False), *(extra or [])])


def test_a_well_formed_session_has_no_violation_and_values_follow_aliases() -> None:
    c = Checker()
    _feed(c, "spBv1.0/G/NBIRTH/E", _nbirth(3, [m("Temp", "Double", 20.5, alias=100)]))
    _feed(c, "spBv1.0/G/DBIRTH/E/plc", Payload(timestamp=now_ms(), seq=1, metrics=dbirth_metrics()))
    _feed(c, "spBv1.0/G/DDATA/E/plc", Payload(timestamp=now_ms(), seq=2, metrics=[
        m(None, "Int16", -7, alias=1, with_datatype=False),
        m(None, "UInt16", None, alias=2, is_null=True, quality=0, with_datatype=False),
        m("B3:0/0", "Boolean", False, with_datatype=False)]))
    _feed(c, "spBv1.0/G/NDATA/E", Payload(timestamp=now_ms(), seq=3, metrics=[m(None, "Double", 21.0, alias=100)]))
    assert c.violations == []
    assert c.value("G", "E", "plc", "N7:0") == (-7, False, None)
    assert c.value("G", "E", "plc", "N7:1") == (None, True, 0)
    assert c.value("G", "E", "plc", "F8:0") == (1.5, False, None)
    assert c.value("G", "E", "plc", "B3:0/0").value is False
    assert c.value("G", "E", None, "Temp").value == 21.0
    assert c.device_online("G", "E", "plc") and c.node_online("G", "E")
    _feed(c, "spBv1.0/G/DDEATH/E/plc", Payload(timestamp=now_ms(), seq=4))
    assert not c.device_online("G", "E", "plc") and c.node_online("G", "E")
    _feed(c, "spBv1.0/G/NDEATH/E", Payload(timestamp=now_ms(), metrics=[m("bdSeq", "Int64", 3)]))
    assert not c.node_online("G", "E")
    _feed(c, "spBv1.0/G/NDEATH/E", Payload(timestamp=now_ms(), metrics=[m("bdSeq", "Int64", 3)]))  # Will after
    assert c.violations == []


@pytest.mark.parametrize(("topic", "payload", "expected"), [
    ("spBv1.0/G/NBIRTH/E", Payload(timestamp=1, seq=0, metrics=[m("Node Control/Rebirth", "Boolean", False)]),
     ["no bdSeq metric"]),
    ("spBv1.0/G/NBIRTH/E", Payload(timestamp=1, seq=0, metrics=[m("bdSeq", "Int64", 0)]),
     ["no 'Node Control/Rebirth' metric"]),
    ("spBv1.0/G/NBIRTH/E", Payload(timestamp=1, seq=0, metrics=[
        m("bdSeq", "Int64", 0), m("Node Control/Rebirth", "Boolean", False, alias=9)]), ["MUST NOT have an alias"]),
    ("spBv1.0/G/NBIRTH/E", _nbirth(seq=5), ["NBIRTH seq 5, MUST be 0"]),
    ("spBv1.0/G/NBIRTH/E", Payload(seq=0, metrics=_nbirth().metrics), ["payload has no timestamp"]),
    ("spBv1.0/G/NBIRTH/E", _nbirth(extra=[Metric(name="x", datatype=3, timestamp=1)]),
     ["has no value and is not is_null"]),
    ("spBv1.0/G/NBIRTH/E", _nbirth(extra=[m("x", "Int32", 1, with_datatype=False)]), ["has no datatype"]),
    ("spBv1.0/G/NBIRTH/E", _nbirth(extra=[make_metric("x", "Int32", 1)]), ["'x' has no timestamp"]),
    ("spBv1.0/G/NBIRTH/E", _nbirth(extra=[m("x", "Int32", 1, alias=4), m("y", "Int32", 1, alias=4)]),
     ["alias 4 of 'y' is already declared"]),
    ("spBv1.0/G/NBIRTH/E", _nbirth(extra=[m("x", "Int32", 1, quality=7)]), ["Quality property"]),
    ("spBv1.0/G/NBIRTH", _nbirth(), ["topic"]),
    ("spBv1.0/G/DDATA/E", _nbirth(), ["must carry a device_id"]),
])
def test_each_birth_rule_is_reported(topic: str, payload: Payload, expected: list[str]) -> None:
    c = Checker()
    _feed(c, topic, payload)
    assert len(c.violations) == len(expected), c.violations
    for line, text in zip(c.violations, expected, strict=True):
        assert text in line


def test_mqtt_flags_of_births_are_checked() -> None:
    c = Checker()
    _feed(c, "spBv1.0/G/NBIRTH/E", _nbirth(), qos=1, retain=True)
    assert len(c.violations) == 2
    assert "QoS 1" in c.violations[0] and "retained" in c.violations[1]
    _feed(c, "spBv1.0/G/NDEATH/E", Payload(metrics=[m("bdSeq", "Int64", 0)]), qos=1, retain=True)
    assert len(c.violations) == 3 and "retained NDEATH" in c.violations[2]


def test_data_rules() -> None:
    c = Checker()
    _feed(c, "spBv1.0/G/NBIRTH/E", _nbirth())
    _feed(c, "spBv1.0/G/DBIRTH/E/a", Payload(timestamp=1, seq=1, metrics=[m("x", "Int16", 1, alias=1)]))
    _feed(c, "spBv1.0/G/DBIRTH/E/b", Payload(timestamp=1, seq=2, metrics=[m("y", "Int16", 1, alias=1)]))
    assert len(c.violations) == 1 and "alias 1 of 'y' is already declared by device 'a'" in c.violations[0]
    c.violations.clear()
    cases: list[tuple[list[Metric], str]] = [
        ([m("x", "Int16", 2, alias=1, with_datatype=False)], "carries both name and alias"),
        ([m("x", "Int16", 2, with_datatype=False)], "sent by name though its birth declared alias 1"),
        ([m(None, "UInt16", 2, alias=1)], "datatype UInt16 differs from its birth's Int16"),
        ([m(None, "Int16", 2, alias=1, timestamp=None)], "has no timestamp"),
        ([m(None, "Int16", 2, with_datatype=False)], "neither name nor alias"),
        ([m("zz", "Int16", 2)], "metric 'zz' is not in the current DBIRTH"),
        ([Metric(alias=1, timestamp=1, value_field="int_value", raw=0x12345)], "neither 16-bit"),
        ([Metric(alias=1, timestamp=1, value_field="double_value", raw=1.0)], "travels in int_value"),
    ]
    for seq, (metrics, text) in enumerate(cases, start=3):
        _feed(c, "spBv1.0/G/DDATA/E/a", Payload(timestamp=1, seq=seq, metrics=metrics))
        assert len(c.violations) == 1 and text in c.violations[0], (text, c.violations)
        c.violations.clear()
    seq = 3 + len(cases)
    _feed(c, "spBv1.0/G/NDATA/E", Payload(timestamp=1, seq=seq, metrics=[m("bdSeq", "Int64", 1)]))
    assert c.violations == []
    _feed(c, "spBv1.0/G/NDATA/E", Payload(timestamp=1, metrics=[]))
    assert len(c.violations) == 1 and "no seq" in c.violations[0]


def test_undecodable_payload_and_bad_state_are_reported() -> None:
    c = Checker()
    _feed(c, "spBv1.0/G/NBIRTH/E", _nbirth())
    c.feed("spBv1.0/G/NDATA/E", b"\x0a\xff\x01")
    assert len(c.violations) == 1 and "does not decode" in c.violations[0]
    assert c.messages[1].error is not None
    _feed(c, "spBv1.0/G/NDATA/E", Payload(timestamp=1, seq=2, metrics=[]))  # the lost seq 1 is not a gap
    assert len(c.violations) == 1
    c.feed("spBv1.0/STATE/h", b"ONLINE", qos=1, retain=True)  # the 2.2 form is not 3.0's JSON
    c.feed("spBv1.0/STATE/h", b'{"online": "yes", "timestamp": 5}', qos=1, retain=True)
    c.feed("spBv1.0/STATE/h", b'{"online": true, "timestamp": 5}', qos=0, retain=False)
    assert len(c.violations) == 5, c.violations
    assert "not JSON" in c.violations[1] and "'online'" in c.violations[2]
    assert "QoS 0" in c.violations[3] and "not retained" in c.violations[4]


def test_ndeath_rules() -> None:
    c = Checker()
    _feed(c, "spBv1.0/G/NBIRTH/E", _nbirth(4))
    _feed(c, "spBv1.0/G/NDEATH/E", Payload(metrics=[m("bdSeq", "Int64", 4)], seq=1))
    assert len(c.violations) == 1 and "NDEATH carries seq" in c.violations[0]
    assert not c.node_online("G", "E")
    _feed(c, "spBv1.0/G/NBIRTH/E", _nbirth(5))
    _feed(c, "spBv1.0/G/NDEATH/E", Payload(metrics=[m("bdSeq", "Int64", 4)]))  # a late Will of session 4
    assert len(c.violations) == 1 and c.node_online("G", "E")
    _feed(c, "spBv1.0/G/NDEATH/E", Payload(metrics=[m("bdSeq", "Int64", 9)]))
    assert len(c.violations) == 2 and "bdSeq 9 matches neither" in c.violations[1]
    assert c.node_online("G", "E")


def test_sessions_end_with_deaths_and_births_start_them_again() -> None:
    c = Checker()
    dd = Payload(timestamp=1, metrics=[m(None, "Int16", 5, alias=1)])
    _feed(c, "spBv1.0/G/NBIRTH/E", _nbirth(2))
    _feed(c, "spBv1.0/G/DBIRTH/E/a", Payload(timestamp=1, seq=1, metrics=[m("x", "Int16", 1, alias=1)]))
    _feed(c, "spBv1.0/G/DDEATH/E/a", Payload(timestamp=1, seq=2))
    dd.seq = 3
    _feed(c, "spBv1.0/G/DDATA/E/a", dd)  # after its DDEATH
    assert len(c.violations) == 1 and "DDATA before a DBIRTH of device 'a'" in c.violations[0]
    _feed(c, "spBv1.0/G/DBIRTH/E/a", Payload(timestamp=1, seq=4, metrics=[m("x", "Int16", 1, alias=1)]))
    dd.seq = 5
    _feed(c, "spBv1.0/G/DDATA/E/a", dd)
    assert len(c.violations) == 1
    # a rebirth: the new NBIRTH (same bdSeq, seq 0) starts a birth sequence, devices must be born again
    c.nodes[("G", "E")].rebirth_requested = True
    _feed(c, "spBv1.0/G/NBIRTH/E", _nbirth(2))
    dd.seq = 1
    _feed(c, "spBv1.0/G/DDATA/E/a", dd)
    assert len(c.violations) == 2 and "DDATA before a DBIRTH" in c.violations[1]
    # a rebirth answered with another bdSeq breaks 5.17
    c.nodes[("G", "E")].rebirth_requested = True
    _feed(c, "spBv1.0/G/NBIRTH/E", _nbirth(3))
    assert len(c.violations) == 3 and "changed bdSeq 2 -> 3" in c.violations[2]
    # without a rebirth request a new bdSeq is a new session whose Will may still come (5.4)
    _feed(c, "spBv1.0/G/NBIRTH/E", _nbirth(4))
    _feed(c, "spBv1.0/G/NDEATH/E", Payload(metrics=[m("bdSeq", "Int64", 3)]))
    assert len(c.violations) == 3 and c.node_online("G", "E")
    _feed(c, "spBv1.0/G/NDEATH/E", Payload(metrics=[m("bdSeq", "Int64", 4)]))
    assert not c.node_online("G", "E")
    _feed(c, "spBv1.0/G/NDATA/E", Payload(timestamp=1, seq=1, metrics=[m("bdSeq", "Int64", 4)]))
    _feed(c, "spBv1.0/G/DBIRTH/E/a", Payload(timestamp=1, seq=2, metrics=[m("x", "Int16", 1, alias=1)]))
    assert len(c.violations) == 5
    assert "NDATA while the edge node is not born (after its NDEATH" in c.violations[3]
    assert "DBIRTH while the edge node is not born" in c.violations[4]


# ------------------------------------------------------------------------------------------------
# over mosquitto
# ------------------------------------------------------------------------------------------------

async def test_well_behaved_edge_node_has_no_violation(broker: int) -> None:
    async with SparkplugHost("127.0.0.1", broker, primary_host_id="test-host") as h:
        await h.publish_state(True)
        async with edge(broker, "G1", "gw", will_bdseq=0) as e:
            ts = now_ms()
            await e.nbirth(0, [m("Properties/OS", "String", "Linux", alias=10), m("Links up", "UInt8", 1, alias=11)])
            await e.send("DBIRTH", "plc", dbirth_metrics())
            await e.send("DDATA", "plc", [m(None, "Int16", -300, alias=1), m(None, "Float", 2.25, alias=3)])
            await e.send("NDATA", None, [m(None, "UInt8", 0, alias=11)])
            await e.send("DDATA", "plc", [m(None, "UInt16", None, alias=2, is_null=True, quality=0)])
            await h.wait_for(lambda msg: msg.message_type == "DDATA" and msg.payload is not None
                             and msg.payload.seq == 4, WAIT)
            assert h.value("G1", "gw", "plc", "N7:0") == (-300, False, None)
            assert h.value("G1", "gw", "plc", "F8:0") == (2.25, False, None)
            assert h.value("G1", "gw", "plc", "N7:1") == (None, True, 0)
            assert h.value("G1", "gw", None, "Links up") == (0, False, None)
            assert h.node_online("G1", "gw") and h.device_online("G1", "gw", "plc")

            # a DCMD goes by the DBIRTH's alias, no name, no datatype; -5 as Int16 sign-extended to 32 bits
            await h.send_dcmd("G1", "gw", "plc", "N7:0", -5, "Int16")
            topic, data = await e.mqtt.receive()
            assert topic == "spBv1.0/G1/DCMD/gw/plc"
            cmd = decode_payload(data)
            assert cmd.seq is None and cmd.timestamp is not None and cmd.timestamp >= ts
            assert [(x.name, x.alias, x.datatype, x.value_field, x.raw) for x in cmd.metrics] == [
                (None, 1, None, "int_value", 0xFFFFFFFB)]
            # a metric born without alias goes by name
            await h.send_dcmd("G1", "gw", "plc", "B3:0/0", False, "Boolean")
            _, data = await e.mqtt.receive()
            assert [(x.name, x.alias, x.raw) for x in decode_payload(data).metrics] == [("B3:0/0", None, False)]

            # seq wraps 255 -> 0 over every message of the node
            for i in range(300):
                await e.send("DDATA", "plc", [m(None, "Int16", i, alias=1)])
            await h.wait_for(lambda msg: msg.message_type == "DDATA" and msg.metrics != []
                             and msg.metrics[0].value == 299, WAIT)
            assert h.value("G1", "gw", "plc", "N7:0").value == 299

            # a device dies and is born again; a DDEATH ends only that device
            await e.send("DDEATH", "plc", [])
            await h.wait_for(is_type("DDEATH"), WAIT)
            assert not h.device_online("G1", "gw", "plc") and h.node_online("G1", "gw")
            mark = len(h.messages)
            await e.send("DBIRTH", "plc", dbirth_metrics())
            await h.wait_for(is_type("DBIRTH"), WAIT, since=mark)
            assert h.device_online("G1", "gw", "plc")

            # rebirth: NCMD by name, Boolean true, no alias, no seq; the node answers in the same session
            mark = len(h.messages)
            await h.send_rebirth("G1", "gw")
            topic, data = await e.mqtt.receive()
            assert topic == "spBv1.0/G1/NCMD/gw"
            ncmd = decode_payload(data)
            assert ncmd.seq is None and ncmd.timestamp is not None
            assert [(x.name, x.alias, x.value) for x in ncmd.metrics] == [("Node Control/Rebirth", None, True)]
            await e.nbirth(0, [m("Properties/OS", "String", "Linux", alias=10), m("Links up", "UInt8", 1, alias=11)])
            await e.send("DBIRTH", "plc", dbirth_metrics())
            await h.wait_for(is_type("DBIRTH"), WAIT, since=mark)
            assert h.value("G1", "gw", "plc", "N7:0").value == -3

            # the Will NDEATH: the node and its devices go offline
            await e.mqtt.drop()
            death = await h.wait_for(is_type("NDEATH", "gw"), WAIT)
            assert death.metric("bdSeq") is not None
            assert not h.node_online("G1", "gw") and not h.device_online("G1", "gw", "plc")
        # wait_for also answers from the messages already received, and times out with a clear error
        assert await h.wait_for(is_type("NDEATH", "gw"), 0.1) is death
        with pytest.raises(TimeoutError, match=r"no matching Sparkplug message within 0\.2 s"):
            await h.wait_for(lambda msg: False, 0.2)
        assert h.violations == [], h.violations
        kinds = [msg.message_type for msg in h.messages if msg.message_type != "STATE"]
        assert kinds.count("NBIRTH") == 2 and kinds.count("NDEATH") == 1 and kinds.count("DCMD") == 2


async def test_misbehaving_edge_node_gives_exactly_its_violations(broker: int) -> None:
    async with SparkplugHost("127.0.0.1", broker) as h:
        async with edge(broker, "G1", "bad", will_bdseq=7) as e:
            await e.nbirth(6)  # the Will says 7: the NDEATH will not match
            await e.send("DDATA", "plc", [m(None, "Int16", 1, alias=1)])  # 1. before its DBIRTH
            await e.send("DBIRTH", "plc", dbirth_metrics())
            await e.send("DDATA", "plc", [m(None, "Int16", 2, alias=1)], seq=4)  # 2. seq gap: 3 expected
            await e.send("DDATA", "plc", [m(None, "Int16", 3, alias=99)])  # 3. alias never declared
            await e.send("DDATA", "plc", [m(None, "Int16", 4, alias=1)])
            await h.wait_for(lambda msg: msg.metrics != [] and msg.metrics[0].value == 4, WAIT)
            await e.mqtt.drop()  # 4. Will NDEATH with bdSeq 7, NBIRTH said 6
            await h.wait_for(is_type("NDEATH", "bad"), WAIT)
        # a garbage payload on a Sparkplug topic
        async with edge(broker, "G1", "noise", will_bdseq=0) as junk:
            await junk.mqtt.publish("spBv1.0/G1/NDATA/noise", b"\xff\xff\xff")
            await h.wait_for(is_type("NDATA", "noise"), WAIT)
    expected = [
        "DDATA G1/bad/plc (#1): DDATA before a DBIRTH of device 'plc'",
        "DDATA G1/bad/plc (#3): seq 4 after 2, expected 3",
        "DDATA G1/bad/plc (#4): alias 99 is not declared in the current DBIRTH",
        "NDEATH G1/bad (#6): NDEATH bdSeq 7 matches neither the current NBIRTH's bdSeq 6",
        "NDATA G1/noise (#7): payload does not decode as a Sparkplug B Payload",
    ]
    assert len(h.violations) == len(expected), "\n".join(h.violations)
    for line, start in zip(h.violations, expected, strict=True):
        assert line.startswith(start), (line, start)
    assert h.node_online("G1", "bad")  # a non-matching NDEATH does not end the session (5.4)


async def test_retained_birth_is_seen_as_retained(broker: int) -> None:
    async with SparkplugHost("127.0.0.1", broker) as h, edge(broker, "G1", "r", will_bdseq=0) as e:
        await e.nbirth(0, retain=True)
        msg = await h.wait_for(is_type("NBIRTH"), WAIT)
        assert msg.retain
        assert len(h.violations) == 1 and "retained" in h.violations[0]


async def test_state_birth_and_death_certificates(broker: int) -> None:
    """4.2.3 / 5.13 / 5.14: JSON, QoS 1, retained; the birth repeats the Will's timestamp; a clean exit
    publishes offline with a newer timestamp; an own offline STATE while online is answered (5.3)."""
    async with SparkplugHost("127.0.0.1", broker) as watcher:
        async with SparkplugHost("127.0.0.1", broker, primary_host_id="scada") as h:
            await h.publish_state(True)
            birth = await watcher.wait_for(is_type("STATE"), WAIT)
            assert birth.topic == "spBv1.0/STATE/scada" and birth.qos == 1 and birth.retain
            assert birth.state == {"online": True, "timestamp": h.connect_timestamp}
            # somebody delivers an offline STATE for us: we republish online with the same timestamp
            async with edge(broker, "G", "liar", will_bdseq=0) as liar:
                await liar.mqtt.publish("spBv1.0/STATE/scada", json.dumps(
                    {"online": False, "timestamp": now_ms()}).encode())
                lie = await watcher.wait_for(lambda msg: msg.state is not None and msg.state["online"] is False,
                                             WAIT)
            again = await watcher.wait_for(lambda msg: msg.state is not None and msg.state["online"] is True,
                                           WAIT, since=lie.index + 1)
            assert again.state == {"online": True, "timestamp": h.connect_timestamp}
        death = await watcher.wait_for(lambda msg: msg.message_type == "STATE" and msg.state is not None
                                       and msg.state["online"] is False and msg.qos == 1 and msg.retain, WAIT)
        assert death.state is not None and death.state["timestamp"] > h.connect_timestamp
    # the liar's QoS 0, unretained STATE is the only violation seen
    assert len(watcher.violations) == 2, watcher.violations
    assert "QoS 0" in watcher.violations[0] and "not retained" in watcher.violations[1]


async def test_cli_will_and_exit_status(broker: int, tmp_path: Path) -> None:
    """The CLI as primary host: STATE online at start, its Will (offline, same timestamp) when killed;
    with --seconds it exits 1 when it saw a violation and prints it."""
    async with SparkplugHost("127.0.0.1", broker) as watcher:
        proc = await asyncio.create_subprocess_exec(
            sys.executable, str(HOST_PY), "--broker", f"127.0.0.1:{broker}", "--primary-host-id", "cli-host",
            stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.DEVNULL)
        try:
            online = await watcher.wait_for(lambda msg: msg.topic == "spBv1.0/STATE/cli-host", 15)
            assert online.state is not None and online.state["online"] is True
        finally:
            proc.send_signal(signal.SIGKILL)
            await proc.wait()
        will = await watcher.wait_for(lambda msg: msg.topic == "spBv1.0/STATE/cli-host"
                                      and msg.index > online.index, WAIT)
        assert will.state == {"online": False, "timestamp": online.state["timestamp"]}

        proc = await asyncio.create_subprocess_exec(
            sys.executable, str(HOST_PY), "--broker", f"127.0.0.1:{broker}", "--seconds", "3",
            "--primary-host-id", "cli-2", stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
        # its STATE online means it has subscribed (5.13); its 3 seconds run from there
        await watcher.wait_for(lambda msg: msg.topic == "spBv1.0/STATE/cli-2", 15)
        async with edge(broker, "G", "cli", will_bdseq=0) as e:
            await e.send("NDATA", None, [m("x", "Int16", 1)])
        out, err = await asyncio.wait_for(proc.communicate(), 20)
        assert proc.returncode == 1, (out, err)
        assert b"VIOLATION NDATA G/cli (#" in out and b"no NBIRTH was seen" in out


async def test_rebirth_unknown_asks_a_node_already_running(broker: int) -> None:
    """5.17: a host that joins late requests a rebirth instead of reporting data before birth."""
    async with edge(broker, "G", "early", will_bdseq=0) as e:
        await e.nbirth(0)
        async with SparkplugHost("127.0.0.1", broker, rebirth_unknown=True) as h:
            await e.send("NDATA", None, [m("bdSeq", "Int64", 0)])
            topic, data = await e.mqtt.receive()
            assert topic == "spBv1.0/G/NCMD/early"
            assert decode_payload(data).metrics[0].name == "Node Control/Rebirth"
            await e.nbirth(0)
            await h.wait_for(is_type("NBIRTH"), WAIT)
            assert h.node_online("G", "early") and h.violations == []
