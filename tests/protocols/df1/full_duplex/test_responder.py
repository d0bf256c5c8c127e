"""DF1 full-duplex responder (``gateway.protocols.df1.full_duplex.responder``): the link layer of DF1 target mode.

* the station's tables (``full_duplex/table.py``): every receiver input in both transmitter states,
  and every transmitter pair the responder can meet, walked through a real responder;
* byte scripts with a fake clock, each fed whole, byte by byte, and followed by trailing garbage;
* a property test: the responder against the master-side link (``Df1DataLink``) on a line that drops
  and damages frames and response symbols both ways.
"""

from __future__ import annotations

import itertools
from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import gateway.protocols.df1.full_duplex.station as station_module
from gateway.protocols.df1.framing import (
    ACK_SYMBOL,
    ENQ_SYMBOL,
    NAK_SYMBOL,
    NEED_DATA,
    Checksum,
    Frame,
    encode_frame,
)
from gateway.protocols.df1.framing.decoder import FrameDecoder
from gateway.protocols.df1.full_duplex.datalink import Df1DataLink, MessageReceived, SendComplete, SendFailed
from gateway.protocols.df1.full_duplex.responder import Df1Responder
from gateway.protocols.df1.full_duplex.responder_events import (
    CommandReceived,
    DuplicateReceived,
    ReplyDelivered,
    ReplyLost,
    ResponderEvent,
)
from gateway.protocols.df1.full_duplex.station import SendFailure, TxState
from gateway.protocols.df1.full_duplex.table import (
    RECEIVER,
    TRANSITIONS,
    RxInput,
    StationStep,
    TxAction,
    TxInput,
)
from gateway.protocols.df1.pccc.codec import HEADER_SIZE

S = TxState
STATION = 1


def command(tns: int, *, src: int = 0, dst: int = STATION, data: bytes = b"\x02\x07\x89\x00\x00") -> bytes:
    """An SLC protected typed logical read: DST SRC CMD STS TNS FNC ..."""
    return bytes((dst, src, 0x0F, 0x00)) + tns.to_bytes(2, "little") + b"\xa2" + data


def reply_to(packet: bytes, data: bytes | None = None) -> bytes:
    """Its reply: DST and SRC interchanged (1770-6.5.16 p. 6-4), CMD | 0x40, the same TNS."""
    body = data if data is not None else packet[4:6]
    return bytes((packet[1], packet[0], packet[2] | 0x40, 0x00)) + packet[4:6] + body


def frame(packet: bytes, checksum: Checksum = Checksum.CRC) -> bytes:
    return encode_frame(packet, checksum)


def damaged(data: bytes) -> bytes:
    """The frame with its last check byte wrong."""
    return data[:-1] + bytes((data[-1] ^ 0x01,))


def drain(responder: Df1Responder) -> list[ResponderEvent]:
    events: list[ResponderEvent] = []
    while (event := responder.next_event()) is not NEED_DATA:
        events.append(event)
    return events


C1, C2, C3 = command(1), command(2), command(3)
R1, R2, R3 = reply_to(C1), reply_to(C2), reply_to(C3)


def received(packet: bytes) -> CommandReceived:
    return CommandReceived(packet, packet[1], packet[0], packet[2], packet[4] | packet[5] << 8)


def duplicate(packet: bytes, reply_handle: int | None) -> DuplicateReceived:
    return DuplicateReceived(packet, packet[1], packet[2], packet[4] | packet[5] << 8, reply_handle)


# ---------------------------------------------------------------------------------------- table


def test_the_receiver_has_one_action_for_every_input() -> None:
    assert set(RECEIVER) == set(RxInput)


def test_a_missing_pair_raises(monkeypatch: pytest.MonkeyPatch) -> None:
    table = {pair: step for pair, step in TRANSITIONS.items() if pair != (S.IDLE, TxInput.SEND)}
    monkeypatch.setattr(station_module, "TRANSITIONS", table)
    responder = Df1Responder()
    responder.feed(frame(C1), 0.0)
    with pytest.raises(KeyError):
        responder.send_reply(R1, 0.0)


def _in_state(state: TxState) -> Df1Responder:
    """A responder in ``state`` that delivered C1 and gave its reply R1 (pending: none)."""
    responder = Df1Responder(station=STATION, check_dst=True, max_pending=1, nak_limit=1, enq_limit=1)
    responder.feed(frame(C1), 0.0)
    responder.send_reply(R1, 0.0)
    responder.data_to_send()
    if state is S.IDLE:
        responder.feed(ACK_SYMBOL, 0.0)
        responder.data_to_send()
    drain(responder)
    assert responder.state is state and responder.pending_commands == 0
    return responder


def _nak_twice(responder: Df1Responder) -> None:
    responder.feed(NAK_SYMBOL, 0.0)
    responder.data_to_send()
    responder.feed(NAK_SYMBOL, 0.0)


#: How the public API makes each input (some in both states, some only while a reply is on the line).
DRIVERS: dict[RxInput | TxInput, Any] = {
    RxInput.MESSAGE: lambda r: r.feed(frame(C2), 0.0),
    RxInput.DUPLICATE: lambda r: r.feed(frame(C1), 0.0),
    RxInput.NOT_FOR_US: lambda r: r.feed(frame(command(9, dst=STATION + 1)), 0.0),
    RxInput.SINK_FULL: lambda r: r.feed(frame(C2) + frame(C3), 0.0),
    RxInput.BAD_FRAME: lambda r: r.feed(damaged(frame(C2)), 0.0),
    RxInput.ENQ_IN_FRAME: lambda r: r.feed(frame(C2)[:6] + ENQ_SYMBOL, 0.0),
    RxInput.ENQ: lambda r: r.feed(ENQ_SYMBOL, 0.0),
    RxInput.NOISE: lambda r: r.feed(b"\x55", 0.0),
    TxInput.SEND: lambda r: r.send_reply(R2, 0.0),
    TxInput.ACK: lambda r: r.feed(ACK_SYMBOL, 0.0),
    TxInput.NAK: lambda r: r.feed(NAK_SYMBOL, 0.0),
    TxInput.NAK_LIMIT: _nak_twice,
    TxInput.STALE: lambda r: r.feed(NAK_SYMBOL + ACK_SYMBOL, 0.0),
    TxInput.TIMEOUT: lambda r: r.handle_timeout(1.0),
    TxInput.TIMEOUT_LIMIT: lambda r: (r.handle_timeout(1.0), r.handle_timeout(2.0)),
    TxInput.RESET: lambda r: r.reset(),
}

#: Pairs the public API cannot make: no reply on the line, so no NAK count, no frame in the output
#: and no timer.  They are ignored in the table, and walked through the machine's input directly.
UNREACHABLE = {(S.IDLE, TxInput.NAK_LIMIT), (S.IDLE, TxInput.STALE), (S.IDLE, TxInput.TIMEOUT),
               (S.IDLE, TxInput.TIMEOUT_LIMIT)}
#: The data link's own inputs: the responder never confirms a reply nor sends a frame that must
#: not run twice.
DATA_LINK_ONLY = {TxInput.CONFIRM, TxInput.NAK_NOT_PROOF}
PAIRS = [(state, what) for state in S for what in (*RxInput, *TxInput) if what not in DATA_LINK_ONLY]


@pytest.mark.parametrize("pair", PAIRS, ids=lambda p: f"{p[0].name}-{p[1].name}")
def test_walk_every_pair(pair: tuple[TxState, RxInput | TxInput]) -> None:
    state, what = pair
    responder = _in_state(state)
    before = len(responder.history)
    if pair in UNREACHABLE:
        assert isinstance(what, TxInput) and TRANSITIONS[pair].action is TxAction.IGNORE
        responder._tx(what, 0.0)
        assert responder.state is state and responder.data_to_send() == b"" and drain(responder) == []
    else:
        DRIVERS[what](responder)
    if isinstance(what, RxInput):
        step = StationStep(state, what, RECEIVER[what], state)
    else:
        action, next_state, _ = TRANSITIONS[state, what]
        step = StationStep(state, what, action, next_state)
    assert step in list(responder.history)[before:]


@pytest.mark.parametrize(("symbol", "what"), [(ACK_SYMBOL, TxInput.ACK), (NAK_SYMBOL, TxInput.NAK)])
def test_a_stray_answer_before_any_reply_is_a_stray_one_not_stale(symbol: bytes, what: TxInput) -> None:
    """No frame of ours has ever waited in the output: nothing the peer sends can be stale."""
    responder = Df1Responder(station=STATION)
    responder.feed(symbol, 0.0)
    assert list(responder.history) == [StationStep(S.IDLE, what, TxAction.IGNORE, S.IDLE)]


# ---------------------------------------------------------------------------------- byte scripts

#: ("in", bytes) feed; ("out", bytes) data_to_send() must be; ("reply", packet) send_reply;
#: ("at", t) the clock moves to t and handle_timeout runs; ("events", [...]) next_event() until
#: NEED_DATA must give; ("deadline", t) next_deadline() must be.
Script = list[tuple[str, object]]

MODES = ("whole", "byte by byte", "trailing garbage")
GARBAGE = b"\x55\x00\xff\x02\x03\x10\x41"  # ends in DLE + a byte that is no symbol: noise all through


def run(script: Script, mode: str, **options: Any) -> Df1Responder:
    responder = Df1Responder(**options)
    now = 0.0
    for kind, arg in script:
        if kind == "in":
            assert isinstance(arg, bytes)
            chunks = [arg[i : i + 1] for i in range(len(arg))] if mode == "byte by byte" else [arg]
            for chunk in chunks:
                responder.feed(chunk, now)
        elif kind == "out":
            assert responder.data_to_send() == arg, f"after {kind} step of {script}"
        elif kind == "reply":
            assert isinstance(arg, bytes)
            responder.send_reply(arg, now)
        elif kind == "at":
            assert isinstance(arg, float)
            now = arg
            responder.handle_timeout(now)
        elif kind == "events":
            assert drain(responder) == arg
        elif kind == "deadline":
            assert responder.next_deadline() == arg
        else:
            raise AssertionError(kind)
    assert responder.data_to_send() == b"" and drain(responder) == [], "the script left output or events"
    if mode == "trailing garbage":
        noise = responder.counters.noise
        responder.feed(GARBAGE, now)
        assert responder.data_to_send() == b"" and drain(responder) == []
        assert responder.counters.noise > noise
        responder.feed(ENQ_SYMBOL, now)
        assert responder.data_to_send() == NAK_SYMBOL  # noise made the last response DLE NAK
    return responder


SCRIPTS: dict[str, tuple[Script, dict[str, Any]]] = {
    "command, reply, ACK": ([
        ("in", frame(C1)), ("out", ACK_SYMBOL), ("events", [received(C1)]),
        ("reply", R1), ("out", frame(R1)), ("deadline", 1.0),
        ("in", ACK_SYMBOL), ("events", [ReplyDelivered(1, R1)]), ("deadline", None),
    ], {}),
    "damaged frame NAKed, ENQ repeats the last response": ([
        ("in", ENQ_SYMBOL), ("out", NAK_SYMBOL),  # nothing answered yet: DLE NAK
        ("in", damaged(frame(C1))), ("out", NAK_SYMBOL), ("events", []),
        ("in", ENQ_SYMBOL), ("out", NAK_SYMBOL),
        ("in", frame(C1)), ("out", ACK_SYMBOL), ("events", [received(C1)]),
        ("in", ENQ_SYMBOL + ENQ_SYMBOL), ("out", ACK_SYMBOL + ACK_SYMBOL),
        ("reply", R1), ("out", frame(R1)), ("in", ACK_SYMBOL), ("events", [ReplyDelivered(1, R1)]),
    ], {}),
    "leading and trailing noise in the same read": ([
        ("in", b"\x00\x55" + frame(C1) + b"\x66\x77"), ("out", ACK_SYMBOL), ("events", [received(C1)]),
        ("in", ENQ_SYMBOL), ("out", NAK_SYMBOL),  # "else LAST-RESPONSE = NAK" (p. 4-8)
        ("reply", R1), ("out", frame(R1)), ("in", ACK_SYMBOL), ("events", [ReplyDelivered(1, R1)]),
    ], {}),
    "DLE ETX without DLE STX is noise, not NAKed": ([
        ("in", frame(C1)), ("out", ACK_SYMBOL), ("events", [received(C1)]),
        ("in", frame(C2)[2:]), ("out", b""), ("events", []),
        ("in", ENQ_SYMBOL), ("out", NAK_SYMBOL),
        ("reply", R1), ("out", frame(R1)), ("in", ACK_SYMBOL), ("events", [ReplyDelivered(1, R1)]),
    ], {}),
    "too short a packet is NAKed": ([
        ("in", frame(C1[:5])), ("out", NAK_SYMBOL), ("events", []),
    ], {}),
    # 1770-6.5.16 p. 4-13 (message transfer with re-transmission): the receiver discards the
    # duplicate message and the reply is returned once: one reply per TNS.
    "duplicate after the reply was delivered: ACKed, no second reply (p. 4-13)": ([
        ("in", frame(C1)), ("out", ACK_SYMBOL), ("events", [received(C1)]),
        ("reply", R1), ("out", frame(R1)), ("in", ACK_SYMBOL), ("events", [ReplyDelivered(1, R1)]),
        ("in", frame(C1)), ("out", ACK_SYMBOL), ("events", [duplicate(C1, None)]),
        ("at", 5.0), ("out", b""), ("events", []), ("deadline", None),
        ("in", frame(C2)), ("out", ACK_SYMBOL), ("events", [received(C2)]),
        ("reply", R2), ("out", frame(R2)), ("in", ACK_SYMBOL), ("events", [ReplyDelivered(2, R2)]),
    ], {}),
    "duplicate after the reply was lost: no second reply either (p. 4-13)": ([
        ("in", frame(C1)), ("out", ACK_SYMBOL), ("events", [received(C1)]),
        ("reply", R1), ("out", frame(R1)),
        ("in", NAK_SYMBOL), ("out", b""), ("events", [ReplyLost(1, R1, SendFailure.NAK_LIMIT)]),
        ("in", frame(C1)), ("out", ACK_SYMBOL), ("events", [duplicate(C1, None)]),
    ], {"nak_limit": 0}),
    "resend_reply: a duplicate after the reply was delivered gets the reply again": ([
        ("in", frame(C1)), ("out", ACK_SYMBOL), ("events", [received(C1)]),
        ("reply", R1), ("out", frame(R1)), ("in", ACK_SYMBOL), ("events", [ReplyDelivered(1, R1)]),
        ("in", frame(C1)), ("out", ACK_SYMBOL + frame(R1)), ("events", [duplicate(C1, 2)]),
        ("in", ACK_SYMBOL), ("events", [ReplyDelivered(2, R1)]),
        ("in", frame(C2)), ("out", ACK_SYMBOL), ("events", [received(C2)]),
        ("reply", R2), ("out", frame(R2)), ("in", ACK_SYMBOL), ("events", [ReplyDelivered(3, R2)]),
    ], {"resend_reply": True}),
    "duplicate before the reply, and while it is on the line: ACK only": ([
        ("in", frame(C1)), ("out", ACK_SYMBOL), ("events", [received(C1)]),
        ("in", frame(C1)), ("out", ACK_SYMBOL), ("events", [duplicate(C1, None)]),
        ("reply", R1), ("out", frame(R1)),
        ("in", frame(C1)), ("out", ACK_SYMBOL), ("events", [duplicate(C1, None)]),
        ("in", ACK_SYMBOL), ("events", [ReplyDelivered(1, R1)]),
    ], {}),
    "resend_reply: a duplicate after the reply was lost gives the reply another chance": ([
        ("in", frame(C1)), ("out", ACK_SYMBOL), ("events", [received(C1)]),
        ("reply", R1), ("out", frame(R1)),
        ("in", NAK_SYMBOL), ("out", b""), ("events", [ReplyLost(1, R1, SendFailure.NAK_LIMIT)]),
        ("in", frame(C1)), ("out", ACK_SYMBOL + frame(R1)), ("events", [duplicate(C1, 2)]),
        ("in", ACK_SYMBOL), ("events", [ReplyDelivered(2, R1)]),
    ], {"nak_limit": 0, "resend_reply": True}),
    "duplicate detection off: the copy is delivered again": ([
        ("in", frame(C1)), ("out", ACK_SYMBOL), ("events", [received(C1)]),
        ("in", frame(C1)), ("out", ACK_SYMBOL), ("events", [received(C1)]),
    ], {"duplicate_detect": False}),
    "a duplicate is SRC, CMD and TNS: another SRC is a new command": ([
        ("in", frame(C1)), ("out", ACK_SYMBOL), ("events", [received(C1)]),
        ("in", frame(command(1, src=5))), ("out", ACK_SYMBOL), ("events", [received(command(1, src=5))]),
        ("in", frame(command(1, src=5, dst=9, data=b"\x00"))), ("out", ACK_SYMBOL),
        ("events", [duplicate(command(1, src=5, dst=9, data=b"\x00"), None)]),
    ], {}),
    "DST is ignored by default": ([
        ("in", frame(command(1, dst=7))), ("out", ACK_SYMBOL), ("events", [received(command(1, dst=7))]),
    ], {}),
    "check_dst: another DST is ACKed, not delivered": ([
        ("in", frame(command(1, dst=7))), ("out", ACK_SYMBOL), ("events", []),
        ("in", ENQ_SYMBOL), ("out", ACK_SYMBOL),
        ("in", frame(C1)), ("out", ACK_SYMBOL), ("events", [received(C1)]),
    ], {"check_dst": True, "station": STATION}),
    "sink full: NAK until a reply is given": ([
        ("in", frame(C1)), ("out", ACK_SYMBOL), ("events", [received(C1)]),
        ("in", frame(C2)), ("out", NAK_SYMBOL), ("events", []),
        ("reply", R1), ("out", frame(R1)),
        ("in", frame(C2)), ("out", ACK_SYMBOL), ("events", [received(C2)]),
        ("in", ACK_SYMBOL), ("events", [ReplyDelivered(1, R1)]),
    ], {"max_pending": 1}),
    "an ACK embedded in an incoming frame completes our reply": ([
        ("in", frame(C1)), ("out", ACK_SYMBOL), ("events", [received(C1)]),
        ("reply", R1), ("out", frame(R1)),
        ("in", frame(C2)[:5] + ACK_SYMBOL + frame(C2)[5:]), ("out", ACK_SYMBOL),
        ("events", [ReplyDelivered(1, R1), received(C2)]),
    ], {}),
    "DLE ENQ inside a frame: the frame is NAKed and dropped": ([
        ("in", frame(C1)[:6] + ENQ_SYMBOL), ("out", NAK_SYMBOL), ("events", []),
        ("in", frame(C1)), ("out", ACK_SYMBOL), ("events", [received(C1)]),
    ], {}),
    "NAK: the same frame again, then lost; the next reply follows": ([
        ("in", frame(C1) + frame(C2)), ("out", ACK_SYMBOL + ACK_SYMBOL), ("events", [received(C1), received(C2)]),
        ("reply", R1), ("reply", R2), ("out", frame(R1)),
        ("in", NAK_SYMBOL), ("out", frame(R1)),
        ("in", NAK_SYMBOL), ("out", frame(R1)),
        ("in", NAK_SYMBOL), ("out", frame(R2)), ("events", [ReplyLost(1, R1, SendFailure.NAK_LIMIT)]),
        ("in", ACK_SYMBOL), ("events", [ReplyDelivered(2, R2)]),
    ], {"nak_limit": 2}),
    "timeout: ENQ, then lost": ([
        ("in", frame(C1)), ("out", ACK_SYMBOL), ("events", [received(C1)]),
        ("reply", R1), ("out", frame(R1)), ("deadline", 0.5),
        ("at", 0.499), ("out", b""),
        ("at", 0.5), ("out", ENQ_SYMBOL), ("deadline", 1.0),
        ("at", 1.0), ("out", ENQ_SYMBOL), ("deadline", 1.5),
        ("at", 1.5), ("out", b""), ("deadline", None), ("events", [ReplyLost(1, R1, SendFailure.NO_RESPONSE)]),
        ("in", ACK_SYMBOL), ("events", []),  # too late: ignored
    ], {"ack_timeout": 0.5, "enq_limit": 2}),
    "ENQ answered NAK: the frame again; ENQ answered ACK: delivered": ([
        ("in", frame(C1)), ("out", ACK_SYMBOL), ("events", [received(C1)]),
        ("reply", R1), ("out", frame(R1)),
        ("at", 1.0), ("out", ENQ_SYMBOL), ("in", NAK_SYMBOL), ("out", frame(R1)), ("deadline", 2.0),
        ("at", 2.0), ("out", ENQ_SYMBOL), ("in", ACK_SYMBOL), ("events", [ReplyDelivered(1, R1)]),
    ], {}),
    "ACK before our frame left the output answers an older frame": ([
        ("in", frame(C1)), ("out", ACK_SYMBOL), ("events", [received(C1)]),
        ("reply", R1), ("in", ACK_SYMBOL + NAK_SYMBOL), ("events", []),
        ("out", frame(R1)), ("in", ACK_SYMBOL), ("events", [ReplyDelivered(1, R1)]),
    ], {}),
    "replies go in order, one on the line at a time": ([
        ("in", frame(C1) + frame(C2) + frame(C3)), ("out", ACK_SYMBOL * 3),
        ("events", [received(C1), received(C2), received(C3)]),
        ("reply", R2), ("reply", R1), ("reply", R3), ("out", frame(R2)),
        ("in", ACK_SYMBOL), ("events", [ReplyDelivered(1, R2)]), ("out", frame(R1)),
        ("in", ACK_SYMBOL), ("events", [ReplyDelivered(2, R1)]), ("out", frame(R3)),
        ("in", ACK_SYMBOL), ("events", [ReplyDelivered(3, R3)]),
    ], {}),
    "BCC and DLE in the packet": ([
        ("in", frame(command(0x1010, data=b"\x10\x10\x03"), Checksum.BCC)), ("out", ACK_SYMBOL),
        ("events", [received(command(0x1010, data=b"\x10\x10\x03"))]),
        ("reply", reply_to(command(0x1010))), ("out", frame(reply_to(command(0x1010)), Checksum.BCC)),
        ("in", ACK_SYMBOL), ("events", [ReplyDelivered(1, reply_to(command(0x1010)))]),
    ], {"checksum": Checksum.BCC}),
}


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("name", list(SCRIPTS))
def test_script(name: str, mode: str) -> None:
    script, options = SCRIPTS[name]
    run(script, mode, **options)


def test_counters_after_a_busy_script() -> None:
    script, options = SCRIPTS["NAK: the same frame again, then lost; the next reply follows"]
    counters = run(script, "whole", **options).counters
    assert (counters.frames_received, counters.commands_delivered, counters.acks_sent) == (2, 2, 2)
    assert (counters.frames_sent, counters.retransmissions, counters.naks_received) == (4, 2, 3)
    assert (counters.replies_delivered, counters.replies_lost) == (1, 1)
    script, options = SCRIPTS["resend_reply: a duplicate after the reply was delivered gets the reply again"]
    counters = run(script, "whole", **options).counters
    assert (counters.duplicates, counters.replies_resent, counters.commands_delivered) == (1, 1, 2)
    counters = run(SCRIPTS["damaged frame NAKed, ENQ repeats the last response"][0], "whole").counters
    assert (counters.bad_frames, counters.enqs_received, counters.naks_sent) == (1, 4, 3)


def test_a_reply_is_matched_by_cmd_and_tns_and_frees_the_sink() -> None:
    responder = Df1Responder(max_pending=2)
    responder.feed(frame(C1) + frame(C2), 0.0)
    assert responder.pending_commands == 2
    responder.send_reply(reply_to(C1)[:1] + b"\x63" + reply_to(C1)[2:], 0.0)  # any SRC
    responder.send_reply(reply_to(C3), 0.0)  # answers nothing pending: sent, frees nothing
    assert responder.pending_commands == 1
    responder.send_reply(R2, 0.0)
    assert responder.pending_commands == 0 and responder.queued_replies == 3


def test_reset_loses_every_reply_and_forgets_the_line() -> None:
    responder = Df1Responder()
    responder.feed(frame(C1) + frame(C2), 0.0)
    responder.send_reply(R1, 0.0)
    responder.send_reply(R2, 0.0)
    drain(responder)
    responder.reset()
    assert drain(responder) == [ReplyLost(1, R1, SendFailure.LINK_RESET), ReplyLost(2, R2, SendFailure.LINK_RESET)]
    assert responder.data_to_send() == b"" and responder.next_deadline() is None
    assert responder.state is S.IDLE and responder.pending_commands == 0
    responder.feed(ENQ_SYMBOL + frame(C2), 0.0)
    assert responder.data_to_send() == NAK_SYMBOL + ACK_SYMBOL and drain(responder) == [received(C2)]


@pytest.mark.parametrize("options", [
    {"station": 255}, {"ack_timeout": 0.0}, {"nak_limit": -1}, {"enq_limit": -1}, {"max_pending": 0},
    {"max_message": 5},
])
def test_bad_options(options: dict[str, Any]) -> None:
    with pytest.raises(ValueError):
        Df1Responder(**options)


@pytest.mark.parametrize("packet", [b"", b"\x00\x01\x4f\x00\x01", bytes(600)])
def test_a_reply_must_be_a_packet(packet: bytes) -> None:
    with pytest.raises(ValueError):
        Df1Responder().send_reply(packet, 0.0)


# ------------------------------------------------------------------------------ faulty line

DELAY = 0.01  # one way, well under both ACK timeouts: an answer never comes after its timer
ACK_TIMEOUT = 0.3
FAULTS = ("pass", "drop", "corrupt", "split")


def corruptible(unit: bytes) -> list[int]:
    """Positions whose byte can be damaged without changing where frames start and end: never a
    DLE (0x10) or a byte that would become one (0x50), and after a DLE only the second byte of
    DLE ACK / NAK / ENQ.  A damaged frame then always fails its check (one byte off), and every
    unit ends with the decoders back outside a frame."""
    return [
        i for i, byte in enumerate(unit)
        if byte not in (0x10, 0x50) and (i == 0 or unit[i - 1] != 0x10 or byte in (0x05, 0x06, 0x15))
    ]


@dataclass
class Wire:
    """One direction of the line: units (one data_to_send() each) in flight, FIFO."""

    in_flight: deque[tuple[float, list[bytes]]] = field(default_factory=deque)
    intact: list[bytes] = field(default_factory=list)  #: units that arrived unaltered
    dropped: int = 0
    damaged: int = 0


def frames_in(units: list[bytes], checksum: Checksum) -> set[bytes]:
    decoder = FrameDecoder(checksum)
    found: set[bytes] = set()
    for unit in units:
        decoder.feed(unit)
        while (event := decoder.next_event()) is not NEED_DATA:
            if isinstance(event, Frame):
                found.add(event.message)
    return found


def simulate(faults: list[tuple[str, int]], commands: int, checksum: Checksum) -> None:
    peer = Df1DataLink(checksum=checksum, ack_timeout=ACK_TIMEOUT)
    responder = Df1Responder(checksum=checksum, ack_timeout=ACK_TIMEOUT)
    to_responder, to_peer = Wire(), Wire()
    script = iter(faults)
    sent = {command(tns, data=bytes((tns,))) for tns in range(1, commands + 1)}
    for packet in sorted(sent):
        peer.send(packet, 0.0)
    delivered: list[bytes] = []
    replies: dict[int, bytes] = {}  # handle -> packet, every reply queued
    outcomes: Counter[int] = Counter()
    delivered_replies: set[bytes] = set()
    peer_got: list[bytes] = []
    peer_completed: set[bytes] = set()
    now = 0.0

    def put(wire: Wire, unit: bytes) -> None:
        fault, seed = next(script, ("pass", 0))
        chunks = [unit]
        if fault == "drop":
            wire.dropped += 1
            return
        if fault == "corrupt" and (places := corruptible(unit)):
            i = places[seed % len(places)]
            chunks = [unit[:i] + bytes((unit[i] ^ 0x40,)) + unit[i + 1 :]]
            wire.damaged += 1
        else:
            wire.intact.append(unit)
            if fault == "split":
                cut = sorted({0, len(unit), *(seed % (k + 2) for k in range(3))})
                chunks = [unit[a:b] for a, b in itertools.pairwise(cut)]
        wire.in_flight.append((now + DELAY, chunks))

    for _ in range(100_000):
        moved = False
        if out := peer.data_to_send():
            put(to_responder, out)
        if out := responder.data_to_send():
            put(to_peer, out)
        for wire, is_responder in ((to_responder, True), (to_peer, False)):
            while wire.in_flight and wire.in_flight[0][0] <= now:
                for chunk in wire.in_flight.popleft()[1]:
                    if is_responder:
                        responder.feed(chunk, now)
                    else:
                        peer.receive_data(chunk, now)
                moved = True
        while (event := responder.next_event()) is not NEED_DATA:
            moved = True
            if isinstance(event, CommandReceived):
                delivered.append(event.packet)
                reply = reply_to(event.packet)
                replies[responder.send_reply(reply, now)] = reply
            elif isinstance(event, DuplicateReceived) and event.reply_handle is not None:
                replies[event.reply_handle] = reply_to(event.packet)
            elif isinstance(event, ReplyDelivered | ReplyLost):
                outcomes[event.handle] += 1
                if isinstance(event, ReplyDelivered):
                    delivered_replies.add(event.packet)
        while (link_event := peer.next_event()) is not NEED_DATA:
            moved = True
            if isinstance(link_event, MessageReceived):
                peer_got.append(link_event.payload)
            elif isinstance(link_event, SendComplete):
                peer_completed.add(sorted(sent)[link_event.handle - 1])
            else:
                assert isinstance(link_event, SendFailed)
        if moved:
            continue
        times = [wire.in_flight[0][0] for wire in (to_responder, to_peer) if wire.in_flight]
        times += [t for t in (responder.next_deadline(), peer.next_deadline()) if t is not None]
        if not times:
            break
        now = max(now, min(times))
        responder.handle_timeout(now)
        peer.handle_timeout(now)
    else:
        raise AssertionError("the line did not settle")

    # Commands: each delivered at most once, unaltered; each that reached us intact, exactly once.
    assert len(delivered) == len(set(delivered)) and set(delivered) <= sent
    assert frames_in(to_responder.intact, checksum) & sent <= set(delivered)
    # Replies: each queued one ends exactly once, delivered or lost; the peer gets each at most once.
    assert set(outcomes) == set(replies) and set(outcomes.values()) <= {1}
    assert len(peer_got) == len(set(peer_got)) and set(peer_got) <= set(replies.values())
    assert frames_in(to_peer.intact, checksum) & set(replies.values()) <= set(peer_got)
    # Without a frame lost whole (the protocol's known limit), an ACK is proof of delivery.
    if to_responder.dropped == 0:
        assert peer_completed <= set(delivered)
    if to_peer.dropped == 0:
        assert delivered_replies <= set(peer_got)
    # No frame lost whole and fewer damaged units than the retry limits (3 NAKs, 3 ENQs on both
    # sides): each damage costs at most one NAK or one ENQ, so nothing is given up.
    if to_responder.dropped + to_peer.dropped == 0 and to_responder.damaged + to_peer.damaged <= 3:
        assert set(delivered) == sent and peer_completed == sent
        assert set(peer_got) == {reply_to(packet) for packet in sent}
        assert all(replies[handle] in delivered_replies for handle in replies)
        assert responder.counters.replies_lost == 0
    assert responder.state is S.IDLE and responder.queued_replies == 0 and responder.pending_commands == 0
    assert peer.pending == 0


@settings(max_examples=150, deadline=None)
@given(
    faults=st.lists(st.tuples(st.sampled_from(FAULTS), st.integers(0, 2**16)), max_size=40),
    commands=st.integers(1, 6),
    checksum=st.sampled_from(list(Checksum)),
)
def test_each_command_once_each_reply_accounted_for_on_a_faulty_line(
    faults: list[tuple[str, int]], commands: int, checksum: Checksum
) -> None:
    simulate(faults, commands, checksum)


@settings(max_examples=150, deadline=None)
@given(
    damage=st.lists(st.tuples(st.integers(0, 40), st.integers(0, 2**16)), max_size=3),
    splits=st.lists(st.integers(0, 40), max_size=10),
    commands=st.integers(1, 6),
    checksum=st.sampled_from(list(Checksum)),
)
def test_a_few_damaged_units_lose_nothing(
    damage: list[tuple[int, int]], splits: list[int], commands: int, checksum: Checksum
) -> None:
    faults = [("split", 7) if i in splits else ("pass", 0) for i in range(41)]
    for i, seed in damage:
        faults[i] = ("corrupt", seed)
    simulate(faults, commands, checksum)


def test_a_clean_line_delivers_everything() -> None:
    simulate([], 5, Checksum.CRC)


# ------------------------------------------------------------------ edges of the public surface


def test_the_shortest_packet_is_a_command_and_the_shortest_reply_is_sent() -> None:
    responder = Df1Responder(max_message=8)
    header_only = command(1)[:6]
    responder.feed(frame(header_only), 0.0)
    assert responder.data_to_send() == ACK_SYMBOL and drain(responder) == [received(header_only)]
    reply = reply_to(header_only, b"")
    assert len(reply) == 6
    responder.send_reply(reply, 0.0)
    assert responder.data_to_send() == frame(reply)
    longest = reply_to(command(2), b"\x00\x00")
    assert len(longest) == responder.max_message
    responder.send_reply(longest, 0.0)  # accepted: as long as max_message
    assert responder.queued_replies == 2


def test_dle_dle_outside_a_frame_is_a_false_symbol() -> None:
    responder = Df1Responder()
    responder.feed(frame(C1), 0.0)
    assert responder.data_to_send() == ACK_SYMBOL
    responder.feed(b"\x10" + ENQ_SYMBOL, 0.0)  # DLE DLE ENQ: the first DLE starts nothing: noise
    assert responder.data_to_send() == NAK_SYMBOL and responder.counters.noise == 1
    responder.feed(frame(C2), 0.0)
    responder.feed(b"\x55" + ENQ_SYMBOL, 0.0)  # noise, then a DLE that does start a symbol
    assert responder.data_to_send() == ACK_SYMBOL + NAK_SYMBOL and responder.counters.noise == 2


def test_reset_forgets_a_dle_read_before_it() -> None:
    responder = Df1Responder()
    responder.feed(b"\x10", 0.0)
    responder.reset()
    responder.feed(frame(C1) + ENQ_SYMBOL, 0.0)
    assert responder.data_to_send() == ACK_SYMBOL + ACK_SYMBOL and responder.counters.noise == 0


def test_a_duplicate_gets_the_reply_of_its_own_command_only() -> None:
    responder = Df1Responder()
    responder.feed(frame(C1) + frame(C2), 0.0)
    responder.send_reply(R1, 0.0)  # answers C1, not C2 (the last command)
    responder.data_to_send()
    responder.feed(ACK_SYMBOL, 0.0)
    drain(responder)
    responder.feed(frame(C2), 0.0)  # a copy of C2: its reply was not given, nothing to resend
    assert responder.data_to_send() == ACK_SYMBOL and drain(responder) == [duplicate(C2, None)]


@pytest.mark.parametrize("resend_reply", [False, True])
def test_a_duplicate_after_the_previous_reply_was_given_is_not_answered_with_it(resend_reply: bool) -> None:
    """C1 answered and delivered, then C2 arrives and its copy comes before C2's reply is given:
    the copy is ACKed and nothing is sent (R1 answers C1, never C2; p. 6-3 ties a reply to its
    command's SRC, CMD and TNS), whether or not a copy after the reply gets the reply again."""
    responder = Df1Responder(resend_reply=resend_reply)
    responder.feed(frame(C1), 0.0)
    assert drain(responder) == [received(C1)]
    responder.send_reply(R1, 0.0)
    assert responder.data_to_send() == ACK_SYMBOL + frame(R1)
    responder.feed(ACK_SYMBOL, 0.0)
    assert drain(responder) == [ReplyDelivered(1, R1)]
    responder.feed(frame(C2), 0.0)
    assert drain(responder) == [received(C2)]
    responder.feed(frame(C2), 0.0)  # the PLC lost our ACK and sends C2 again
    assert responder.data_to_send() == ACK_SYMBOL + ACK_SYMBOL
    assert drain(responder) == [duplicate(C2, None)] and responder.counters.replies_resent == 0
    responder.send_reply(R2, 0.0)  # C2's own reply, once it is given
    assert responder.data_to_send() == frame(R2)


def test_with_resend_reply_the_stored_reply_is_resent_for_every_later_copy() -> None:
    responder = Df1Responder(resend_reply=True)
    responder.feed(frame(C1), 0.0)
    drain(responder)
    responder.send_reply(R1, 0.0)
    for handle in (1, 2, 3):
        assert responder.data_to_send().endswith(frame(R1))
        responder.feed(ACK_SYMBOL, 0.0)
        assert drain(responder) == [ReplyDelivered(handle, R1)]
        responder.feed(frame(C1), 0.0)
        assert drain(responder) == [duplicate(C1, handle + 1)]
    assert responder.counters.replies_resent == 3


def test_a_reply_queued_behind_another_is_not_the_stored_one() -> None:
    responder = Df1Responder(max_pending=3, resend_reply=True)
    responder.feed(frame(C1) + frame(C2) + frame(C3), 0.0)
    responder.send_reply(R3, 0.0)  # the last command's reply: stored, on the line
    responder.send_reply(R1, 0.0)
    responder.send_reply(R2, 0.0)
    responder.data_to_send()
    responder.feed(ACK_SYMBOL, 0.0)  # R3 delivered; R1 on the line, R2 queued
    drain(responder)
    responder.feed(frame(C3), 0.0)  # R3 is neither on the line nor queued: sent again
    assert drain(responder) == [duplicate(C3, 4)]


def test_a_reply_finds_its_command_by_the_commands_src() -> None:
    """Two pending commands with the same CMD and TNS from two SRCs: the reply's DST picks one."""
    from_5, from_6 = command(1, src=5), command(1, src=6)
    responder = Df1Responder(resend_reply=True)
    responder.feed(frame(from_5) + frame(from_6), 0.0)
    drain(responder)
    responder.send_reply(reply_to(from_6), 0.0)  # answers the last command: its reply is stored
    responder.data_to_send()
    responder.feed(ACK_SYMBOL + frame(from_6), 0.0)
    assert drain(responder) == [ReplyDelivered(1, reply_to(from_6)), duplicate(from_6, 2)]
    assert responder.pending_commands == 1
    routed = bytes((0x63,)) + reply_to(from_5)[1:]  # a DST no pending command has as SRC
    responder.send_reply(routed, 0.0)  # still answers a command of that CMD and TNS
    assert responder.pending_commands == 0


def test_every_counter_counts_each_occurrence() -> None:
    responder = Df1Responder(station=STATION, check_dst=True, max_pending=1, nak_limit=0, enq_limit=0,
                             resend_reply=True)
    other = command(9, dst=STATION + 1)
    for _ in range(2):
        responder.feed(frame(other), 0.0)  # not for us
        responder.feed(damaged(frame(C1)), 0.0)  # bad
        responder.feed(b"\x55", 0.0)  # noise
    responder.feed(frame(C1) + frame(C2) + frame(C2), 0.0)  # delivered; the sink is full twice
    responder.feed(frame(C1) + frame(C1), 0.0)  # duplicates
    counters = responder.counters
    assert (counters.not_for_us, counters.bad_frames, counters.noise) == (2, 2, 2)
    assert (counters.commands_delivered, counters.sink_full, counters.duplicates) == (1, 2, 2)
    responder.send_reply(R1, 0.0)
    for answer in (ACK_SYMBOL, ACK_SYMBOL):  # delivered, then a copy of C1 gets it again: delivered
        responder.data_to_send()
        responder.feed(answer + frame(C1), 0.0)
    responder.data_to_send()
    responder.feed(NAK_SYMBOL + frame(C1), 0.0)  # lost (no retransmission), sent again for the copy
    responder.data_to_send()
    responder.handle_timeout(1.0)  # lost (no DLE ENQ)
    assert (counters.replies_delivered, counters.replies_lost, counters.replies_resent) == (2, 2, 3)
    assert counters.duplicates == 5
    responder.feed(frame(C1), 0.0)
    responder.reset()  # the resent reply on the line is lost
    assert counters.replies_lost == 3


def test_after_a_reset_a_stray_symbol_is_no_answer_to_a_forgotten_reply() -> None:
    """The reply on the line (still in the output, one DLE NAK already taken) is forgotten by the
    reset: a DLE ACK / DLE NAK that follows is a late symbol in IDLE, never STALE or NAK_LIMIT."""
    responder = Df1Responder(nak_limit=1)
    responder.feed(frame(C1), 0.0)
    responder.send_reply(R1, 0.0)
    responder.data_to_send()
    responder.feed(NAK_SYMBOL, 0.0)  # the frame again, in the output
    responder.reset()
    responder.feed(ACK_SYMBOL + NAK_SYMBOL, 0.0)
    steps = [(step.state, step.input) for step in list(responder.history)[-2:]]
    assert steps == [(S.IDLE, TxInput.ACK), (S.IDLE, TxInput.NAK)]


def test_after_a_reply_is_delivered_a_second_ack_is_a_late_symbol() -> None:
    responder = Df1Responder()
    responder.feed(frame(C1), 0.0)
    responder.send_reply(R1, 0.0)
    responder.data_to_send()
    responder.feed(ACK_SYMBOL + ACK_SYMBOL, 0.0)
    steps = [(step.state, step.input) for step in list(responder.history)[-2:]]
    assert steps == [(S.AWAIT_ACK, TxInput.ACK), (S.IDLE, TxInput.ACK)]


def test_bytes_read_before_a_reset_never_join_those_after_it() -> None:
    responder = Df1Responder()
    data = frame(C1)
    responder.feed(data[:8], 0.0)
    responder.reset()
    responder.feed(data[8:], 0.0)  # the rest of the frame, its DLE ETX without DLE STX: noise
    assert responder.data_to_send() == b"" and drain(responder) == []
    assert responder.counters.frames_received == 0


def test_a_late_nak_after_a_reply_was_given_up_is_a_nak_to_nothing() -> None:
    responder = Df1Responder(station=STATION, nak_limit=0)
    responder.feed(frame(C1), 0.0)
    responder.send_reply(R1, 0.0)
    responder.data_to_send()
    responder.feed(NAK_SYMBOL, 0.0)  # no retransmission left: the reply is lost
    assert drain(responder)[-1] == ReplyLost(1, R1, SendFailure.NAK_LIMIT)
    responder.feed(NAK_SYMBOL, 0.1)  # a late copy of that NAK
    assert (responder.history[-1].state, responder.history[-1].input) == (S.IDLE, TxInput.NAK)
    assert drain(responder) == [] and responder.data_to_send() == b""


# ------------------------------------------------------------------------- documented defaults


def test_by_default_the_sink_holds_four_commands() -> None:
    """The target driver passes no ``max_pending``: the fifth command without a reply is NAKed."""
    responder = Df1Responder()
    responder.feed(b"".join(frame(command(tns)) for tns in range(1, 6)), 0.0)
    assert responder.data_to_send() == ACK_SYMBOL * 4 + NAK_SYMBOL
    assert responder.pending_commands == 4 and responder.counters.sink_full == 1


def test_by_default_a_reply_is_given_up_after_three_retransmissions() -> None:
    """RM NAK retries 3: the fourth DLE NAK loses the reply (the target driver passes no ``nak_limit``)."""
    responder = Df1Responder()
    responder.feed(frame(C1), 0.0)
    responder.send_reply(R1, 0.0)
    drain(responder)
    assert responder.data_to_send() == ACK_SYMBOL + frame(R1)
    for _ in range(3):
        responder.feed(NAK_SYMBOL, 0.0)
        assert responder.data_to_send() == frame(R1) and drain(responder) == []
    responder.feed(NAK_SYMBOL, 0.0)
    assert drain(responder) == [ReplyLost(1, R1, SendFailure.NAK_LIMIT)] and responder.data_to_send() == b""


def test_by_default_a_reply_is_given_up_after_three_enqs() -> None:
    """RM ENQ retries 3: the fourth ACK timeout loses the reply (the target driver passes no ``enq_limit``)."""
    responder = Df1Responder()
    responder.feed(frame(C1), 0.0)
    responder.send_reply(R1, 0.0)
    drain(responder)
    responder.data_to_send()
    for _ in range(3):
        deadline = responder.next_deadline()
        assert deadline is not None
        responder.handle_timeout(deadline)
        assert responder.data_to_send() == ENQ_SYMBOL and drain(responder) == []
    deadline = responder.next_deadline()
    assert deadline is not None
    responder.handle_timeout(deadline)
    assert drain(responder) == [ReplyLost(1, R1, SendFailure.NO_RESPONSE)] and responder.data_to_send() == b""


def test_by_default_the_station_is_0() -> None:
    responder = Df1Responder(check_dst=True)
    responder.feed(frame(command(1, dst=0)) + frame(command(2, dst=1)), 0.0)
    assert drain(responder) == [received(command(1, dst=0))] and responder.counters.not_for_us == 1


def test_the_limits_of_the_options_are_accepted() -> None:
    assert Df1Responder(station=254).station == 254
    responder = Df1Responder(max_message=HEADER_SIZE)
    responder.feed(frame(command(1)[:HEADER_SIZE]), 0.0)
    assert drain(responder) == [received(command(1)[:HEADER_SIZE])]


def test_the_history_keeps_the_last_64_steps() -> None:
    """The diagnostic record of the transitions taken is bounded and holds the newest ones."""
    responder = Df1Responder()
    for _ in range(70):
        responder.feed(b"\x55", 0.0)
    responder.feed(ENQ_SYMBOL, 0.0)
    assert len(responder.history) == 64 and responder.history[-1].input is RxInput.ENQ
