"""The Sparkplug B payload: the specification's ``sparkplug_b.proto`` as a protobuf descriptor, and records.

Sparkplug 3.0 §6.4.1 ("Google Protocol Buffer Schema") gives the schema; it is transcribed here as
a ``FileDescriptorProto`` (field names, numbers and types as in the specification) for the parts an
edge node of plain values uses: ``Payload``, ``Metric``, ``MetaData``, ``PropertySet`` and
``PropertyValue``.  A ``DataSet`` or ``Template`` value (fields 17 and 18 of a metric) is not
modelled: protobuf keeps it as an unknown field and such a metric decodes with no value.

The protobuf classes stay inside this module: the rest of the package uses :class:`Payload` and
:class:`Metric`.  Value fields by datatype (§6.4.17 "Datatype Details"): the signed and unsigned
integers of 8 to 32 bits go in ``int_value`` (uint32), the 64-bit ones and DateTime in
``long_value`` (uint64).  A negative value is stored as its two's complement in the field's
width (an Int16 -5 is ``int_value`` 0xFFFFFFFB); read back, the value is taken modulo the
datatype's own width, so 0xFFFB reads as -5 too.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from enum import IntEnum
from typing import Any, Final

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from google.protobuf.message import DecodeError

from gateway.frozen import frozen

__all__ = [
    "BAD",
    "GOOD",
    "STALE",
    "Metric",
    "Payload",
    "PayloadError",
    "SparkplugType",
    "Value",
    "decode",
    "encode",
    "typed",
]

#: Quality codes of the ``Quality`` property (§6.4.9.1 "Quality Codes")
BAD: Final = 0
GOOD: Final = 192
STALE: Final = 500


class SparkplugType(IntEnum):
    """Sparkplug B datatypes (§6.4.16 "Data Types"; the ones this package uses and their neighbours)."""

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
    Bytes = 17
    File = 18


#: integer datatypes: (bits, signed)
_INTEGERS: Final[Mapping[int, tuple[int, bool]]] = {
    SparkplugType.Int8: (8, True), SparkplugType.Int16: (16, True), SparkplugType.Int32: (32, True),
    SparkplugType.Int64: (64, True),
    SparkplugType.UInt8: (8, False), SparkplugType.UInt16: (16, False), SparkplugType.UInt32: (32, False),
    SparkplugType.UInt64: (64, False), SparkplugType.DateTime: (64, False),
}
_LONG: Final = frozenset({SparkplugType.Int64, SparkplugType.UInt64, SparkplugType.DateTime})
_STRINGS: Final = frozenset({SparkplugType.String, SparkplugType.Text, SparkplugType.UUID})

Value = bool | int | float | str | bytes


class PayloadError(ValueError):
    """A payload that is not a Sparkplug B protobuf, or a value its datatype cannot hold."""


@frozen
class Metric:
    """One metric of a payload (§6.4.6 "Metric").  ``value`` None: none given (``is_null`` says whether null)."""

    name: str | None = None
    alias: int | None = None
    timestamp: int | None = None
    datatype: int | None = None
    value: Value | None = None
    is_null: bool = False
    #: the PropertySet (§6.4.8): key -> (PropertyValue type, value)
    properties: Mapping[str, tuple[int, Value]] | None = None
    #: the datatype ``value`` is encoded as when ``datatype`` is not sent (DATA messages, §6.4.6)
    value_type: int | None = None
    #: not a real time / current value: sent after it was acquired (store and forward, §6.4.6 "is_historical")
    is_historical: bool = False


@frozen
class Payload:
    """A Sparkplug B payload (§6.4.5 "Payload")."""

    timestamp: int | None = None
    metrics: Sequence[Metric] = ()
    seq: int | None = None


# --- the schema (§6.4.1), as a descriptor ----------------------------------------------------

_F = descriptor_pb2.FieldDescriptorProto
_OPT, _REP = _F.LABEL_OPTIONAL, _F.LABEL_REPEATED
_PACKAGE: Final = "org.eclipse.tahu.protobuf"


def _message_type(name: str, fields: Sequence[tuple[str, int, int, int, str | None, int | None]]) -> Any:
    """A DescriptorProto: fields (name, number, label, type, message type name, oneof index)."""
    message = descriptor_pb2.DescriptorProto(name=name)
    for field_name, number, label, kind, type_name, oneof in fields:
        field = message.field.add(name=field_name, number=number, label=label, type=kind)
        if type_name is not None:
            field.type_name = f".{_PACKAGE}.Payload.{type_name}"
        if oneof is not None:
            field.oneof_index = oneof
    return message


def _schema() -> descriptor_pb2.FileDescriptorProto:
    f = _F
    u32, u64, flt, dbl, bln, txt, byt, msg = (f.TYPE_UINT32, f.TYPE_UINT64, f.TYPE_FLOAT, f.TYPE_DOUBLE,
                                               f.TYPE_BOOL, f.TYPE_STRING, f.TYPE_BYTES, f.TYPE_MESSAGE)
    property_value = _message_type("PropertyValue", [
        ("type", 1, _OPT, u32, None, None), ("is_null", 2, _OPT, bln, None, None),
        ("int_value", 3, _OPT, u32, None, 0), ("long_value", 4, _OPT, u64, None, 0),
        ("float_value", 5, _OPT, flt, None, 0), ("double_value", 6, _OPT, dbl, None, 0),
        ("boolean_value", 7, _OPT, bln, None, 0), ("string_value", 8, _OPT, txt, None, 0),
        ("propertyset_value", 9, _OPT, msg, "PropertySet", 0),
        ("propertysets_value", 10, _OPT, msg, "PropertySetList", 0),
    ])
    property_value.oneof_decl.add(name="value")
    property_set = _message_type("PropertySet", [
        ("keys", 1, _REP, txt, None, None), ("values", 2, _REP, msg, "PropertyValue", None),
    ])
    property_set_list = _message_type("PropertySetList", [("propertyset", 1, _REP, msg, "PropertySet", None)])
    meta = _message_type("MetaData", [
        ("is_multi_part", 1, _OPT, bln, None, None), ("content_type", 2, _OPT, txt, None, None),
        ("size", 3, _OPT, u64, None, None), ("seq", 4, _OPT, u64, None, None),
        ("file_name", 5, _OPT, txt, None, None), ("file_type", 6, _OPT, txt, None, None),
        ("md5", 7, _OPT, txt, None, None), ("description", 8, _OPT, txt, None, None),
    ])
    metric = _message_type("Metric", [
        ("name", 1, _OPT, txt, None, None), ("alias", 2, _OPT, u64, None, None),
        ("timestamp", 3, _OPT, u64, None, None), ("datatype", 4, _OPT, u32, None, None),
        ("is_historical", 5, _OPT, bln, None, None), ("is_transient", 6, _OPT, bln, None, None),
        ("is_null", 7, _OPT, bln, None, None), ("metadata", 8, _OPT, msg, "MetaData", None),
        ("properties", 9, _OPT, msg, "PropertySet", None),
        ("int_value", 10, _OPT, u32, None, 0), ("long_value", 11, _OPT, u64, None, 0),
        ("float_value", 12, _OPT, flt, None, 0), ("double_value", 13, _OPT, dbl, None, 0),
        ("boolean_value", 14, _OPT, bln, None, 0), ("string_value", 15, _OPT, txt, None, 0),
        ("bytes_value", 16, _OPT, byt, None, 0),
    ])
    metric.oneof_decl.add(name="value")
    payload = _message_type("Payload", [
        ("timestamp", 1, _OPT, u64, None, None), ("metrics", 2, _REP, msg, "Metric", None),
        ("seq", 3, _OPT, u64, None, None), ("uuid", 4, _OPT, txt, None, None), ("body", 5, _OPT, byt, None, None),
    ])
    payload.nested_type.extend([metric, meta, property_set, property_value, property_set_list])
    schema = descriptor_pb2.FileDescriptorProto(name="gateway_sparkplug_b.proto", package=_PACKAGE, syntax="proto2")
    schema.message_type.append(payload)
    return schema


_POOL: Final = descriptor_pool.DescriptorPool()
_POOL.Add(_schema())
_PAYLOAD: Final = message_factory.GetMessageClass(_POOL.FindMessageTypeByName(f"{_PACKAGE}.Payload"))


# --- values -----------------------------------------------------------------------------------


def _value_field(datatype: int) -> str:
    if datatype in _LONG:
        return "long_value"
    if datatype in _INTEGERS:
        return "int_value"
    if datatype == SparkplugType.Float:
        return "float_value"
    if datatype == SparkplugType.Double:
        return "double_value"
    if datatype == SparkplugType.Boolean:
        return "boolean_value"
    if datatype in _STRINGS:
        return "string_value"
    if datatype in (SparkplugType.Bytes, SparkplugType.File):
        return "bytes_value"
    raise PayloadError(f"datatype {datatype} is not a plain value")


def _set_value(target: Any, datatype: int, value: Value) -> None:
    field = _value_field(datatype)
    if field in ("int_value", "long_value"):
        if not isinstance(value, int):
            raise PayloadError(f"datatype {SparkplugType(datatype).name} needs an integer, not {value!r}")
        width = 32 if field == "int_value" else 64
        setattr(target, field, value & ((1 << width) - 1))
    else:
        setattr(target, field, value)


def typed(datatype: int, value: Value) -> Value:
    """A received value read as ``datatype``: integers in their own width or sign-extended to the field's
    (an Int16 -5 as 0xFFFB or 0xFFFFFFFB), anything else out of range; else as given.

    Raises :class:`PayloadError` for a value of another kind (a string for an Int16, a float for a
    Boolean): a DCMD must carry "a compatible metric value" (§5.17 "Commands")."""
    bits_signed = _INTEGERS.get(datatype)
    if bits_signed is not None:
        if isinstance(value, bool) or not isinstance(value, int):
            raise PayloadError(f"{SparkplugType(datatype).name} needs an integer value, got {value!r}")
        bits, signed = bits_signed
        field = 64 if datatype in _LONG else 32
        if signed and -(1 << (bits - 1)) <= value < 0:
            return value
        if signed and bits < field and (1 << field) - (1 << (bits - 1)) <= value < 1 << field:
            value -= (1 << field) - (1 << bits)  # sign-extended to the field's width: back to our own
        if not 0 <= value < 1 << bits:
            raise PayloadError(f"{value} does not fit {SparkplugType(datatype).name}")
        return value - (1 << bits) if signed and value >> (bits - 1) else value
    if datatype == SparkplugType.Boolean:
        if not isinstance(value, bool):
            raise PayloadError(f"Boolean needs boolean_value, got {value!r}")
        return value
    if datatype in (SparkplugType.Float, SparkplugType.Double):
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise PayloadError(f"{SparkplugType(datatype).name} needs a number, got {value!r}")
        return float(value)
    return value


# --- encode / decode --------------------------------------------------------------------------


def encode(payload: Payload) -> bytes:
    """The protobuf bytes of ``payload``."""
    message: Any = _PAYLOAD()
    if payload.timestamp is not None:
        message.timestamp = payload.timestamp
    if payload.seq is not None:
        message.seq = payload.seq
    for metric in payload.metrics:
        out = message.metrics.add()
        if metric.name is not None:
            out.name = metric.name
        if metric.alias is not None:
            out.alias = metric.alias
        if metric.timestamp is not None:
            out.timestamp = metric.timestamp
        if metric.datatype is not None:
            out.datatype = metric.datatype
        if metric.is_historical:
            out.is_historical = True
        if metric.is_null:
            out.is_null = True  # and no value (§5.16 "Data Publish")
        elif metric.value is not None:
            kind = metric.datatype if metric.datatype is not None else metric.value_type
            if kind is None:
                raise PayloadError(f"metric {metric.name or metric.alias}: a value needs its datatype")
            _set_value(out, kind, metric.value)
        if metric.properties is not None:
            for key, (kind, value) in metric.properties.items():
                out.properties.keys.append(key)
                _set_value(out.properties.values.add(type=kind), kind, value)
    return bytes(message.SerializeToString())


def _oneof(source: Any) -> Value | None:
    which = source.WhichOneof("value")
    if which is None or which not in _PLAIN_FIELDS:
        return None
    value: Value = getattr(source, which)
    return value


_PLAIN_FIELDS: Final = frozenset({"int_value", "long_value", "float_value", "double_value", "boolean_value",
                                  "string_value", "bytes_value"})


def decode(data: bytes) -> Payload:
    """A payload from its protobuf bytes; :class:`PayloadError` when they are not one."""
    message: Any = _PAYLOAD()
    try:
        message.ParseFromString(data)
    except (DecodeError, RuntimeError, ValueError) as exc:
        raise PayloadError(f"not a Sparkplug B payload: {exc}") from None
    metrics: list[Metric] = []
    for m in message.metrics:
        properties: dict[str, tuple[int, Value]] | None = None
        if m.HasField("properties"):
            properties = {}
            for key, value in zip(m.properties.keys, m.properties.values, strict=False):
                plain = _oneof(value)
                if plain is not None:
                    properties[key] = (value.type, plain)
        metrics.append(Metric(
            name=m.name if m.HasField("name") else None,
            alias=m.alias if m.HasField("alias") else None,
            timestamp=m.timestamp if m.HasField("timestamp") else None,
            datatype=m.datatype if m.HasField("datatype") else None,
            value=_oneof(m),
            is_null=m.is_null,
            properties=properties,
            is_historical=m.is_historical,
        ))
    return Payload(
        timestamp=message.timestamp if message.HasField("timestamp") else None,
        metrics=tuple(metrics),
        seq=message.seq if message.HasField("seq") else None,
    )
