"""The multi-drop DF1 half-duplex slave model and its variant switches
(docs/develop/df1-half-duplex-notes.md §4, §5)."""

from __future__ import annotations

import pytest

from gateway.kinds.df1.sim.df1_half_duplex_slave import VARIANTS, HalfDuplexSlave, SlaveVariant
from gateway.protocols.df1.framing import (
    ACK_SYMBOL,
    EOT_SYMBOL,
    NAK_SYMBOL,
    Checksum,
    encode_frame,
    encode_master_message,
    encode_poll,
)


def command(station: int, tns: int) -> bytes:
    return bytes((station, 0, 0x0F, 0x00)) + tns.to_bytes(2, "little") + b"\x01"


def answer(cmd: bytes) -> bytes:
    return bytes((cmd[1], cmd[0], cmd[2] | 0x40, 0)) + cmd[4:6]


def make(station: int = 3, **choices: str) -> tuple[HalfDuplexSlave, list[bytes]]:
    executed: list[bytes] = []

    def handler(cmd: bytes) -> bytes:
        executed.append(cmd)
        return answer(cmd)

    return HalfDuplexSlave(station, Checksum.BCC, handler, SlaveVariant.from_choices(choices)), executed


def test_poll_with_nothing_to_send_answers_eot_and_other_stations_are_ignored() -> None:
    """KA p. 11-12: DLE EOT when nothing is queued; polls for other STNs get no answer."""
    slave, _ = make(3)
    slave.receive_data(encode_poll(4))
    assert slave.data_to_send() == b""
    slave.receive_data(encode_poll(3))
    assert slave.data_to_send() == EOT_SYMBOL


def test_message_ack_reply_on_poll_then_eot() -> None:
    slave, executed = make(3)
    cmd = command(3, 9)
    slave.receive_data(encode_master_message(3, cmd, Checksum.BCC))
    assert slave.data_to_send() == ACK_SYMBOL
    assert executed == [cmd]
    slave.receive_data(encode_poll(3))
    assert slave.data_to_send() == encode_frame(answer(cmd), Checksum.BCC)
    slave.receive_data(ACK_SYMBOL + encode_poll(3))
    assert slave.data_to_send() == EOT_SYMBOL


def test_duplicate_detection_switch() -> None:
    """KA p. 11-12: same SRC, CMD, TNS -> ACK without executing; switch off -> executed again."""
    frame = encode_master_message(3, command(3, 9), Checksum.BCC)
    slave, executed = make(3)
    slave.receive_data(frame + frame)
    assert slave.data_to_send() == ACK_SYMBOL + ACK_SYMBOL
    assert len(executed) == 1
    slave, executed = make(3, duplicate_detect="off")
    slave.receive_data(frame + frame)
    assert len(executed) == 2


@pytest.mark.parametrize(("reading", "expected"), [("silent", b""), ("nak", NAK_SYMBOL)])
def test_bad_frame_reply_switch(reading: str, expected: bytes) -> None:
    frame = bytearray(encode_master_message(3, command(3, 1), Checksum.BCC))
    frame[-1] ^= 1
    slave, executed = make(3, bad_frame_reply=reading)
    slave.receive_data(bytes(frame))
    assert slave.data_to_send() == expected
    assert executed == []


@pytest.mark.parametrize(("reading", "sends"), [("unlimited", 6), ("3", 4), ("0", 1)])
def test_reply_retries_switch(reading: str, sends: int) -> None:
    """KA p. 11-12: an unacknowledged message is resent at each poll, up to a limit (or forever)."""
    slave, _ = make(3, reply_retries=reading)
    slave.initiate(b"\x00\x03\x0f\x00\x01\x00")
    frame = encode_frame(b"\x00\x03\x0f\x00\x01\x00", Checksum.BCC)
    answers = []
    for _ in range(6):
        slave.receive_data(encode_poll(3))
        answers.append(slave.data_to_send())
    assert answers.count(frame) == sends
    assert answers[sends:] == [EOT_SYMBOL] * (6 - sends)


def test_silent_when_busy_switch() -> None:
    slave, _ = make(3, when_busy="silent")
    slave.busy = 1
    slave.receive_data(encode_poll(3))
    assert slave.data_to_send() == b""
    slave.receive_data(encode_poll(3))
    assert slave.data_to_send() == EOT_SYMBOL


def test_link_reset_drops_queued_messages() -> None:
    """Table 2.C: DLE NAK cancels every message ready to go to the master."""
    slave, _ = make(3)
    slave.initiate(b"\x00\x03\x0f\x00\x01\x00")
    slave.receive_data(NAK_SYMBOL + encode_poll(3))
    assert slave.data_to_send() == EOT_SYMBOL
    assert slave.counters.link_resets == 1


def test_variant_table_rejects_unknown_readings() -> None:
    assert set(VARIANTS) == {"bad_frame_reply", "reply_retries", "duplicate_detect", "when_busy", "reply_addresses"}
    with pytest.raises(ValueError, match="not one of"):
        SlaveVariant.from_choices({"bad_frame_reply": "shout"})


@pytest.mark.parametrize("reading", ["swapped", "unswapped", "own_station"])
def test_reply_addresses_variant(reading: str) -> None:
    """``reply_addresses``: DST / SRC of the reply as 1770-6.5.16 p. 6-4 has them, or as some
    devices fill them (docs/develop/controller-variants.md)."""
    from gateway.kinds.df1.sim.slc500_line import address_reply

    command = bytes((3, 0, 0x0F, 0, 0x34, 0x12, 0xA2))
    reply = bytes((0, 3, 0x4F, 0, 0x34, 0x12))
    expected = {"swapped": reply, "unswapped": bytes((3, 0)) + reply[2:], "own_station": bytes((0, 9)) + reply[2:]}
    assert address_reply(command, reply, reading, own_station=9) == expected[reading]
    assert SlaveVariant.from_choices({"reply_addresses": reading}).reply_addresses == reading
