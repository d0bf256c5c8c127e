"""Every reply form the manual allows is an answer to the core, and the core takes only what the
parser parses.

The manual prints the data reply as ``:<number of bytes> <address> <data byte(s)>`` with a 4-digit
``<number of bytes>`` in the command and, in its one printed reply (``:021FFE <device type>
<FRN #>``), a 2-digit one; a reply ends with ``<cr>``, and a device server may add LF.  The
parsers of :mod:`gateway.protocols.slc_ascii.commands` accept every such form; the transaction
core must take each of them as the answer to its command (it asks the same parser), and must
never take a reply the parser refuses.
"""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.errors import ProtocolError
from gateway.protocols.slc_ascii import commands as cmds
from gateway.protocols.slc_ascii.framing import DataReply, encode_data_reply
from gateway.protocols.slc_ascii.memory_map import is_readable
from gateway.protocols.slc_ascii.transaction import SlcSession, SlcVerdict

TIMEOUT = 0.3

#: every address of the "Reading Data" list with the counts it may be read with
READS = [(a, n) for a in range(0x113) for n in (1, 2) if is_readable(a, n)]


def _frame(body_hex: str, msg_id: int, *, crlf: bool, lower: bool) -> bytes:
    frame = encode_data_reply(body_hex, msg_id)
    if lower:  # "ascii hex characters": a controller may send a-f
        frame = frame[:1] + frame[1:-3].lower() + frame[-3:]
    return frame + b"\n" if crlf else frame


def _handshake(session: SlcSession, frn_body: str, *, crlf: bool, lower: bool) -> None:
    """A new session resyncs with ``#0108`` (ID 00) before its first command."""
    sent = session.data_to_send()
    assert sent.startswith(b"#010800"), sent
    session.receive_data(_frame(frn_body, 0, crlf=crlf, lower=lower), 0.01)


def _run(command: cmds.Command, frn_body: str, reply_body: str, *, crlf: bool, lower: bool) -> SlcVerdict | None:
    """A fresh session: handshake, then ``command`` answered with ``reply_body`` (ID 01)."""
    session = SlcSession(timeout=TIMEOUT, retries=3)
    session.start(command, 0.0)
    _handshake(session, frn_body, crlf=crlf, lower=lower)
    assert session.data_to_send().startswith(b"#"), "the command follows the handshake at once"
    session.receive_data(_frame(reply_body, 1, crlf=crlf, lower=lower), 0.02)
    return session.result.verdict if session.result is not None else None


def _count(n: int, digits: int) -> str:
    return f"{n:0{digits}X}"


frn_bodies = st.builds(lambda d, device, frn: f"{_count(2, d)}1FFE{device:02X}{frn:02X}",
                       st.sampled_from((2, 4)), st.integers(0, 255), st.integers(0, 255))


@settings(max_examples=300, deadline=None)
@given(read=st.sampled_from(READS), digits=st.sampled_from((2, 4)), frn=frn_bodies, crlf=st.booleans(),
       lower=st.booleans(), data=st.binary(min_size=2, max_size=2))
def test_every_read_reply_form_is_the_answer(read: tuple[int, int], digits: int, frn: str, crlf: bool,
                                             lower: bool, data: bytes) -> None:
    address, count = read
    body = f"{_count(count, digits)}{address:04X}{data[:count].hex().upper()}"
    command = cmds.read_bytes(address, count)
    assert cmds.parse_reply(command, body) == data[:count]  # the parser takes it ...
    assert _run(command, frn, body, crlf=crlf, lower=lower) is SlcVerdict.DONE  # ... and so does the core


@settings(max_examples=100, deadline=None)
@given(frn=frn_bodies, crlf=st.booleans(), lower=st.booleans())
def test_every_frn_reply_form_completes_the_resync(frn: str, crlf: bool, lower: bool) -> None:
    # the handshake answered in either width; the write then goes out with ID 01 and is answered
    session = SlcSession(timeout=TIMEOUT, retries=3)
    session.start(cmds.read_frn(), 0.0)
    _handshake(session, frn, crlf=crlf, lower=lower)
    sent = session.data_to_send()
    assert sent.startswith(b"#010801"), f"FRN reply {frn!r} did not end the resync: sent {sent!r}"
    session.receive_data(_frame(frn, 1, crlf=crlf, lower=lower), 0.02)
    assert session.result is not None and session.result.verdict is SlcVerdict.DONE
    assert isinstance(session.result.answer, DataReply)
    assert cmds.parse_reply(cmds.read_frn(), session.result.answer.body_hex) == cmds.parse_frn_reply(frn)


@settings(max_examples=100, deadline=None)
@given(digits=st.sampled_from((2, 4)), frn=frn_bodies, user=st.integers(0x901, 0x932), word=st.integers(0, 0xFFFF),
       sequencer=st.booleans(), crlf=st.booleans())
def test_every_word_reply_form_is_the_answer(digits: int, frn: str, user: int, word: int, sequencer: bool,
                                             crlf: bool) -> None:
    command = cmds.read_sequencer_preset(0x10, 1) if sequencer else cmds.read_reset_accumulator(0x20)
    body = f"{_count(2, digits)}{user:04X}{word:04X}"
    assert cmds.parse_reply(command, body).value == word & 0x7FFF  # type: ignore[union-attr]
    assert _run(command, frn, body, crlf=crlf, lower=False) is SlcVerdict.DONE


@settings(max_examples=400, deadline=None)
@given(read=st.sampled_from(READS), body=st.one_of(
    st.binary(min_size=1, max_size=8).map(lambda b: b.hex().upper()),
    st.builds(lambda d, c, a, data: f"{_count(c, d)}{a:04X}{data.hex().upper()}", st.sampled_from((2, 4)),
              st.integers(0, 3), st.integers(0, 0x120), st.binary(max_size=3))))
def test_the_core_takes_a_data_reply_exactly_when_the_parser_parses_it(read: tuple[int, int], body: str) -> None:
    # the reverse direction: a reply the core accepts as the answer is one the parser can parse,
    # and a reply the parser refuses is not an answer (the read resends instead)
    address, count = read
    command = cmds.read_bytes(address, count)
    try:
        cmds.parse_reply(command, body)
        parses = True
    except ProtocolError:
        parses = False
    verdict = _run(command, "021FFE1547", body, crlf=False, lower=False)
    assert (verdict is SlcVerdict.DONE) is parses, (body, verdict)
