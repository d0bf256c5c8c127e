"""``sim://plc-msg``: a PLC whose MSG instructions read and write the gateway (DF1 target mode).

It plays the initiating station on a DF1 full-duplex link: a PLC-5, SLC 500 or ControlLogix
channel 0 whose ladder runs MSG instructions at the gateway, as the S4516-DF1 manual's examples
do.  Its link and transaction layers are the gateway's own master cores
(:class:`~gateway.protocols.df1.full_duplex.datalink.Df1DataLink`,
:class:`~gateway.protocols.df1.full_duplex.transaction.Df1Transactions`):
DLE ACK / NAK / ENQ, retransmission, one TNS per message.  A MSG whose reply does not come is
sent again with a new TNS, as a PLC's ladder re-triggers an errored MSG (every command of the
script is safe to repeat).

The script (:data:`DEMO_SCRIPT`, repeated every ``cycle`` seconds, one MSG every ``every``
seconds) covers every command family the target answers:

=====  =====================================  =====================================================
CMD    MSG                                    what it does
=====  =====================================  =====================================================
0F AA  SLC typed logical write N7:0, 10 words a counter that advances every cycle
0F A2  SLC typed logical read N7:10, 10 words  setpoints a SCADA client writes
0F AA  SLC typed logical write F8:0, 4 floats  a slow sine
0F AB  masked write B3:0                       one bit walks through the word
0F 00  PLC-5 word range write N7:20, 5 words   the counter again, PLC-5 style
0F 01  PLC-5 word range read N7:10, 5 words
0F 67  PLC-5 typed write N7:30, 5 words        what a ControlLogix "PLC5 Typed" MSG sends
0F 68  PLC-5 typed read N7:30, 5 words
06 03  diagnostic status                       once every 10 cycles
06 00  echo
=====  =====================================  =====================================================

Faults (URL options, 1 in N): ``corrupt`` (a frame we send is damaged: the gateway NAKs it),
``lose_ack`` (a DLE ACK from the gateway is lost: we send DLE ENQ, or the frame again - a
duplicate the gateway must not run twice), ``nak_reply`` (a reply frame arrives damaged: we NAK
it and the gateway sends it again), ``duplicate`` (a frame we send goes out twice, as a PLC that
answers a lost DLE ACK by sending the frame again rather than DLE ENQ: the gateway must ACK the
copy and not run it again); ``seed``, ``every``, ``cycle``, ``station`` (the gateway's node,
our DST), ``source`` (ours), ``checksum``, ``scan`` (``scan=0.05`` or ``scan=0.02-0.06`` seconds,
:mod:`gateway.sim.scan`: the ladder enables a MSG during a scan and the channel sends it at the end
of that scan, so each MSG goes out at the end of the scan in progress when its turn comes).
Results: :attr:`PlcMsgSimulator.counters` and
:attr:`PlcMsgSimulator.log` (the last results, newest last).
"""

from __future__ import annotations

import math
import random
import struct
from collections import Counter, deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Final

from gateway.frozen import frozen
from gateway.protocols.df1.address import FileType
from gateway.protocols.df1.framing import (
    ACK_SYMBOL,
    DEFAULT_ACK_TIMEOUT,
    DEFAULT_CHECKSUM,
    ENQ_SYMBOL,
    NAK_SYMBOL,
    NEED_DATA,
    AckReceived,
    Checksum,
    EnqReceived,
    Frame,
    NakReceived,
    Symbol,
    encode_frame,
)
from gateway.protocols.df1.framing.decoder import FrameDecoder
from gateway.protocols.df1.full_duplex.datalink import Df1DataLink
from gateway.protocols.df1.full_duplex.transaction import (
    Df1Transactions,
    OutcomeUnknown,
    TransactionDone,
    TransactionFailed,
    TransactionRefused,
)
from gateway.protocols.df1.pccc import (
    DiagnosticStatus,
    LogicalBinaryAddress,
    ProtectedTypedLogicalMaskedWrite,
    ProtectedTypedLogicalRead,
    ProtectedTypedLogicalWrite,
    Request,
    TypedRead,
    TypedWrite,
    WordRangeRead,
    WordRangeWrite,
)
from gateway.protocols.df1.pccc.plc5 import DataType
from gateway.protocols.df1.pccc.slc import Echo
from gateway.sim.scan import SCAN_OPTION, ScanTime, parse_scan, scan_clock
from gateway.sim.serve import Output

__all__ = ["DEMO_SCRIPT", "PlcMsgSimulator", "create_plc_msg"]

_DLE: Final = Symbol.DLE

#: one MSG of the script: (label, request builder taking the cycle number)
Msg = tuple[str, Callable[[int], Request]]


def _le_words(values: Sequence[int]) -> bytes:
    return b"".join((v & 0xFFFF).to_bytes(2, "little") for v in values)


def _counting(cycle: int, n: int) -> list[int]:
    return [(cycle * n + k) & 0x7FFF for k in range(n)]


DEMO_SCRIPT: tuple[Msg, ...] = (
    ("SLC typed logical write N7:0-9",
     lambda c: ProtectedTypedLogicalWrite(FileType.INTEGER, 7, 0, 0, _le_words(_counting(c, 10)))),
    ("SLC typed logical read N7:10-19", lambda c: ProtectedTypedLogicalRead(FileType.INTEGER, 7, 10, 0, 20)),
    ("SLC typed logical write F8:0-3", lambda c: ProtectedTypedLogicalWrite(
        FileType.FLOAT, 8, 0, 0, b"".join(struct.pack("<f", math.sin(c / 10 + k)) for k in range(4)))),
    ("masked write B3:0", lambda c: ProtectedTypedLogicalMaskedWrite(
        FileType.BIT, 3, 0, 0, 0xFFFF, (1 << (c % 16)).to_bytes(2, "little"))),
    ("PLC-5 word range write N7:20-24", lambda c: WordRangeWrite(LogicalBinaryAddress.for_element(7, 20),
                                                                 _le_words(_counting(c, 5)))),
    ("PLC-5 word range read N7:10-14", lambda c: WordRangeRead(LogicalBinaryAddress.for_element(7, 10), 10)),
    ("PLC-5 typed write N7:30-34", lambda c: TypedWrite(LogicalBinaryAddress.for_element(7, 30), DataType.INTEGER, 2,
                                                        _le_words([c & 0x7FFF] * 5))),
    ("PLC-5 typed read N7:30-34", lambda c: TypedRead(LogicalBinaryAddress.for_element(7, 30), 5)),
    ("diagnostic status", lambda c: DiagnosticStatus()),
    ("echo", lambda c: Echo(b"slc-gateway %d" % c)),
)


@frozen
class MsgResult:
    cycle: int
    label: str
    outcome: str  # "done", "refused STS xx", "failed: ..."


@dataclass
class PlcMsgCounters:
    sent: int = 0
    done: int = 0
    refused: int = 0
    failed: int = 0
    faults: Counter[str] = field(default_factory=Counter)


class PlcMsgSimulator:
    """The initiating PLC (module doc).  A :class:`gateway.sim.serve.SimDevice`."""

    def __init__(self, *, script: Sequence[Msg] = DEMO_SCRIPT, every: float = 0.1, cycle: float = 1.0,
                 station: int = 1, source: int = 0, checksum: Checksum = DEFAULT_CHECKSUM, corrupt: int = 0,
                 lose_ack: int = 0, nak_reply: int = 0, duplicate: int = 0, seed: int = 1,
                 scan: ScanTime | None = None) -> None:
        self.script = tuple(script)
        self.every = every
        self.cycle_time = cycle
        self.checksum = checksum
        #: the one DF1 decoder, reading our own bytes and the gateway's (to inject faults per frame)
        self._out_decoder = FrameDecoder(checksum)
        self._in_decoder = FrameDecoder(checksum)
        self.link = Df1DataLink(checksum=checksum, ack_timeout=DEFAULT_ACK_TIMEOUT)
        self.core = Df1Transactions(self.link, station=station, source=source, reply_timeout=2.0, retries=2)
        self.faults = {"corrupt": corrupt, "lose_ack": lose_ack, "nak_reply": nak_reply, "duplicate": duplicate}
        self._random = random.Random(seed)
        self._scan_clock = scan_clock(scan, seed)
        self.counters = PlcMsgCounters()
        self.log: deque[MsgResult] = deque(maxlen=200)
        #: the data of the last successful reply to each MSG of the script, by label
        self.replies: dict[str, bytes] = {}
        self._cycle = 0
        self._step = 0
        self._next: float | None = 0.0  # when the next MSG starts (None: one is running)
        self._running: tuple[int, str] | None = None

    # --- SimDevice ------------------------------------------------------------------------------

    def receive(self, data: bytes, now: float) -> Sequence[Output]:
        self.core.receive_data(self._faulty_in(data), now)
        return self._after(now)

    def poll(self, now: float) -> Sequence[Output]:
        deadline = self.core.next_deadline()
        if deadline is not None and now >= deadline:
            self.core.handle_timeout(now)
        if self._running is None and self._next is not None and now >= self._next:
            self._start(now)
        return self._after(now)

    def next_deadline(self) -> float | None:
        times = [t for t in (self.core.next_deadline(), self._next if self._running is None else None) if t is not None]
        return min(times, default=None)

    # --- the script -----------------------------------------------------------------------------

    def _start(self, now: float) -> None:
        label, build = self.script[self._step]
        if label == "diagnostic status" and self._cycle % 10:
            self._advance(now)
            return
        handle = self.core.start(build(self._cycle), now, write=False)
        self._running = (handle, label)
        self.counters.sent += 1

    def _advance(self, now: float) -> None:
        self._step += 1
        if self._step == len(self.script):
            self._step = 0
            self._cycle += 1
            due = now + self.cycle_time
        else:
            due = now + self.every
        self._next = self._scan_clock.answer_at(due) if self._scan_clock is not None else due

    def _after(self, now: float) -> list[Output]:
        while (event := self.core.next_event()) is not NEED_DATA:
            running = self._running
            if running is None or event.handle != running[0]:
                continue
            if isinstance(event, TransactionDone):
                self.counters.done += 1
                outcome = "done"
                self.replies[running[1]] = event.reply.data
            elif isinstance(event, TransactionRefused):
                self.counters.refused += 1
                outcome = f"refused STS {event.reply.sts:02X}"
            elif isinstance(event, TransactionFailed | OutcomeUnknown):
                self.counters.failed += 1
                outcome = f"failed: {event.reason}"
            self.log.append(MsgResult(self._cycle, running[1], outcome))
            self._running = None
            self._advance(now)
        out = self.core.data_to_send()
        return [Output(0.0, self._faulty_out(out))] if out else []

    # --- faults ---------------------------------------------------------------------------------

    def _hit(self, fault: str) -> bool:
        n = self.faults[fault]
        if n and self._random.randrange(n) == 0:
            self.counters.faults[fault] += 1
            return True
        return False

    def _faulty_out(self, data: bytes) -> bytes:
        """Damage a frame we send (one byte flipped: the gateway must NAK it), or send it twice."""
        out = bytearray()
        for token, is_frame in _tokens(self._out_decoder, data, self.checksum):
            if is_frame and self._hit("duplicate"):
                token += token
            elif is_frame and self._hit("corrupt"):
                damaged = bytearray(token)
                end = len(token) - 2 - self.checksum.size  # before DLE ETX and the check
                body = [k for k in range(2, end) if damaged[k] not in (_DLE, _DLE ^ 0x40)]
                if body:  # flip a byte that neither is nor becomes a DLE: still a frame, its check fails
                    damaged[self._random.choice(body)] ^= 0x40
                token = bytes(damaged)
            out += token
        return bytes(out)

    def _faulty_in(self, data: bytes) -> bytes:
        """Lose a DLE ACK, damage a reply frame: each symbol and frame of the gateway's bytes on its own."""
        out = bytearray()
        for token, is_frame in _tokens(self._in_decoder, data, self.checksum):
            if token == ACK_SYMBOL and self._hit("lose_ack"):
                continue
            if is_frame and self._hit("nak_reply"):  # the check byte: the frame is damaged, its length is not
                token = token[:-1] + bytes((token[-1] ^ 0x01,))
            out += token
        return bytes(out)


def _tokens(decoder: FrameDecoder, data: bytes, checksum: Checksum) -> list[tuple[bytes, bool]]:
    """The symbols and frames of ``data`` as the one DF1 decoder reads them, each as bytes again
    (whether it is a frame); a frame cut by the chunk comes out with the chunk that completes it.
    Both sides send canonical frames, so re-encoding gives the bytes that came."""
    decoder.feed(data)
    tokens: list[tuple[bytes, bool]] = []
    while (event := decoder.next_event()) is not NEED_DATA:
        if isinstance(event, Frame):
            tokens.append((encode_frame(event.message, checksum), True))
        elif isinstance(event, AckReceived | NakReceived | EnqReceived):
            symbol = ACK_SYMBOL if isinstance(event, AckReceived) else NAK_SYMBOL if isinstance(event, NakReceived) \
                else ENQ_SYMBOL
            tokens.append((symbol, False))
    return tokens


def _int(options: Mapping[str, str], key: str, default: int) -> int:
    text = options.get(key, "")
    try:
        return int(text) if text else default
    except ValueError:
        raise ValueError(f"sim://plc-msg: {key}={text!r} is not a number") from None


def create_plc_msg(options: Mapping[str, str], ladder: bool = True,
                   variants: Mapping[str, str] | None = None) -> PlcMsgSimulator:
    """The simulator of a ``sim://plc-msg?...`` URL (module doc lists the options)."""
    checksum = options.get("checksum", DEFAULT_CHECKSUM.value)
    if checksum not in ("crc", "bcc"):
        raise ValueError(f"sim://plc-msg: checksum={checksum!r}: crc or bcc")
    return PlcMsgSimulator(
        every=float(options.get("every", "0.1") or 0.1),
        cycle=float(options.get("cycle", "1.0") or 1.0),
        station=_int(options, "station", 1),
        source=_int(options, "source", 0),
        checksum=Checksum.CRC if checksum == "crc" else Checksum.BCC,
        corrupt=_int(options, "corrupt", 0),
        lose_ack=_int(options, "lose_ack", 0),
        nak_reply=_int(options, "nak_reply", 0),
        duplicate=_int(options, "duplicate", 0),
        seed=_int(options, "seed", 1),
        scan=parse_scan(options.get(SCAN_OPTION)),
    )
