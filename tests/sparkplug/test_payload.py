"""Sparkplug B values (``gateway.sparkplug.payload``): a received integer taken as its metric's datatype.

A DCMD's integer must fit the metric's datatype (Sparkplug 3.0 §6.4.16): every type's minimum and
maximum are taken as they are, one past either end is refused (the write is not made), through
the protobuf encoding as a host sends them.
"""

from __future__ import annotations

import pytest

from gateway.sparkplug.payload import _PAYLOAD, Metric, Payload, PayloadError, SparkplugType, decode, encode, typed

#: datatype -> (minimum, maximum), written out from the types' definitions (§6.4.16)
LIMITS = {
    SparkplugType.Int8: (-128, 127),
    SparkplugType.Int16: (-32768, 32767),
    SparkplugType.Int32: (-2147483648, 2147483647),
    SparkplugType.Int64: (-9223372036854775808, 9223372036854775807),
    SparkplugType.UInt8: (0, 255),
    SparkplugType.UInt16: (0, 65535),
    SparkplugType.UInt32: (0, 4294967295),
    SparkplugType.UInt64: (0, 18446744073709551615),
}


def received(datatype: SparkplugType, value: int) -> int | bool | float | str | bytes:
    """``value`` as a DCMD metric of ``datatype``: encoded, decoded, taken as the datatype."""
    (metric,) = decode(encode(Payload(0, [Metric(name="m", datatype=datatype, value=value)]))).metrics
    assert metric.value is not None
    return typed(datatype, metric.value)


#: datatype -> its width in bits
BITS = {SparkplugType.Int8: 8, SparkplugType.Int16: 16, SparkplugType.Int32: 32, SparkplugType.Int64: 64,
        SparkplugType.UInt8: 8, SparkplugType.UInt16: 16, SparkplugType.UInt32: 32, SparkplugType.UInt64: 64}


@pytest.mark.parametrize("datatype", list(LIMITS), ids=lambda d: d.name)
def test_every_integer_type_takes_its_minimum_and_maximum_and_refuses_one_past(datatype: SparkplugType) -> None:
    low, high = LIMITS[datatype]
    middle = (low + high) // 2
    for value in (low, low + 1, middle, high - 1, high):
        assert typed(datatype, value) == value
    # one past: below the minimum, and past the type's width (a signed type's max + 1 is the two's
    # complement of its minimum, in its own width: taken as the minimum, as a host may send it)
    for value in (low - 1, high + 1 if low == 0 else 1 << BITS[datatype]):
        with pytest.raises(PayloadError):
            typed(datatype, value)
    if low < 0:
        assert typed(datatype, high + 1) == low
        assert typed(datatype, (1 << BITS[datatype]) - 1) == -1


@pytest.mark.parametrize("datatype", list(LIMITS), ids=lambda d: d.name)
def test_the_limits_survive_the_wire(datatype: SparkplugType) -> None:
    low, high = LIMITS[datatype]
    assert received(datatype, low) == low
    assert received(datatype, high) == high


def test_an_unsigned_16_bit_value_with_its_top_bit_set_is_itself_not_negative() -> None:
    for value in (32768, 40000, 65535):
        assert received(SparkplugType.UInt16, value) == value
    assert received(SparkplugType.UInt8, 200) == 200
    assert received(SparkplugType.UInt32, 3_000_000_000) == 3_000_000_000
    for value in (-1, 0xFFFF8000, 0xFFFFFFFB):  # an unsigned type has no sign to extend
        with pytest.raises(PayloadError):
            typed(SparkplugType.UInt16, value)


def test_a_signed_value_sign_extended_to_its_field_is_taken_back_to_its_own_width() -> None:
    # an Int16 -5 as a host may send it: 16 bits (0xFFFB) or sign-extended to 32 (0xFFFFFFFB)
    assert typed(SparkplugType.Int16, 0xFFFB) == -5
    assert typed(SparkplugType.Int16, 0xFFFFFFFB) == -5
    assert typed(SparkplugType.Int8, 0xFF) == -1
    assert typed(SparkplugType.Int8, 0xFFFFFF80) == -128
    for value in (0x1FFFB, 0xFFFF0000):  # bits past 16 that are not a sign extension
        with pytest.raises(PayloadError):
            typed(SparkplugType.Int16, value)


def test_a_boolean_is_not_an_integer_and_an_integer_not_a_boolean() -> None:
    with pytest.raises(PayloadError):
        typed(SparkplugType.UInt16, True)
    with pytest.raises(PayloadError):
        typed(SparkplugType.Boolean, 1)


@pytest.mark.parametrize(("datatype", "value"), [
    (SparkplugType.Double, 1.25), (SparkplugType.Float, 0.5), (SparkplugType.Boolean, True),
    (SparkplugType.String, "text"), (SparkplugType.Text, "more"), (SparkplugType.Bytes, b"\x00\xff"),
    (SparkplugType.File, b"%PDF"), (SparkplugType.Int16, 7),
], ids=lambda v: getattr(v, "name", ""))
def test_every_plain_datatype_survives_the_wire(datatype: SparkplugType, value: object) -> None:
    (metric,) = decode(encode(Payload(0, [Metric(name="m", datatype=datatype, value=value)]))).metrics  # type: ignore[arg-type]
    assert metric.value == value and type(metric.value) is type(value)


def test_a_message_or_metric_without_a_timestamp_has_none() -> None:
    payload = decode(encode(Payload(None, [Metric(name="m", datatype=SparkplugType.Int16, value=1)])))
    assert payload.timestamp is None and payload.metrics[0].timestamp is None
    payload = decode(encode(Payload(0, [Metric(name="m", timestamp=0, datatype=SparkplugType.Int16, value=1)])))
    assert payload.timestamp == 0 and payload.metrics[0].timestamp == 0


def test_a_property_set_with_more_keys_than_values_is_read_pair_by_pair() -> None:
    """A host's malformed property set does not make its message unreadable."""
    message = _PAYLOAD()
    metric = message.metrics.add()
    metric.name, metric.datatype, metric.int_value = "m", SparkplugType.Int16, 3
    metric.properties.keys.extend(["Quality", "extra"])
    metric.properties.values.add(type=SparkplugType.Int32, int_value=192)
    (decoded,) = decode(message.SerializeToString()).metrics
    assert decoded.value == 3
    assert decoded.properties == {"Quality": (SparkplugType.Int32, 192)}


def test_a_float_metric_takes_a_number_as_a_float_and_nothing_else() -> None:
    for datatype in (SparkplugType.Float, SparkplugType.Double):
        assert typed(datatype, 1) == 1.0 and type(typed(datatype, 1)) is float
        for wrong in (True, "1.5", b"\x00"):
            with pytest.raises(PayloadError):
                typed(datatype, wrong)


def test_a_refused_integer_is_named_as_received() -> None:
    for raw in (1 << 32, (1 << 32) + 5):
        with pytest.raises(PayloadError, match=f"^{raw} does not fit Int16"):
            typed(SparkplugType.Int16, raw)
