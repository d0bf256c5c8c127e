#!/usr/bin/env python3
"""A Sparkplug 3.0 host application for tests: it watches edge nodes and reports every rule they break.

Written from the Eclipse Sparkplug Specification 3.0.0 (the AsciiDoc chapters of tag v3.0.0 of
eclipse-sparkplug/sparkplug) alone, as a second reading next to the gateway's edge node.  Section
numbers are those of the rendered specification; the tck-id of each normative statement is quoted
where a check rests on one.

  [4.1]      topic namespace: namespace/group_id/message_type/edge_node_id/[device_id]
  [4.2.1.1]  NBIRTH: QoS 0, not retained, seq 0, timestamp, every metric with name/datatype/value,
             a bdSeq metric, 'Node Control/Rebirth' Boolean false
  [4.2.1.3]  NDEATH: the Will Message; only the bdSeq metric; no seq
  [4.2.2.x]  DBIRTH / DDATA / DDEATH: seq one more than the node's previous message, wrapping at 255
  [4.2.3]    STATE: spBv1.0/STATE/<sparkplug_host_id>, JSON {"online": bool, "timestamp": ms},
             QoS 1, retained; the birth repeats the timestamp of the Will's death certificate
  [5.3, 5.13, 5.14]  host session: Will first, subscribe, then STATE online; STATE offline before
             an intentional disconnect; republish online when our own offline STATE is delivered
  [5.4]      bdSeq metric is Int64 and equals the Will's value
  [5.5]      a Will NDEATH after an NDEATH already published carries the same bdSeq: ignored
  [5.9]      message ordering by seq (reorder timeout: see reading 3 below)
  [5.16]     every birth metric carries its current value, or is_null=true and no value
  [5.17]     Rebirth: NCMD 'Node Control/Rebirth' = true, no alias on that metric; the NBIRTH that
             answers a rebirth keeps the bdSeq of the session
  [6.4.5]    Payload: timestamp (ms UTC), seq 0..255 on everything from an edge node but NDEATH
  [6.4.6]    Metric: name unless aliased; alias unique across the node; births carry name and
             alias, DATA/CMD only the alias; timestamp on every metric of births and DATA;
             datatype in births, SHOULD NOT in DATA/CMD
  [6.4.9.1]  Quality property: type Int32 (3), int_value 0 BAD / 192 GOOD / 500 STALE
  [6.4.17]   datatype -> protobuf field: Int8..Int32, UInt8..UInt32 in int_value (uint32);
             Int64, UInt64, DateTime in long_value (uint64); arrays packed little-endian in bytes
  [6.4.23-25] NCMD/DCMD: timestamp, no seq, QoS 0, not retained; NDEATH: no seq

Readings chosen where the specification is open or contradicts itself:
  1. NBIRTH seq.  4.2.1.1.2 (tck-id-topics-nbirth-seq-num) says it MUST be 0; 5.4 and 6.4.5/6.4.19
     allow 0..255.  Only 0 satisfies every statement, so anything else is a violation.
  2. Signed Int8/Int16/Int32 in a uint32 int_value (6.4.17 gives no rule).  Decoding accepts the
     value two's complement in its own width (Int16 -2 = 0xFFFE) and sign-extended to 32 bits
     (0xFFFFFFFE, what a protobuf library writes for a cast int); bits beyond either are a violation.
     Commands are encoded sign-extended to 32 bits unless send_dcmd(..., int_form="width").
  3. Reorder timeout 0 (5.9 allows it where the server keeps the order): one MQTT server, one
     publisher, so any seq gap or repetition is a violation at once.  The expected seq then
     resynchronises on the received one, so one gap is one violation.
  4. "Aliases are used" (6.4.6) is read per metric: a DATA metric whose birth declared an alias
     must carry that alias and no name; a metric born without alias is sent by name.
  5. A DBIRTH may follow DDATA/NDATA of the same birth sequence (a device that comes online later,
     5.6: "as long as an NBIRTH has been sent previously"); 6.4.20's "immediately after the NBIRTH"
     is not checked.  A DDEATH for a device never born is accepted.
  6. NDEATH bdSeq: equal to the current NBIRTH's -> node offline; equal to a bdSeq of an ended or
     superseded session -> a late or duplicate Will (5.4, 5.5), ignored; anything else is a
     violation.  An NBIRTH with a new bdSeq while online starts a new session (its NDEATH may come
     late, 5.4), unless a rebirth was requested since the last NBIRTH: then it breaks 5.17.
  7. Commands: DCMD/NCMD metrics carry no datatype (6.4.6 SHOULD NOT) unless include_datatype=True,
     carry the alias instead of the name when the DBIRTH declared one (6.4.6), and a metric
     timestamp (MAY).  UInt32 travels in int_value as 6.4.17 says; a UInt32 in long_value is a
     violation (older Tahu versions did that).
  8. Data from a node or device the host has not seen born is a violation; the host must be started
     before the edge node, or pass rebirth_unknown=True to request a rebirth (5.17) instead.
  9. DATA that arrives after a rebirth request but before the new NBIRTH is not checked: it may have
     been in flight (5.17 "immediately stop sending DATA" cannot be timed from the host).
 10. The host connects with MQTT 5 (Clean Start, session expiry 0, 5.3) and subscribes with
     "retain as published", so a retained NBIRTH/DATA is seen as retained and reported (4.2.1.1.2),
     and with QoS 1, so a birth or data message published with QoS 1 is seen and reported.

CLI: python sparkplug_host.py --broker 127.0.0.1:1883 [--primary-host-id X] [--seconds N]
prints every decoded message and violation; exit status 1 on any violation.
"""
from __future__ import annotations

import argparse
import asyncio
import enum
import json
import struct
import sys
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any, Literal, NamedTuple

NAMESPACE = "spBv1.0"
REBIRTH = "Node Control/Rebirth"
BDSEQ = "bdSeq"
QUALITY = "Quality"
QUALITY_CODES = {0: "BAD", 192: "GOOD", 500: "STALE"}  # 6.4.9.1


class DataType(enum.IntEnum):
    """The DataType enum of sparkplug_b.proto (6.4.1, 6.4.16)."""

    Unknown = 0
    Int8 = 1
    Int16 = 2
    Int32 = 3
    Int64 = 4
    UInt8 = 5
    UInt16 = 6
    UInt32 = 7
    UInt64 = 8
    Float = 9
    Double = 10
    Boolean = 11
    String = 12
    DateTime = 13
    Text = 14
    UUID = 15
    DataSet = 16
    Bytes = 17
    File = 18
    Template = 19
    PropertySet = 20
    PropertySetList = 21
    Int8Array = 22
    Int16Array = 23
    Int32Array = 24
    Int64Array = 25
    UInt8Array = 26
    UInt16Array = 27
    UInt32Array = 28
    UInt64Array = 29
    FloatArray = 30
    DoubleArray = 31
    BooleanArray = 32
    StringArray = 33
    DateTimeArray = 34


def datatype_by_name(name: str) -> DataType:
    """'Int16', 'int16' or 'INT16' -> DataType.Int16; a clear error for anything else."""
    for member in DataType:
        if member.name.lower() == name.lower():
            return member
    known = ", ".join(m.name for m in DataType if m is not DataType.Unknown)
    raise ValueError(f"unknown Sparkplug datatype {name!r}; use one of {known}")


def datatype_name(code: int | None) -> str:
    if code is None:
        return "-"
    try:
        return DataType(code).name
    except ValueError:
        return f"invalid({code})"


# --------------------------------------------------------------------------------------------
# Protocol Buffers wire format (proto2), written from the encoding rules: tags are varints of
# (field_number << 3 | wire_type); wire types 0 varint, 1 fixed64, 2 length-delimited, 5 fixed32.
# Sparkplug uses uint32/uint64/bool/float/double/string/bytes and nested messages only: no zigzag.
# --------------------------------------------------------------------------------------------

class DecodeError(ValueError):
    """A payload that is not a valid Sparkplug B protobuf message."""


VARINT, FIXED64, LENGTH, FIXED32 = 0, 1, 2, 5
_MASK32 = (1 << 32) - 1
_MASK64 = (1 << 64) - 1


def encode_varint(value: int) -> bytes:
    if value < 0:
        raise ValueError(f"varint of a negative number {value}: encode it two's complement first")
    if value > _MASK64:
        raise ValueError(f"varint {value} does not fit 64 bits")
    out = bytearray()
    while True:
        byte = value & 0x7F
        value >>= 7
        if value:
            out.append(byte | 0x80)
        else:
            out.append(byte)
            return bytes(out)


def decode_varint(data: bytes, pos: int) -> tuple[int, int]:
    """The varint at data[pos:] and the position after it; at most 10 bytes (64 bits)."""
    result = 0
    for i in range(10):
        if pos + i >= len(data):
            raise DecodeError(f"varint runs past the end of the data at byte {pos}")
        byte = data[pos + i]
        result |= (byte & 0x7F) << (7 * i)
        if not byte & 0x80:
            return result & _MASK64, pos + i + 1
    raise DecodeError(f"varint longer than 10 bytes at byte {pos}")


def iter_fields(data: bytes) -> Iterator[tuple[int, int, int | bytes]]:
    """(field number, wire type, value): an int for varint/fixed fields, bytes for length-delimited."""
    pos = 0
    while pos < len(data):
        key, pos = decode_varint(data, pos)
        number, wire = key >> 3, key & 7
        if number == 0:
            raise DecodeError(f"field number 0 at byte {pos}")
        value: int | bytes
        if wire == VARINT:
            value, pos = decode_varint(data, pos)
        elif wire == FIXED64:
            if pos + 8 > len(data):
                raise DecodeError(f"fixed64 field {number} runs past the end")
            value = int.from_bytes(data[pos:pos + 8], "little")
            pos += 8
        elif wire == FIXED32:
            if pos + 4 > len(data):
                raise DecodeError(f"fixed32 field {number} runs past the end")
            value = int.from_bytes(data[pos:pos + 4], "little")
            pos += 4
        elif wire == LENGTH:
            length, pos = decode_varint(data, pos)
            if pos + length > len(data):
                raise DecodeError(f"length-delimited field {number} ({length} bytes) runs past the end")
            value = data[pos:pos + length]
            pos += length
        else:
            raise DecodeError(f"wire type {wire} (groups or invalid) for field {number}")
        yield number, wire, value


def _key(number: int, wire: int) -> bytes:
    return encode_varint(number << 3 | wire)


def field_varint(number: int, value: int) -> bytes:
    return _key(number, VARINT) + encode_varint(value)


def field_bytes(number: int, value: bytes) -> bytes:
    return _key(number, LENGTH) + encode_varint(len(value)) + value


def field_float(number: int, value: float) -> bytes:
    return _key(number, FIXED32) + struct.pack("<f", value)


def field_double(number: int, value: float) -> bytes:
    return _key(number, FIXED64) + struct.pack("<d", value)


def _expect(wire: int, wanted: int, what: str) -> None:
    if wire != wanted:
        raise DecodeError(f"{what}: wire type {wire}, the schema says {wanted}")


def _int(value: int | bytes, wire: int, what: str) -> int:
    _expect(wire, VARINT, what)
    assert isinstance(value, int)
    return value


def _bytes(value: int | bytes, wire: int, what: str) -> bytes:
    _expect(wire, LENGTH, what)
    assert isinstance(value, bytes)
    return value


def _str(value: int | bytes, wire: int, what: str) -> str:
    try:
        return _bytes(value, wire, what).decode("utf-8")
    except UnicodeDecodeError as exc:
        raise DecodeError(f"{what}: not UTF-8 ({exc})") from exc


def _f32(value: int | bytes, wire: int, what: str) -> float:
    _expect(wire, FIXED32, what)
    assert isinstance(value, int)
    return float(struct.unpack("<f", value.to_bytes(4, "little"))[0])


def _f64(value: int | bytes, wire: int, what: str) -> float:
    _expect(wire, FIXED64, what)
    assert isinstance(value, int)
    return float(struct.unpack("<d", value.to_bytes(8, "little"))[0])


# --------------------------------------------------------------------------------------------
# Sparkplug B messages (6.4.1).  Only what a host needs is modelled in full; DataSet and Template
# are decoded into plain dicts and lists.
# --------------------------------------------------------------------------------------------

# oneof value field numbers shared by Metric (10..16), PropertyValue (3..8) and the DataSet/Template
# values, with the protobuf type each carries.
_VALUE_KINDS = ("int_value", "long_value", "float_value", "double_value", "boolean_value", "string_value",
                "bytes_value")


@dataclass
class PropertyValue:
    type: int | None = None
    is_null: bool = False
    value_field: str | None = None
    raw: Any = None

    @property
    def value(self) -> Any:
        if self.type is None or self.value_field is None:
            return self.raw
        try:
            return interpret(self.type, self.value_field, self.raw)
        except ValueError:
            return self.raw


@dataclass
class PropertySet:
    keys: list[str] = field(default_factory=list)
    values: list[PropertyValue] = field(default_factory=list)

    def as_dict(self) -> dict[str, PropertyValue]:
        return dict(zip(self.keys, self.values, strict=False))  # unequal sizes: see _check_quality


@dataclass
class Metric:
    """One Payload.Metric as it was on the wire, plus what the host resolved from the births."""

    name: str | None = None
    alias: int | None = None
    timestamp: int | None = None
    datatype: int | None = None
    is_historical: bool = False
    is_transient: bool = False
    is_null: bool = False
    metadata: dict[str, Any] | None = None
    properties: PropertySet | None = None
    value_field: str | None = None  # which member of the oneof was present, e.g. "int_value"
    raw: Any = None  # the oneof member as protobuf decoded it (uint32 for Int16, etc.)
    value: Any = None  # the value interpreted with the datatype (own, or the birth's through alias)
    resolved_name: str | None = None  # the name, or the name the birth gave the alias
    resolved_datatype: int | None = None  # the datatype, or the birth's

    @property
    def quality(self) -> int | None:
        """The 'Quality' property (6.4.9.1); None when absent, which means GOOD."""
        if self.properties is None:
            return None
        prop = self.properties.as_dict().get(QUALITY)
        if prop is None or not isinstance(prop.raw, int) or isinstance(prop.raw, bool):
            return None
        return int(prop.value)

    def describe(self) -> str:
        label = self.resolved_name if self.resolved_name is not None else f"alias {self.alias}"
        dt = datatype_name(self.resolved_datatype if self.resolved_datatype is not None else self.datatype)
        val = "null" if self.is_null else repr(self.value)
        qual = self.quality
        extra = f" quality={qual}" if qual is not None else ""
        alias = f" #{self.alias}" if self.alias is not None and self.resolved_name is not None else ""
        return f"{label}{alias}:{dt}={val}{extra}"


@dataclass
class Payload:
    timestamp: int | None = None
    metrics: list[Metric] = field(default_factory=list)
    seq: int | None = None
    uuid: str | None = None
    body: bytes | None = None


def _decode_value_member(number: int, first: int, wire: int, value: int | bytes, what: str) -> tuple[str, Any]:
    """Decode the oneof member `number` of a value oneof whose int_value has field number `first`."""
    kind = _VALUE_KINDS[number - first]
    if kind == "int_value":
        return kind, _int(value, wire, what) & _MASK32  # uint32: protobuf keeps the low 32 bits
    if kind == "long_value":
        return kind, _int(value, wire, what)
    if kind == "float_value":
        return kind, _f32(value, wire, what)
    if kind == "double_value":
        return kind, _f64(value, wire, what)
    if kind == "boolean_value":
        return kind, _int(value, wire, what) != 0
    if kind == "string_value":
        return kind, _str(value, wire, what)
    return kind, _bytes(value, wire, what)


def decode_property_value(data: bytes) -> PropertyValue:
    pv = PropertyValue()
    for number, wire, value in iter_fields(data):
        if number == 1:
            pv.type = _int(value, wire, "PropertyValue.type") & _MASK32
        elif number == 2:
            pv.is_null = _int(value, wire, "PropertyValue.is_null") != 0
        elif 3 <= number <= 8:
            pv.value_field, pv.raw = _decode_value_member(number, 3, wire, value, "PropertyValue value")
        elif number == 9:
            pv.value_field, pv.raw = "propertyset_value", decode_property_set(_bytes(value, wire, "propertyset"))
        elif number == 10:
            pv.value_field = "propertysets_value"
            pv.raw = [decode_property_set(_bytes(v, w, "PropertySetList.propertyset"))
                      for n, w, v in iter_fields(_bytes(value, wire, "propertysets")) if n == 1]
    return pv


def decode_property_set(data: bytes) -> PropertySet:
    ps = PropertySet()
    for number, wire, value in iter_fields(data):
        if number == 1:
            ps.keys.append(_str(value, wire, "PropertySet.keys"))
        elif number == 2:
            ps.values.append(decode_property_value(_bytes(value, wire, "PropertySet.values")))
    return ps


def _decode_metadata(data: bytes) -> dict[str, Any]:
    names = {1: "is_multi_part", 2: "content_type", 3: "size", 4: "seq", 5: "file_name", 6: "file_type",
             7: "md5", 8: "description"}
    out: dict[str, Any] = {}
    for number, wire, value in iter_fields(data):
        name = names.get(number)
        if name is None:
            continue
        if number in (1, 3, 4):
            raw = _int(value, wire, f"MetaData.{name}")
            out[name] = raw != 0 if number == 1 else raw
        else:
            out[name] = _str(value, wire, f"MetaData.{name}")
    return out


def _repeated_uint32(wire: int, value: int | bytes, what: str) -> list[int]:
    """A repeated uint32 element, packed (wire type 2) or not (wire type 0): parsers accept both."""
    if wire == LENGTH:
        assert isinstance(value, bytes)
        out, pos = [], 0
        while pos < len(value):
            item, pos = decode_varint(value, pos)
            out.append(item & _MASK32)
        return out
    return [_int(value, wire, what) & _MASK32]


def _decode_dataset(data: bytes) -> dict[str, Any]:
    ds: dict[str, Any] = {"num_of_columns": None, "columns": [], "types": [], "rows": []}
    for number, wire, value in iter_fields(data):
        if number == 1:
            ds["num_of_columns"] = _int(value, wire, "DataSet.num_of_columns")
        elif number == 2:
            ds["columns"].append(_str(value, wire, "DataSet.columns"))
        elif number == 3:
            ds["types"].extend(_repeated_uint32(wire, value, "DataSet.types"))
        elif number == 4:
            row: list[Any] = []
            for n, w, v in iter_fields(_bytes(value, wire, "DataSet.rows")):
                if n == 1:
                    element: Any = None
                    for en, ew, ev in iter_fields(_bytes(v, w, "Row.elements")):
                        if 1 <= en <= 6:
                            element = _decode_value_member(en, 1, ew, ev, "DataSetValue")[1]
                    row.append(element)
            ds["rows"].append(row)
    return ds


def _decode_template(data: bytes) -> dict[str, Any]:
    tpl: dict[str, Any] = {"version": None, "metrics": [], "parameters": [], "template_ref": None,
                           "is_definition": None}
    for number, wire, value in iter_fields(data):
        if number == 1:
            tpl["version"] = _str(value, wire, "Template.version")
        elif number == 2:
            tpl["metrics"].append(decode_metric(_bytes(value, wire, "Template.metrics")))
        elif number == 3:
            param: dict[str, Any] = {}
            for n, w, v in iter_fields(_bytes(value, wire, "Template.parameters")):
                if n == 1:
                    param["name"] = _str(v, w, "Parameter.name")
                elif n == 2:
                    param["type"] = _int(v, w, "Parameter.type") & _MASK32
                elif 3 <= n <= 8:
                    param["value"] = _decode_value_member(n, 3, w, v, "Parameter value")[1]
            tpl["parameters"].append(param)
        elif number == 4:
            tpl["template_ref"] = _str(value, wire, "Template.template_ref")
        elif number == 5:
            tpl["is_definition"] = _int(value, wire, "Template.is_definition") != 0
    return tpl


def decode_metric(data: bytes) -> Metric:
    m = Metric()
    for number, wire, value in iter_fields(data):
        if number == 1:
            m.name = _str(value, wire, "Metric.name")
        elif number == 2:
            m.alias = _int(value, wire, "Metric.alias")
        elif number == 3:
            m.timestamp = _int(value, wire, "Metric.timestamp")
        elif number == 4:
            m.datatype = _int(value, wire, "Metric.datatype") & _MASK32
        elif number == 5:
            m.is_historical = _int(value, wire, "Metric.is_historical") != 0
        elif number == 6:
            m.is_transient = _int(value, wire, "Metric.is_transient") != 0
        elif number == 7:
            m.is_null = _int(value, wire, "Metric.is_null") != 0
        elif number == 8:
            m.metadata = _decode_metadata(_bytes(value, wire, "Metric.metadata"))
        elif number == 9:
            m.properties = decode_property_set(_bytes(value, wire, "Metric.properties"))
        elif 10 <= number <= 16:
            m.value_field, m.raw = _decode_value_member(number, 10, wire, value, "Metric value")
        elif number == 17:
            m.value_field, m.raw = "dataset_value", _decode_dataset(_bytes(value, wire, "Metric.dataset_value"))
        elif number == 18:
            m.value_field, m.raw = "template_value", _decode_template(_bytes(value, wire, "Metric.template_value"))
        elif number == 19:
            m.value_field, m.raw = "extension_value", _bytes(value, wire, "Metric.extension_value")
    m.resolved_name = m.name
    m.resolved_datatype = m.datatype
    m.value = None if m.is_null else m.raw
    if m.datatype is not None and m.value_field is not None and not m.is_null:
        try:  # the value as its own datatype reads it; the Checker re-reads DATA metrics with the birth's
            m.value = interpret(m.datatype, m.value_field, m.raw)
        except ValueError:
            pass
    return m


def decode_payload(data: bytes) -> Payload:
    """Decode a Sparkplug B Payload; raises DecodeError for anything the schema does not allow."""
    p = Payload()
    for number, wire, value in iter_fields(data):
        if number == 1:
            p.timestamp = _int(value, wire, "Payload.timestamp")
        elif number == 2:
            p.metrics.append(decode_metric(_bytes(value, wire, "Payload.metrics")))
        elif number == 3:
            p.seq = _int(value, wire, "Payload.seq")
        elif number == 4:
            p.uuid = _str(value, wire, "Payload.uuid")
        elif number == 5:
            p.body = _bytes(value, wire, "Payload.body")
    return p


# --------------------------------------------------------------------------------------------
# Values: datatype <-> oneof member (6.4.17)
# --------------------------------------------------------------------------------------------

_INT_WIDTH = {DataType.Int8: 8, DataType.Int16: 16, DataType.Int32: 32}
_UINT_WIDTH = {DataType.UInt8: 8, DataType.UInt16: 16, DataType.UInt32: 32}
# array datatype -> struct format of one element (little-endian, 6.4.17 "Array Types")
_ARRAY_FORMAT = {DataType.Int8Array: "b", DataType.Int16Array: "h", DataType.Int32Array: "i",
                 DataType.Int64Array: "q", DataType.UInt8Array: "B", DataType.UInt16Array: "H",
                 DataType.UInt32Array: "I", DataType.UInt64Array: "Q", DataType.FloatArray: "f",
                 DataType.DoubleArray: "d", DataType.DateTimeArray: "q"}


def expected_field(datatype: int) -> str | None:
    """The oneof member 6.4.17 assigns to a datatype; None when there is none (Unknown, invalid)."""
    try:
        dt = DataType(datatype)
    except ValueError:
        return None
    if dt in _INT_WIDTH or dt in _UINT_WIDTH:
        return "int_value"
    if dt in (DataType.Int64, DataType.UInt64, DataType.DateTime):
        return "long_value"
    if dt is DataType.Float:
        return "float_value"
    if dt is DataType.Double:
        return "double_value"
    if dt is DataType.Boolean:
        return "boolean_value"
    if dt in (DataType.String, DataType.Text, DataType.UUID):
        return "string_value"
    if dt in (DataType.Bytes, DataType.File) or dt in _ARRAY_FORMAT or dt in (DataType.BooleanArray,
                                                                              DataType.StringArray):
        return "bytes_value"
    if dt is DataType.DataSet:
        return "dataset_value"
    if dt is DataType.Template:
        return "template_value"
    if dt is DataType.PropertySet:
        return "propertyset_value"
    if dt is DataType.PropertySetList:
        return "propertysets_value"
    return None


def interpret(datatype: int, value_field: str, raw: Any) -> Any:
    """The value of a oneof member read as `datatype`; ValueError when they do not fit together."""
    wanted = expected_field(datatype)
    name = datatype_name(datatype)
    if wanted is None:
        raise ValueError(f"datatype {name} has no value field")
    if value_field != wanted and not (datatype == DataType.UInt32 and value_field == "long_value"):
        raise ValueError(f"datatype {name} travels in {wanted} (6.4.17), not in {value_field}")
    dt = DataType(datatype)
    if dt in _INT_WIDTH:
        width = _INT_WIDTH[dt]
        low = raw & ((1 << width) - 1)
        high = raw >> width
        sign = low >> (width - 1)
        if high != 0 and not (sign and high == (_MASK32 >> width)):
            raise ValueError(f"{name} int_value 0x{raw:X} is neither {width}-bit two's complement nor "
                             f"sign-extended to 32 bits")
        return low - (1 << width) if sign else low
    if dt in _UINT_WIDTH:
        if raw >> _UINT_WIDTH[dt]:
            raise ValueError(f"{name} value {raw} is out of range")
        return raw
    if dt is DataType.Int64:
        return raw - (1 << 64) if raw >> 63 else raw
    if dt in _ARRAY_FORMAT:
        fmt = _ARRAY_FORMAT[dt]
        size = struct.calcsize(fmt)
        if len(raw) % size:
            raise ValueError(f"{name} of {len(raw)} bytes is not a whole number of {size}-byte elements")
        return list(struct.unpack(f"<{len(raw) // size}{fmt}", raw))
    if dt is DataType.BooleanArray:
        if len(raw) < 4:
            raise ValueError(f"BooleanArray of {len(raw)} bytes has no 4-byte count")
        count = int.from_bytes(raw[:4], "little")
        bits = raw[4:]
        if len(bits) != (count + 7) // 8:
            raise ValueError(f"BooleanArray of {count} values needs {(count + 7) // 8} bytes, has {len(bits)}")
        return [bool(bits[i // 8] >> (7 - i % 8) & 1) for i in range(count)]  # first value in the MSB
    if dt is DataType.StringArray:
        if raw and not raw.endswith(b"\0"):
            raise ValueError("StringArray does not end with a NUL")
        try:
            return [s.decode("utf-8") for s in raw.split(b"\0")[:-1]]
        except UnicodeDecodeError as exc:
            raise ValueError(f"StringArray element not UTF-8: {exc}") from exc
    return raw


def encode_value(datatype: DataType, value: Any, *, int_form: Literal["sign32", "width"] = "sign32",
                 ) -> tuple[str, Any]:
    """(oneof member, protobuf value) for a Python value of `datatype` (6.4.17)."""
    wanted = expected_field(datatype)
    if datatype in _INT_WIDTH:
        width = _INT_WIDTH[datatype]
        if not -(1 << (width - 1)) <= int(value) < (1 << (width - 1)):
            raise ValueError(f"{value} does not fit {datatype.name}")
        return "int_value", int(value) & (_MASK32 if int_form == "sign32" else (1 << width) - 1)
    if datatype in _UINT_WIDTH:
        if not 0 <= int(value) < (1 << _UINT_WIDTH[datatype]):
            raise ValueError(f"{value} does not fit {datatype.name}")
        return "int_value", int(value)
    if datatype in (DataType.Int64, DataType.UInt64, DataType.DateTime):
        return "long_value", int(value) & _MASK64
    if datatype in _ARRAY_FORMAT:
        return "bytes_value", struct.pack(f"<{len(value)}{_ARRAY_FORMAT[datatype]}", *value)
    if datatype is DataType.BooleanArray:
        bits = bytearray((len(value) + 7) // 8)
        for i, bit in enumerate(value):
            if bit:
                bits[i // 8] |= 0x80 >> (i % 8)
        return "bytes_value", len(value).to_bytes(4, "little") + bytes(bits)
    if datatype is DataType.StringArray:
        return "bytes_value", b"".join(s.encode("utf-8") + b"\0" for s in value)
    if wanted in ("float_value", "double_value"):
        return wanted, float(value)
    if wanted == "boolean_value":
        return wanted, bool(value)
    if wanted in ("string_value", "bytes_value"):
        return wanted, value
    raise ValueError(f"encoding {datatype.name} values is not supported by this test host")


_METRIC_VALUE_NUMBER = {kind: 10 + i for i, kind in enumerate(_VALUE_KINDS)}
_PROPERTY_VALUE_NUMBER = {kind: 3 + i for i, kind in enumerate(_VALUE_KINDS[:6])}


def _encode_member(number: int, kind: str, raw: Any) -> bytes:
    if kind in ("int_value", "long_value"):
        return field_varint(number, raw)
    if kind == "float_value":
        return field_float(number, raw)
    if kind == "double_value":
        return field_double(number, raw)
    if kind == "boolean_value":
        return field_varint(number, 1 if raw else 0)
    if kind == "string_value":
        return field_bytes(number, raw.encode("utf-8"))
    return field_bytes(number, bytes(raw))


def encode_property_set(ps: PropertySet) -> bytes:
    out = bytearray()
    for key in ps.keys:
        out += field_bytes(1, key.encode("utf-8"))
    for pv in ps.values:
        body = bytearray()
        if pv.type is not None:
            body += field_varint(1, pv.type)
        if pv.is_null:
            body += field_varint(2, 1)
        if pv.value_field is not None:
            if pv.value_field == "propertyset_value":
                body += field_bytes(9, encode_property_set(pv.raw))
            else:
                body += _encode_member(_PROPERTY_VALUE_NUMBER[pv.value_field], pv.value_field, pv.raw)
        out += field_bytes(2, bytes(body))
    return bytes(out)


def encode_metric(m: Metric) -> bytes:
    out = bytearray()
    if m.name is not None:
        out += field_bytes(1, m.name.encode("utf-8"))
    if m.alias is not None:
        out += field_varint(2, m.alias)
    if m.timestamp is not None:
        out += field_varint(3, m.timestamp)
    if m.datatype is not None:
        out += field_varint(4, m.datatype)
    if m.is_historical:
        out += field_varint(5, 1)
    if m.is_transient:
        out += field_varint(6, 1)
    if m.is_null:
        out += field_varint(7, 1)
    if m.properties is not None:
        out += field_bytes(9, encode_property_set(m.properties))
    if m.value_field is not None:
        out += _encode_member(_METRIC_VALUE_NUMBER[m.value_field], m.value_field, m.raw)
    return bytes(out)


def encode_payload(p: Payload) -> bytes:
    out = bytearray()
    if p.timestamp is not None:
        out += field_varint(1, p.timestamp)
    for m in p.metrics:
        out += field_bytes(2, encode_metric(m))
    if p.seq is not None:
        out += field_varint(3, p.seq)
    if p.uuid is not None:
        out += field_bytes(4, p.uuid.encode("utf-8"))
    if p.body is not None:
        out += field_bytes(5, p.body)
    return bytes(out)


def make_metric(name: str | None, datatype: DataType | str | None, value: Any = None, *,
                alias: int | None = None, timestamp: int | None = None, is_null: bool = False,
                quality: int | None = None, with_datatype: bool = True,
                int_form: Literal["sign32", "width"] = "sign32") -> Metric:
    """A Metric ready for encode_payload; `datatype` decides the oneof member, `with_datatype`
    whether the datatype field itself goes on the wire."""
    dt = datatype_by_name(datatype) if isinstance(datatype, str) else datatype
    m = Metric(name=name, alias=alias, timestamp=timestamp, is_null=is_null,
               datatype=int(dt) if dt is not None and with_datatype else None)
    if not is_null and dt is not None and value is not None:
        m.value_field, m.raw = encode_value(dt, value, int_form=int_form)
        m.value = value
    if quality is not None:
        m.properties = PropertySet([QUALITY], [PropertyValue(type=int(DataType.Int32), value_field="int_value",
                                                             raw=quality & _MASK32)])
    m.resolved_name, m.resolved_datatype = name, int(dt) if dt is not None else None
    return m


def now_ms() -> int:
    return int(time.time() * 1000)


# --------------------------------------------------------------------------------------------
# Messages and the checks (sans I/O: feed() takes what MQTT delivered, the host does the I/O)
# --------------------------------------------------------------------------------------------

NODE_TYPES = ("NBIRTH", "NDEATH", "NDATA", "NCMD")
DEVICE_TYPES = ("DBIRTH", "DDEATH", "DDATA", "DCMD")


@dataclass
class Message:
    """One MQTT message under spBv1.0/#, decoded."""

    index: int
    topic: str
    namespace: str
    group_id: str | None
    message_type: str
    edge_node_id: str | None
    device_id: str | None
    payload: Payload | None = None
    host_id: str | None = None  # STATE only
    state: dict[str, Any] | None = None  # STATE only: the JSON object
    qos: int = 0
    retain: bool = False
    received_at: float = 0.0
    error: str | None = None  # why the payload could not be decoded
    violations: list[str] = field(default_factory=list)

    @property
    def metrics(self) -> list[Metric]:
        return self.payload.metrics if self.payload is not None else []

    def metric(self, name: str) -> Metric | None:
        """The first metric whose name (on the wire or through its alias) is `name`."""
        return next((m for m in self.metrics if m.resolved_name == name), None)

    def where(self) -> str:
        if self.message_type == "STATE":
            return f"STATE/{self.host_id}"
        dev = f"/{self.device_id}" if self.device_id is not None else ""
        return f"{self.message_type} {self.group_id}/{self.edge_node_id}{dev}"

    def __str__(self) -> str:
        head = f"#{self.index} {self.where()}"
        if self.error is not None:
            return f"{head} UNDECODABLE: {self.error}"
        if self.state is not None:
            return f"{head} {json.dumps(self.state)} qos={self.qos} retain={self.retain}"
        if self.payload is None:
            return head
        p = self.payload
        metrics = ", ".join(m.describe() for m in p.metrics)
        return f"{head} seq={p.seq} ts={p.timestamp} [{metrics}]"


class Value(NamedTuple):
    value: Any
    is_null: bool
    quality: int | None  # the Quality property (0 BAD, 192 GOOD, 500 STALE); None = absent = GOOD


@dataclass
class _MetricDef:
    name: str
    alias: int | None
    datatype: int | None


@dataclass
class _Scope:
    """The metrics born for the node itself (device None) or for one device."""

    online: bool = False
    by_name: dict[str, _MetricDef] = field(default_factory=dict)
    by_alias: dict[int, _MetricDef] = field(default_factory=dict)
    values: dict[str, Value] = field(default_factory=dict)


@dataclass
class _Node:
    node: _Scope = field(default_factory=_Scope)
    devices: dict[str, _Scope] = field(default_factory=dict)
    bdseq: int | None = None  # of the current NBIRTH
    old_bdseqs: set[int] = field(default_factory=set)  # sessions that ended or were superseded
    last_seq: int | None = None
    rebirth_requested: bool = False
    aliases: dict[int, str] = field(default_factory=dict)  # alias -> "node" or "device <id>", 6.4.6
    seen_birth: bool = False


def parse_topic(topic: str) -> tuple[str, str | None, str, str | None, str | None, str | None]:
    """(namespace, group_id, message_type, edge_node_id, device_id, host_id); ValueError with the
    rule when the topic does not follow 4.1 / 4.2.3."""
    parts = topic.split("/")
    if len(parts) >= 2 and parts[1] == "STATE":
        if len(parts) != 3 or not parts[2]:
            raise ValueError(f"STATE topic must be {NAMESPACE}/STATE/<sparkplug_host_id> (4.2.3.1)")
        return parts[0], None, "STATE", None, None, parts[2]
    if len(parts) not in (4, 5):
        raise ValueError("topic must be namespace/group_id/message_type/edge_node_id/[device_id] (4.1)")
    namespace, group, mtype, node = parts[:4]
    device = parts[4] if len(parts) == 5 else None
    if namespace != NAMESPACE:
        raise ValueError(f"namespace must be {NAMESPACE} (4.1.1)")
    if mtype in NODE_TYPES:
        if device is not None:
            raise ValueError(f"{mtype} topics carry no device_id (4.1.5)")
    elif mtype in DEVICE_TYPES:
        if not device:
            raise ValueError(f"{mtype} topics must carry a device_id (4.1.5)")
    else:
        raise ValueError(f"unknown message_type {mtype!r} (4.1.3)")
    if not group or not node:
        raise ValueError("empty group_id or edge_node_id (4.1.2, 4.1.4)")
    return namespace, group, mtype, node, device, None


class Checker:
    """Keeps the state of every edge node seen and lists the rules each message breaks."""

    def __init__(self, *, rebirth_unknown: bool = False) -> None:
        self.rebirth_unknown = rebirth_unknown
        self.rebirths_wanted: list[tuple[str, str]] = []  # the host sends these NCMDs
        self.messages: list[Message] = []
        self.violations: list[str] = []
        self.notes: list[str] = []  # observations that break no rule
        self.nodes: dict[tuple[str, str], _Node] = {}

    # ---- entry point ---------------------------------------------------------------------
    def feed(self, topic: str, data: bytes, qos: int = 0, retain: bool = False,
             received_at: float | None = None) -> Message:
        try:
            namespace, group, mtype, node, device, host = parse_topic(topic)
        except ValueError as exc:
            msg = Message(len(self.messages), topic, topic.split("/")[0], None, "?", None, None, qos=qos,
                          retain=retain, received_at=received_at or time.time(), error=str(exc))
            self.messages.append(msg)
            self._violate(msg, f"topic {topic!r}: {exc}")
            return msg
        msg = Message(len(self.messages), topic, namespace, group, mtype, node, device, host_id=host, qos=qos,
                      retain=retain, received_at=received_at or time.time())
        self.messages.append(msg)
        if mtype == "STATE":
            self._state(msg, data)
            return msg
        try:
            msg.payload = decode_payload(data)
        except DecodeError as exc:
            msg.error = str(exc)
            self._violate(msg, f"payload does not decode as a Sparkplug B Payload (6.4.1): {exc}")
            known = self.nodes.get((group or "", node or ""))
            if known is not None:
                known.last_seq = None  # its seq is unknown: the next message starts the count again
            return msg
        assert group is not None and node is not None
        st = self.nodes.setdefault((group, node), _Node())
        self._mqtt_flags(msg)
        handler = getattr(self, f"_on_{mtype.lower()}")
        handler(msg, st)
        return msg

    # ---- helpers ---------------------------------------------------------------------------
    def _violate(self, msg: Message, text: str) -> None:
        line = f"{msg.where()} (#{msg.index}): {text}"
        msg.violations.append(text)
        self.violations.append(line)

    def _mqtt_flags(self, msg: Message) -> None:
        if msg.message_type in ("NBIRTH", "NDATA", "DBIRTH", "DDATA", "DDEATH", "NCMD", "DCMD"):
            if msg.qos != 0:
                self._violate(msg, f"published with QoS {msg.qos}; {msg.message_type} MUST use QoS 0 (4.2)")
            if msg.retain:
                self._violate(msg, f"retained; {msg.message_type} MUST be published with retain false (4.2)")
        elif msg.message_type == "NDEATH" and msg.retain:
            self._violate(msg, "retained NDEATH; the Will Retained flag MUST be false (6.4.25, 5.4)")

    def _timestamps(self, msg: Message, metrics_too: bool) -> None:
        p = msg.payload
        assert p is not None
        if p.timestamp is None:
            self._violate(msg, "payload has no timestamp (6.4.5, tck-id-payloads-"
                               f"{msg.message_type.lower()}-timestamp)")
        if metrics_too:
            for m in p.metrics:
                if m.timestamp is None:
                    self._violate(msg, f"metric {self._label(m)} has no timestamp "
                                       "(6.4.6 tck-id-payloads-name-birth-data-requirement)")

    @staticmethod
    def _label(m: Metric) -> str:
        if m.resolved_name is not None:
            return repr(m.resolved_name)
        return f"alias {m.alias}" if m.alias is not None else "(no name, no alias)"

    def _seq(self, msg: Message, st: _Node) -> None:
        """seq present, 0..255, one more than the node's previous message (6.4.5, 5.9, reading 3)."""
        p = msg.payload
        assert p is not None
        if p.seq is None:
            self._violate(msg, "no seq; every message from an edge node but NDEATH carries one (6.4.5)")
            return
        if p.seq > 255:
            self._violate(msg, f"seq {p.seq} is over 255 (6.4.5)")
        if msg.message_type == "NBIRTH":
            if p.seq != 0:
                self._violate(msg, f"NBIRTH seq {p.seq}, MUST be 0 (4.2.1.1.2 tck-id-topics-nbirth-seq-num)")
        elif st.last_seq is not None:
            expected = (st.last_seq + 1) % 256
            if p.seq != expected:
                self._violate(msg, f"seq {p.seq} after {st.last_seq}, expected {expected} (6.4.5; reorder "
                                   "timeout 0 on one MQTT server, 5.9)")
        st.last_seq = p.seq

    def _check_birth_metrics(self, msg: Message, scope: _Scope, st: _Node, owner: str) -> None:
        """Every birth metric: name, datatype, value or is_null, alias unique in the node (4.2, 5.16, 6.4.6)."""
        assert msg.payload is not None
        scope.by_name.clear()
        scope.by_alias.clear()
        scope.values.clear()
        for alias in [a for a, o in st.aliases.items() if o == owner]:
            del st.aliases[alias]
        for m in msg.payload.metrics:
            if m.name is None:
                self._violate(msg, f"birth metric {self._label(m)} has no name (4.2, 6.4.6 "
                                   "tck-id-payloads-alias-birth-requirement)")
                continue
            if m.datatype is None:
                self._violate(msg, f"birth metric {m.name!r} has no datatype "
                                   "(6.4.6 tck-id-payloads-metric-datatype-req)")
            elif m.datatype not in DataType._value2member_map_ or m.datatype == DataType.Unknown:
                self._violate(msg, f"birth metric {m.name!r} has datatype {m.datatype}, not a Sparkplug "
                                   "datatype with values (6.4.16)")
            if m.is_null and m.value_field is not None:
                self._violate(msg, f"birth metric {m.name!r} is_null yet carries {m.value_field} (5.16)")
            if not m.is_null and m.value_field is None:
                self._violate(msg, f"birth metric {m.name!r} has no value and is not is_null (5.16, "
                                   "tck-id-topics-dbirth-metrics / nbirth-metrics)")
            if m.name in scope.by_name:
                self._violate(msg, f"metric {m.name!r} born twice in one birth")
            if m.alias is not None:
                holder = st.aliases.get(m.alias)
                if holder is not None:
                    self._violate(msg, f"alias {m.alias} of {m.name!r} is already declared by {holder} of this "
                                       "node (6.4.6 tck-id-payloads-alias-uniqueness)")
                else:
                    st.aliases[m.alias] = owner
            d = _MetricDef(m.name, m.alias, m.datatype)
            scope.by_name[m.name] = d
            if m.alias is not None and m.alias not in scope.by_alias:
                scope.by_alias[m.alias] = d
            self._resolve_value(msg, m, m.datatype)
            scope.values[m.name] = Value(m.value, m.is_null, m.quality)

    def _resolve_value(self, msg: Message, m: Metric, datatype: int | None) -> None:
        m.resolved_datatype = datatype
        self._check_quality(msg, m)
        if m.is_null or m.value_field is None or datatype is None:
            m.value = None if m.is_null else m.raw
            return
        if datatype == DataType.UInt32 and m.value_field == "long_value":
            self._violate(msg, f"metric {self._label(m)}: UInt32 carried in long_value; 6.4.17 puts it in "
                               "int_value (uint32)")
        try:
            m.value = interpret(datatype, m.value_field, m.raw)
        except ValueError as exc:
            m.value = m.raw
            self._violate(msg, f"metric {self._label(m)}: {exc}")

    def _check_quality(self, msg: Message, m: Metric) -> None:
        if m.properties is None:
            return
        if len(m.properties.keys) != len(m.properties.values):
            self._violate(msg, f"metric {self._label(m)}: PropertySet has {len(m.properties.keys)} keys and "
                               f"{len(m.properties.values)} values (6.4.8)")
        prop = m.properties.as_dict().get(QUALITY)
        if prop is None:
            return
        if prop.type != DataType.Int32 or prop.value_field != "int_value" or prop.raw not in QUALITY_CODES:
            self._violate(msg, f"metric {self._label(m)}: Quality property type={prop.type} "
                               f"{prop.value_field}={prop.raw!r}; MUST be type 3 (Int32) int_value 0, 192 or "
                               "500 (6.4.9.1)")

    def _data_metrics(self, msg: Message, scope: _Scope) -> None:
        """DATA metrics resolve through the birth: alias known, same datatype, alias only (6.4.6)."""
        assert msg.payload is not None
        for m in msg.payload.metrics:
            d: _MetricDef | None = None
            if m.alias is not None:
                d = scope.by_alias.get(m.alias)
                if d is None:
                    self._violate(msg, f"alias {m.alias} is not declared in the current "
                                       f"{'DBIRTH' if msg.device_id else 'NBIRTH'} (6.4.6, 5.15)")
                elif m.name is not None:
                    self._violate(msg, f"metric {m.name!r} carries both name and alias {m.alias}; DATA "
                                       "messages MUST only include the alias (6.4.6 "
                                       "tck-id-payloads-alias-data-cmd-requirement)")
                if d is not None and m.name is not None and m.name != d.name:
                    self._violate(msg, f"alias {m.alias} was born as {d.name!r}, this metric names it {m.name!r}")
            elif m.name is not None:
                d = scope.by_name.get(m.name)
                if d is None:
                    self._violate(msg, f"metric {m.name!r} is not in the current "
                                       f"{'DBIRTH' if msg.device_id else 'NBIRTH'} (5.16, 5.15)")
                elif d.alias is not None:
                    self._violate(msg, f"metric {m.name!r} sent by name though its birth declared alias "
                                       f"{d.alias} (6.4.6 tck-id-payloads-alias-data-cmd-requirement)")
            else:
                self._violate(msg, "metric with neither name nor alias (6.4.6)")
            if d is None:
                self._resolve_value(msg, m, m.datatype)
                continue
            m.resolved_name = d.name
            if m.datatype is not None and m.datatype != d.datatype:
                self._violate(msg, f"metric {d.name!r} datatype {datatype_name(m.datatype)} differs from its "
                                   f"birth's {datatype_name(d.datatype)}")
            self._resolve_value(msg, m, d.datatype)
            if not m.is_historical:
                scope.values[d.name] = Value(m.value, m.is_null, m.quality)

    def _end_device(self, scope: _Scope) -> None:
        scope.online = False

    def _end_session(self, st: _Node) -> None:
        st.node.online = False
        for dev in st.devices.values():
            self._end_device(dev)
        if st.bdseq is not None:
            st.old_bdseqs.add(st.bdseq)
        st.last_seq = None

    @staticmethod
    def _metric_named(p: Payload, name: str) -> Metric | None:
        return next((m for m in p.metrics if m.name == name), None)

    # ---- per message type ------------------------------------------------------------------
    def _on_nbirth(self, msg: Message, st: _Node) -> None:
        p = msg.payload
        assert p is not None
        self._timestamps(msg, metrics_too=True)
        bd = self._metric_named(p, BDSEQ)
        new_bdseq: int | None = None
        if bd is None:
            self._violate(msg, "NBIRTH has no bdSeq metric (4.2.1.1.2 tck-id-topics-nbirth-bdseq-included)")
        else:
            if bd.datatype != DataType.Int64:
                self._violate(msg, f"bdSeq datatype {datatype_name(bd.datatype)}, MUST be Int64 (5.4)")
            if bd.value_field in ("long_value", "int_value") and isinstance(bd.raw, int):
                new_bdseq = bd.raw
                if bd.raw > 255:
                    self._violate(msg, f"bdSeq {bd.raw} is over 255 (5.4)")
        rb = self._metric_named(p, REBIRTH)
        if rb is None:
            self._violate(msg, f"NBIRTH has no {REBIRTH!r} metric (4.2.1.1.2, 5.17)")
        else:
            if rb.datatype != DataType.Boolean or rb.value_field != "boolean_value" or rb.raw is not False:
                self._violate(msg, f"{REBIRTH!r} MUST be Boolean false in NBIRTH (5.17), is "
                                   f"{datatype_name(rb.datatype)} {rb.value_field}={rb.raw!r}")
            if rb.alias is not None:
                self._violate(msg, f"{REBIRTH!r} MUST NOT have an alias (5.17 "
                                   "tck-id-operational-behavior-data-commands-rebirth-name-aliases)")
        if st.node.online and new_bdseq is not None and st.bdseq is not None and new_bdseq != st.bdseq:
            if st.rebirth_requested:
                self._violate(msg, f"NBIRTH answering a rebirth request changed bdSeq {st.bdseq} -> {new_bdseq}; "
                                   "it MUST keep the session's bdSeq (5.17 rebirth-action-3)")
            else:
                self.notes.append(f"{msg.where()} (#{msg.index}): new session bdSeq {new_bdseq} while "
                                  f"bdSeq {st.bdseq} had no NDEATH yet (its Will may come late, 5.4)")
            st.old_bdseqs.add(st.bdseq)
        st.rebirth_requested = False
        st.bdseq = new_bdseq
        if new_bdseq is not None:
            st.old_bdseqs.discard(new_bdseq)
        # a birth sequence starts: every device must be born again (5.17 rebirth-action-2)
        for dev in st.devices.values():
            dev.online = False
            dev.by_alias.clear()
            dev.by_name.clear()
        st.aliases.clear()
        self._check_birth_metrics(msg, st.node, st, "the NBIRTH")
        st.node.online = True
        st.seen_birth = True
        self._seq(msg, st)

    def _on_ndeath(self, msg: Message, st: _Node) -> None:
        p = msg.payload
        assert p is not None
        if p.seq is not None:
            self._violate(msg, f"NDEATH carries seq {p.seq}; it MUST NOT (4.2.1.3 tck-id-topics-ndeath-seq)")
        bd = self._metric_named(p, BDSEQ)
        born = st.node.by_name.get(BDSEQ)
        if bd is None and born is not None and born.alias is not None:  # tolerated: bdSeq by its alias
            bd = next((m for m in p.metrics if m.name is None and m.alias == born.alias), None)
        if bd is None or len(p.metrics) != 1:
            self._violate(msg, f"NDEATH MUST include exactly the bdSeq metric (4.2.1.3), has "
                               f"{[self._label(m) for m in p.metrics]}")
        if bd is None:
            return
        if bd.datatype is not None and bd.datatype != DataType.Int64:
            self._violate(msg, f"NDEATH bdSeq datatype {datatype_name(bd.datatype)}, MUST be Int64 (5.4)")
        value = bd.raw if isinstance(bd.raw, int) and not isinstance(bd.raw, bool) else None
        if not st.seen_birth:
            self.notes.append(f"{msg.where()} (#{msg.index}): NDEATH bdSeq {value} of a node not seen born")
            return
        if value == st.bdseq and st.node.online:
            self._end_session(st)
        elif value == st.bdseq or value in st.old_bdseqs:
            self.notes.append(f"{msg.where()} (#{msg.index}): NDEATH bdSeq {value} of an ended session, "
                              "ignored (5.5)")
        else:
            self._violate(msg, f"NDEATH bdSeq {value} matches neither the current NBIRTH's bdSeq {st.bdseq} "
                               "nor an earlier session's (4.2.1.3, tck-id-payloads-ndeath-bdseq)")

    def _node_born(self, msg: Message, st: _Node, what: str) -> bool:
        if st.node.online:
            return True
        if self.rebirth_unknown and not st.seen_birth:
            if not st.rebirth_requested:
                assert msg.group_id is not None and msg.edge_node_id is not None
                self.rebirths_wanted.append((msg.group_id, msg.edge_node_id))
                st.rebirth_requested = True
                self.notes.append(f"{msg.where()} (#{msg.index}): {what} of a node not seen born; "
                                  "rebirth requested (5.17)")
            return False
        why = "after its NDEATH" if st.seen_birth else "and no NBIRTH was seen since the host connected"
        self._violate(msg, f"{what} while the edge node is not born ({why}; 4.2, 5.4, 6.4.21)")
        return False

    def _on_ndata(self, msg: Message, st: _Node) -> None:
        self._timestamps(msg, metrics_too=True)
        if self._node_born(msg, st, "NDATA"):
            self._seq(msg, st)
            self._data_metrics(msg, st.node)
        else:
            self._resolve_unknown(msg)

    def _resolve_unknown(self, msg: Message) -> None:
        assert msg.payload is not None
        for m in msg.payload.metrics:
            self._resolve_value(msg, m, m.datatype)

    def _on_dbirth(self, msg: Message, st: _Node) -> None:
        assert msg.device_id is not None
        self._timestamps(msg, metrics_too=True)
        node_ok = self._node_born(msg, st, "DBIRTH")
        if node_ok:
            self._seq(msg, st)
        dev = st.devices.setdefault(msg.device_id, _Scope())
        self._check_birth_metrics(msg, dev, st, f"device {msg.device_id!r}")
        dev.online = node_ok

    def _on_ddata(self, msg: Message, st: _Node) -> None:
        assert msg.device_id is not None
        self._timestamps(msg, metrics_too=True)
        if not self._node_born(msg, st, "DDATA"):
            self._resolve_unknown(msg)
            return
        self._seq(msg, st)
        dev = st.devices.get(msg.device_id)
        if dev is None or not dev.online:
            self._violate(msg, f"DDATA before a DBIRTH of device {msg.device_id!r} in this birth sequence "
                               "(4.2.2.1, 5.6)")
            self._resolve_unknown(msg)
            return
        self._data_metrics(msg, dev)

    def _on_ddeath(self, msg: Message, st: _Node) -> None:
        assert msg.device_id is not None
        self._timestamps(msg, metrics_too=False)
        if not self._node_born(msg, st, "DDEATH"):
            return
        self._seq(msg, st)
        dev = st.devices.get(msg.device_id)
        if dev is not None:
            self._end_device(dev)

    def _on_cmd(self, msg: Message, st: _Node, scope: _Scope | None) -> None:
        p = msg.payload
        assert p is not None
        if p.timestamp is None:
            self._violate(msg, f"{msg.message_type} has no timestamp (6.4.23/6.4.24)")
        if p.seq is not None:
            self._violate(msg, f"{msg.message_type} carries seq {p.seq}; it MUST NOT (6.4.23/6.4.24)")
        for m in p.metrics:
            d = None
            if scope is not None:
                d = scope.by_alias.get(m.alias) if m.alias is not None else scope.by_name.get(m.name or "")
            if d is not None:
                m.resolved_name = d.name
            self._resolve_value(msg, m, m.datatype if m.datatype is not None else (d.datatype if d else None))

    def _on_ncmd(self, msg: Message, st: _Node) -> None:
        self._on_cmd(msg, st, st.node if st.node.online else None)

    def _on_dcmd(self, msg: Message, st: _Node) -> None:
        assert msg.device_id is not None
        self._on_cmd(msg, st, st.devices.get(msg.device_id))

    def _state(self, msg: Message, data: bytes) -> None:
        """STATE payload: JSON UTF-8 with 'online' (bool) and 'timestamp' (ms) (4.2.3, 6.4.27)."""
        try:
            obj = json.loads(data.decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            msg.error = f"not JSON UTF-8: {exc}"
            self._violate(msg, f"STATE payload is not JSON UTF-8 (4.2.3.1): {exc}")
            return
        if not isinstance(obj, dict):
            msg.error = "not a JSON object"
            self._violate(msg, "STATE payload is not a JSON object (4.2.3.1)")
            return
        msg.state = obj
        online, ts = obj.get("online"), obj.get("timestamp")
        if not isinstance(online, bool):
            self._violate(msg, f"STATE 'online' is {online!r}, MUST be a boolean (4.2.3.1)")
        if not isinstance(ts, int | float) or isinstance(ts, bool):
            self._violate(msg, f"STATE 'timestamp' is {ts!r}, MUST be a number of ms since Epoch (4.2.3.1)")
        if msg.qos != 1:
            self._violate(msg, f"STATE published with QoS {msg.qos}; MUST be 1 (4.2.3)")
        if not msg.retain:
            self._violate(msg, "STATE not retained; MUST be (4.2.3)")

    # ---- accessors ---------------------------------------------------------------------------
    def node_online(self, group: str, node: str) -> bool:
        st = self.nodes.get((group, node))
        return st is not None and st.node.online

    def device_online(self, group: str, node: str, device: str) -> bool:
        st = self.nodes.get((group, node))
        if st is None or not st.node.online:
            return False
        dev = st.devices.get(device)
        return dev is not None and dev.online

    def scope(self, group: str, node: str, device: str | None) -> _Scope | None:
        st = self.nodes.get((group, node))
        if st is None:
            return None
        return st.node if device is None else st.devices.get(device)

    def value(self, group: str, node: str, device: str | None, metric_name: str) -> Value:
        scope = self.scope(group, node, device)
        where = f"{group}/{node}" + (f"/{device}" if device is not None else "")
        if scope is None:
            raise KeyError(f"no birth seen for {where}")
        if metric_name not in scope.values:
            raise KeyError(f"{where} has no metric {metric_name!r}; born: {sorted(scope.values)}")
        return scope.values[metric_name]


# --------------------------------------------------------------------------------------------
# The host application on MQTT
# --------------------------------------------------------------------------------------------

class SparkplugHost:
    """`async with SparkplugHost("127.0.0.1", port, primary_host_id="h1") as h:` connects, subscribes
    to spBv1.0/# and checks every message; `h.violations` lists what broke the specification.

    With primary_host_id the CONNECT carries the STATE death certificate as its Will (4.2.3.2, 5.13);
    publish_state(True) announces the host online, or publish_online=True does it right after the
    subscription as 5.13 wants; it is left to the caller so that a test can hold it back and see an
    edge node wait for it (5.4).  Leaving the context publishes STATE offline before the DISCONNECT
    when it was online (5.14)."""

    def __init__(self, host: str, port: int, *, primary_host_id: str | None = None,
                 publish_online: bool = False, rebirth_unknown: bool = False,
                 on_message: Callable[[Message], None] | None = None) -> None:
        self.host = host
        self.port = port
        self.primary_host_id = primary_host_id
        self.publish_online = publish_online
        self.on_message = on_message
        self.checker = Checker(rebirth_unknown=rebirth_unknown)
        self.connect_timestamp = 0
        self._client: Any = None
        self._reader: asyncio.Task[None] | None = None
        self._arrived = asyncio.Condition()
        self._state_online = False  # we announced online and did not take it back
        self._reader_error: BaseException | None = None

    # ---- the agreed interface ----------------------------------------------------------------
    @property
    def messages(self) -> list[Message]:
        return self.checker.messages

    @property
    def violations(self) -> list[str]:
        return self.checker.violations

    @property
    def notes(self) -> list[str]:
        return self.checker.notes

    def value(self, group: str, node: str, device: str | None, metric_name: str) -> Value:
        """Latest (value, is_null, quality) of a metric, through aliases; KeyError if never born."""
        return self.checker.value(group, node, device, metric_name)

    def node_online(self, group: str, node: str) -> bool:
        return self.checker.node_online(group, node)

    def device_online(self, group: str, node: str, device: str) -> bool:
        return self.checker.device_online(group, node, device)

    async def wait_for(self, predicate: Callable[[Message], bool], timeout: float,  # noqa: ASYNC109 (agreed API)
                       *, since: int = 0) -> Message:
        """The first message (index >= since, already received or new) for which predicate is true."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        pos = since
        async with self._arrived:
            while True:
                while pos < len(self.messages):
                    msg = self.messages[pos]
                    pos += 1
                    if predicate(msg):
                        return msg
                if self._reader_error is not None:
                    raise RuntimeError(f"the host stopped reading (lost MQTT connection or on_message "
                                       f"failed): {self._reader_error!r}")
                remaining = deadline - loop.time()
                if remaining <= 0:
                    recent = "; ".join(str(m) for m in self.messages[-5:]) or "none"
                    raise TimeoutError(f"no matching Sparkplug message within {timeout} s "
                                       f"({len(self.messages)} received; last: {recent})")
                try:
                    await asyncio.wait_for(self._arrived.wait(), remaining)
                except TimeoutError:
                    pass

    async def send_rebirth(self, group_id: str, edge_node_id: str) -> Payload:
        """NCMD 'Node Control/Rebirth' = true (5.17): by name, never by alias; no seq (6.4.23)."""
        ts = now_ms()
        payload = Payload(timestamp=ts, metrics=[make_metric(REBIRTH, DataType.Boolean, True, timestamp=ts)])
        st = self.checker.nodes.setdefault((group_id, edge_node_id), _Node())
        st.rebirth_requested = True
        await self._publish(f"{NAMESPACE}/{group_id}/NCMD/{edge_node_id}", encode_payload(payload))
        return payload

    async def send_dcmd(self, group_id: str, edge_node_id: str, device_id: str, metric_name: str, value: Any,
                        datatype_name: str, *, use_alias: bool | None = None, include_datatype: bool = False,
                        int_form: Literal["sign32", "width"] = "sign32") -> Payload:
        """DCMD writing `value` to one metric (6.4.24, 5.17).

        The metric goes by its alias alone when the device's DBIRTH declared one (6.4.6: DCMD "MUST
        only include an alias and the metric name MUST be excluded"), else by name; use_alias
        forces either.  No datatype on the wire unless include_datatype (6.4.6 SHOULD NOT); Int8/16/32
        negatives sign-extended to 32 bits unless int_form="width" (module docstring, reading 2)."""
        dt = datatype_by_name(datatype_name)
        scope = self.checker.scope(group_id, edge_node_id, device_id)
        born = scope.by_name.get(metric_name) if scope is not None else None
        alias = born.alias if born is not None else None
        if use_alias is True and alias is None:
            raise ValueError(f"{group_id}/{edge_node_id}/{device_id} declared no alias for {metric_name!r}")
        by_alias = alias is not None and use_alias is not False
        ts = now_ms()
        m = make_metric(None if by_alias else metric_name, dt, value, alias=alias if by_alias else None,
                        timestamp=ts, with_datatype=include_datatype, int_form=int_form)
        payload = Payload(timestamp=ts, metrics=[m])
        await self._publish(f"{NAMESPACE}/{group_id}/DCMD/{edge_node_id}/{device_id}", encode_payload(payload))
        return payload

    async def publish_state(self, online: bool) -> None:
        """STATE birth (online, the Will's timestamp) or death (offline, now) certificate: JSON, QoS 1,
        retained, on spBv1.0/STATE/<primary_host_id> (4.2.3.1, 4.2.3.2, 5.13, 5.14)."""
        if self.primary_host_id is None:
            raise ValueError("publish_state needs SparkplugHost(..., primary_host_id='...')")
        self._state_online = online
        ts = self.connect_timestamp if online else now_ms()
        await self._client.publish(self.state_topic, self._state_json(online, ts), qos=1, retain=True)

    # ---- plumbing ------------------------------------------------------------------------------
    @property
    def state_topic(self) -> str:
        return f"{NAMESPACE}/STATE/{self.primary_host_id}"

    @staticmethod
    def _state_json(online: bool, ts: int) -> bytes:
        return json.dumps({"online": online, "timestamp": ts}).encode("utf-8")

    async def _publish(self, topic: str, data: bytes) -> None:
        # commands: QoS 0, retain false (6.4.23, 6.4.24)
        await self._client.publish(topic, data, qos=0, retain=False)

    async def __aenter__(self) -> SparkplugHost:
        import aiomqtt
        from paho.mqtt.subscribeoptions import SubscribeOptions

        self.connect_timestamp = now_ms()
        will = None
        if self.primary_host_id is not None:
            will = aiomqtt.Will(self.state_topic, self._state_json(False, self.connect_timestamp), qos=1, retain=True)
        ident = f"sparkplug-test-host-{self.primary_host_id or 'x'}-{uuid.uuid4().hex[:8]}"
        # MQTT 5, Clean Start and session expiry 0 (5.3 tck-id-message-flow-phid-sparkplug-clean-session-50)
        self._client = aiomqtt.Client(self.host, self.port, identifier=ident, will=will,
                                      protocol=aiomqtt.ProtocolVersion.V5, clean_start=True)
        await self._client.__aenter__()
        try:
            await self._client.subscribe(f"{NAMESPACE}/#", options=SubscribeOptions(qos=1, retainAsPublished=True))
            self._reader = asyncio.create_task(self._read())
            if self.publish_online:
                await self.publish_state(True)
        except BaseException:
            await self._client.__aexit__(None, None, None)
            raise
        return self

    async def __aexit__(self, *exc: object) -> None:
        try:
            if self.primary_host_id is not None and self._state_online and self._reader_error is None:
                await self.publish_state(False)  # 5.14: death certificate before the DISCONNECT
        finally:
            if self._reader is not None:
                self._reader.cancel()
                try:
                    await self._reader
                except (asyncio.CancelledError, Exception):
                    pass
            try:
                await self._client.__aexit__(None, None, None)
            except Exception:  # already gone: nothing left to close
                pass

    async def _read(self) -> None:
        try:
            async for mq in self._client.messages:
                data = mq.payload if isinstance(mq.payload, bytes) else str(mq.payload).encode()
                msg = self.checker.feed(str(mq.topic), data, qos=mq.qos, retain=bool(mq.retain))
                if self.on_message is not None:
                    self.on_message(msg)
                await self._after(msg)
                async with self._arrived:
                    self._arrived.notify_all()
        except asyncio.CancelledError:
            raise
        except Exception as exc:  # the connection dropped: waiters learn it instead of timing out
            self._reader_error = exc
            async with self._arrived:
                self._arrived.notify_all()

    async def _after(self, msg: Message) -> None:
        while self.checker.rebirths_wanted:
            group, node = self.checker.rebirths_wanted.pop(0)
            await self.send_rebirth(group, node)
        if (msg.message_type == "STATE" and msg.host_id == self.primary_host_id and self._state_online
                and msg.state is not None and msg.state.get("online") is False):
            # our own death certificate delivered while we are online: republish the birth (5.3)
            await self.publish_state(True)


# --------------------------------------------------------------------------------------------
# CLI
# --------------------------------------------------------------------------------------------

def _parse_broker(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or not port.isdigit():
        raise argparse.ArgumentTypeError(f"--broker must be HOST:PORT, got {text!r}")
    return host.strip("[]"), int(port)


async def _run_cli(broker: tuple[str, int], primary_host_id: str | None, seconds: float | None) -> int:
    def show(msg: Message) -> None:
        print(msg, flush=True)
        for v in msg.violations:
            print(f"  VIOLATION: {v}", flush=True)

    async with SparkplugHost(broker[0], broker[1], primary_host_id=primary_host_id,
                             publish_online=primary_host_id is not None, on_message=show) as h:
        try:
            if seconds is None:
                await asyncio.Event().wait()
            else:
                await asyncio.sleep(seconds)
        except asyncio.CancelledError:
            pass
        violations = list(h.violations)
    print(f"{len(h.messages)} messages, {len(violations)} violations", flush=True)
    for line in h.notes:
        print(f"NOTE {line}", flush=True)
    for line in violations:
        print(f"VIOLATION {line}", flush=True)
    return 1 if violations else 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="Sparkplug 3.0 test host: prints decoded messages and rule "
                                             "violations; exit status 1 on any violation.")
    ap.add_argument("--broker", type=_parse_broker, default=("127.0.0.1", 1883), help="MQTT server HOST:PORT")
    ap.add_argument("--primary-host-id", default=None,
                    help="act as this primary host: STATE Will at CONNECT, STATE online after subscribing")
    ap.add_argument("--seconds", type=float, default=None, help="run this long (default: until Ctrl-C)")
    args = ap.parse_args(argv)
    import aiomqtt

    try:
        return asyncio.run(_run_cli(args.broker, args.primary_host_id, args.seconds))
    except KeyboardInterrupt:
        return 130
    except (OSError, aiomqtt.MqttError) as exc:
        print(f"cannot reach the MQTT server {args.broker[0]}:{args.broker[1]}: {exc}; is it running and is "
              "--broker right?", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
