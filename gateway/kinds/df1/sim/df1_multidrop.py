"""A simulated DF1 half-duplex multi-drop line: several SLC 5/0x (or PLC-5) stations on one byte stream.

Each station is a :class:`~gateway.kinds.df1.sim.df1_half_duplex_slave.HalfDuplexSlave` (the slave actions of
1775-KA p. 11-11/11-12, with the variant switches of that model) in front of a controller model
whose command execution is the SLC 5/04 simulator's (``gateway.kinds.df1.sim.slc500``; the PLC-5 model with
``model="plc5"``).  The line itself is the medium they share, with its timing and its faults:

* **timing** - ``char_time`` seconds per character on the medium (11 bits / baud; 0 = instantaneous);
  the master's bytes occupy the medium from the moment they are written (one after another), a
  slave starts answering ``turnaround`` seconds (plus its ``slow`` extra) after the master's last byte
  reached it, and the master gets the answer when its last byte has come off the medium;
* **radio latency** - ``latency`` seconds each way between the master and the stations;
* **collisions** - master bytes on the medium while a slave is transmitting (a master that does not
  wait for the answer, or polls again too early) garble both: the slave's frame reaches the master
  damaged, and the master's bytes reach the stations damaged (they see bad frames and stay silent);
* ``corrupt=N`` - 1 in N slave message frames is damaged (one message byte changed, the check fails);
  symbols (DLE EOT / DLE ACK) are not;
* ``ignore=N`` - 1 in N master frames or symbols (polls, messages, DLE ACKs) is heard by no station;
* ``lose_symbol=N`` - 1 in N slave symbols (DLE ACK, DLE EOT, DLE NAK) never reaches the master: a
  lost ACK of a master message is what makes a resend reach a slave that already executed it;
* ``dead`` - stations that are on the configuration but never answer (powered off, cable cut);
* ``slow`` - extra turnaround per station (a slow modem or CPU); ``busy_polls`` - per station, the
  number of polls after each command before its reply is ready (the slave answers them DLE EOT or
  not at all, per its ``when_busy`` variant);
* ``echo`` - 2-wire RS-485: the master hears its own bytes back (as they came off the medium);
* ``scan`` - every station's program scan (``scan=0.05`` or ``scan=0.02-0.06`` seconds,
  :mod:`gateway.sim.scan`; each station its own clock): a station ACKs a message at once, and its
  reply is ready at the end of the scan in progress; polls before then are answered as a busy
  station's (DLE EOT, or nothing, per ``when_busy``).

The line paces itself (``char_time``) because it must judge collisions: serve it unpaced
(``SimStream(line)``, ``serve_tcp(line, ...)`` without ``settings``).  It is a
:class:`~gateway.sim.serve.SimDevice`: ``receive(data, now)`` / ``poll(now)`` / ``next_deadline()``
return what reaches the master, as outputs with no delay (the line keeps its own timers).

Variants: the slave model's ``VARIANTS`` (``bad_frame_reply``, ``reply_retries``,
``duplicate_detect``, ``when_busy``), for every station.  Options as strings (``from_options``):
``checksum=bcc|crc stations=1,2,3 dead=4 slow=3:0.2 busy_polls=2:1 turnaround=S latency=S
char_time=S corrupt=N ignore=N lose_symbol=N echo=0|1 seed=N model=slc504|plc5 scan=S|MIN-MAX``.

No I/O; randomness from one seeded generator.
"""

from __future__ import annotations

import heapq
import itertools
import math
import random
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import ClassVar, Final, TypeVar

from gateway.frozen import frozen
from gateway.kinds.df1.sim.df1_half_duplex_slave import VARIANTS as SLAVE_VARIANTS
from gateway.kinds.df1.sim.df1_half_duplex_slave import HalfDuplexSlave, SlaveVariant
from gateway.kinds.df1.sim.plc5 import Plc5Simulator
from gateway.kinds.df1.sim.slc500 import Output, Slc500Options, Slc500Simulator
from gateway.kinds.df1.sim.slc500_line import corrupt_frame
from gateway.protocols.df1.framing import DEFAULT_CHECKSUM, Checksum, Symbol
from gateway.sim.models import read_sim_option
from gateway.sim.scan import SCAN_OPTION, ScanTime, parse_scan, scan_clock

__all__ = ["LineOptions", "MultidropCounters", "MultidropLine", "SlcStation"]

_MULTIDROP_OPTION_NAMES: Final = (
    "checksum", "stations", "dead", "slow", "busy_polls", "turnaround", "latency", "char_time", "corrupt",
    "ignore", "lose_symbol", "echo", "seed", "model", SCAN_OPTION,
)
_MODELS: Final = ("slc504", "plc5")

T = TypeVar("T")


class SlcStation(Slc500Simulator):
    """The SLC 5/04 model as a station: the line calls its ``execute`` (data table and commands);
    its full-duplex link is not used."""


@frozen
class LineOptions:
    """The line's stations, timing and faults (module docstring); ``1 in N`` faults are off at 0."""

    checksum: Checksum = DEFAULT_CHECKSUM
    stations: tuple[int, ...] = (1, 2, 3)
    dead: frozenset[int] = frozenset()
    slow: Mapping[int, float] = field(default_factory=dict)
    busy_polls: Mapping[int, int] = field(default_factory=dict)
    turnaround: float = 0.0
    latency: float = 0.0
    char_time: float = 0.0
    corrupt: int = 0
    ignore: int = 0
    lose_symbol: int = 0
    echo: bool = False
    seed: int = 1
    model: str = "slc504"
    scan: ScanTime | None = None

    def __post_init__(self) -> None:
        if not self.stations:
            raise ValueError("multi-drop line: give at least one station (stations=1,2,3)")
        if len(set(self.stations)) != len(self.stations):
            raise ValueError(f"multi-drop line: station numbers must be unique, got {list(self.stations)}")
        for number in self.stations:
            if not 0 <= number <= 254:
                raise ValueError(f"multi-drop line: station {number} is not a DF1 node address 0-254")
        for name, mapping in (("dead", self.dead), ("slow", self.slow), ("busy_polls", self.busy_polls)):
            unknown = sorted(set(mapping) - set(self.stations))
            if unknown:
                raise ValueError(f"multi-drop line: {name} names stations {unknown} that are not on the line")
        for name in ("turnaround", "latency", "char_time"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"multi-drop line option {name}={value}: seconds, 0 or more")
        if any(not (math.isfinite(v) and v >= 0) for v in self.slow.values()):
            raise ValueError("multi-drop line option slow: seconds, 0 or more")
        if any(v < 0 for v in self.busy_polls.values()) or min(self.corrupt, self.ignore, self.lose_symbol) < 0:
            raise ValueError("multi-drop line: busy_polls, corrupt, ignore and lose_symbol must not be negative")
        if self.model not in _MODELS:
            raise ValueError(f"multi-drop line option model={self.model!r}: choose {' or '.join(_MODELS)}")

    @classmethod
    def from_options(cls, options: Mapping[str, str]) -> LineOptions:
        """Parse string options; ValueError names the bad one."""
        unknown = sorted(set(options) - set(_MULTIDROP_OPTION_NAMES))
        if unknown:
            raise ValueError(f"unknown multi-drop line option(s) {', '.join(unknown)} "
                             f"(known: {', '.join(sorted(_MULTIDROP_OPTION_NAMES))})")

        def get(name: str, parse: Callable[[str], T], default: T) -> T:
            return read_sim_option(options, name, parse, default, what="multi-drop line option")

        def numbers(text: str) -> tuple[int, ...]:
            return tuple(int(part) for part in text.split(",") if part.strip())

        def pairs(text: str) -> dict[int, str]:
            out: dict[int, str] = {}
            for part in text.split(","):
                if part.strip():
                    station, sep, value = part.partition(":")
                    if not sep:
                        raise ValueError(part)
                    out[int(station)] = value
            return out

        checksum_text = options.get("checksum", DEFAULT_CHECKSUM.value).strip().lower()
        if checksum_text not in ("bcc", "crc"):
            raise ValueError(f"multi-drop line option checksum={checksum_text!r}: choose bcc or crc")
        no_pairs: dict[int, str] = {}
        no_stations: tuple[int, ...] = ()
        slow = get("slow", pairs, no_pairs)
        busy = get("busy_polls", pairs, no_pairs)
        try:
            slow_seconds = {k: float(v) for k, v in slow.items()}
            busy_counts = {k: int(v) for k, v in busy.items()}
        except ValueError:
            raise ValueError("multi-drop line options slow / busy_polls: station:value pairs") from None
        return cls(
            checksum=Checksum(checksum_text),
            stations=get("stations", numbers, (1, 2, 3)),
            dead=frozenset(get("dead", numbers, no_stations)),
            slow=slow_seconds,
            busy_polls=busy_counts,
            turnaround=get("turnaround", float, 0.0),
            latency=get("latency", float, 0.0),
            char_time=get("char_time", float, 0.0),
            corrupt=get("corrupt", int, 0),
            ignore=get("ignore", int, 0),
            lose_symbol=get("lose_symbol", int, 0),
            echo=get("echo", lambda text: text.lower() in ("1", "true", "yes"), False),
            seed=get("seed", int, 1),
            model=get("model", str.lower, "slc504"),
            scan=parse_scan(options.get(SCAN_OPTION)),
        )


@dataclass(slots=True)
class MultidropCounters:
    master_bytes: int = 0
    slave_bytes: int = 0
    collisions: int = 0  #: master transmissions that overlapped a slave's
    ignored: int = 0  #: master frames / symbols no station heard (``ignore``)
    corrupted: int = 0  #: slave frames damaged (``corrupt``)
    lost_symbols: int = 0  #: slave DLE ACK / EOT / NAK lost on the way (``lose_symbol``)
    busy_time: float = 0.0  #: seconds the medium carried a signal (line efficiency = busy / elapsed)


@dataclass(slots=True)
class _Transmission:
    """A slave's answer on the medium, and its delivery to the master."""

    start: float
    end: float
    data: bytes
    garbled: bool = False


class MultidropLine:
    """Several half-duplex slave stations on one medium (module docstring).  A ``SimDevice``."""

    VARIANTS: ClassVar[Mapping[str, tuple[str, ...]]] = SLAVE_VARIANTS
    #: paces its own bytes (``char_time``): serve it without line settings (``gateway.sim.serve``)
    self_paced: ClassVar[bool] = True

    def __init__(
        self,
        options: LineOptions | None = None,
        *,
        variants: Mapping[str, str] | None = None,
        ladder: bool = False,
        controller_variants: Mapping[str, str] | None = None,
    ) -> None:
        """``variants``: the slave model's, for every station; ``controller_variants``: the controller
        model's (e.g. ``{"typed_logical": "accept"}`` for ``model="plc5"``)."""
        self.options = options or LineOptions()
        self.variant = SlaveVariant.from_choices(variants or {})
        self.counters = MultidropCounters()
        self._rng = random.Random(self.options.seed)
        checksum = self.options.checksum
        #: every configured station's controller (a dead one keeps its table, it just never answers)
        self.controllers: dict[int, SlcStation | Plc5Simulator] = {}
        self.slaves: dict[int, HalfDuplexSlave] = {}
        for number in self.options.stations:
            station_options = Slc500Options(checksum=checksum, station=number)
            controller: SlcStation | Plc5Simulator = (
                Plc5Simulator(station_options, ladder=ladder, variants=controller_variants)
                if self.options.model == "plc5"
                else SlcStation(station_options, ladder=ladder, variants=controller_variants)
            )
            self.controllers[number] = controller
            if number not in self.options.dead:
                clock = scan_clock(self.options.scan, self.options.seed, salt=str(number))
                self.slaves[number] = HalfDuplexSlave(number, checksum, self._handler(number, controller), self.variant,
                                                      answer_at=clock.answer_at if clock is not None else None)
        self._seq = itertools.count()
        self._to_slaves: list[tuple[float, int, bytes, bool]] = []  # (time, seq, bytes, garbled)
        self._to_master: list[tuple[float, int, _Transmission]] = []
        self._air: list[_Transmission] = []  # slave transmissions not yet delivered
        self._master_free = 0.0  #: when the master's previous bytes have left
        self._medium_free = 0.0  #: when the slaves' side of the medium is free
        self._rx = bytearray()  #: master bytes heard but not yet a whole frame or symbol
        self._now = 0.0

    @classmethod
    def from_options(
        cls,
        options: Mapping[str, str],
        *,
        variants: Mapping[str, str] | None = None,
        ladder: bool = False,
        controller_variants: Mapping[str, str] | None = None,
    ) -> MultidropLine:
        return cls(
            LineOptions.from_options(options), variants=variants, ladder=ladder, controller_variants=controller_variants
        )

    def _handler(self, number: int, controller: SlcStation | Plc5Simulator) -> Callable[[bytes], bytes | None]:
        busy = self.options.busy_polls.get(number, 0)

        def handle(packet: bytes) -> bytes | None:
            controller.advance(self._now)
            reply = controller.execute(packet)
            if busy and reply is not None:
                self.slaves[number].busy = busy  # the reply is ready only after this many polls
            return reply

        return handle

    # --- SimDevice --------------------------------------------------------------------------

    def receive(self, data: bytes, now: float) -> list[Output]:
        """Bytes the master wrote at ``now``."""
        out = self._run(now)
        if not data:
            return out
        options = self.options
        start = max(now, self._master_free)
        end = start + len(data) * options.char_time
        self._master_free = end
        self.counters.master_bytes += len(data)
        self.counters.busy_time += end - start
        # on the slaves' side of the medium (radio: latency later)
        lo, hi = start + options.latency, end + options.latency
        collided = False
        for tx in self._air:
            if (lo < tx.end and tx.start < hi) or (lo == hi and tx.start < lo < tx.end):
                tx.garbled = True
                collided = True
        if collided:
            self.counters.collisions += 1
            data = self._garble(data)
        heapq.heappush(self._to_slaves, (hi, next(self._seq), data, collided))
        if options.echo:  # 2-wire: the master's receiver hears its own bytes as they leave
            heapq.heappush(self._to_master, (end, next(self._seq), _Transmission(start, end, data)))
        return out + self._run(now)

    def poll(self, now: float) -> list[Output]:
        return self._run(now)

    def next_deadline(self) -> float | None:
        times = [queue[0][0] for queue in (self._to_slaves, self._to_master) if queue]
        return min(times) if times else None

    # --- the medium -------------------------------------------------------------------------

    def _run(self, now: float) -> list[Output]:
        out: list[Output] = []
        while True:
            due_slaves = self._to_slaves[0][0] if self._to_slaves else math.inf
            due_master = self._to_master[0][0] if self._to_master else math.inf
            if min(due_slaves, due_master) > now:
                break
            if due_slaves <= due_master:
                at, _, data, garbled = heapq.heappop(self._to_slaves)
                self._now = max(self._now, at)
                self._hear(at, data, garbled)
            else:
                _, _, tx = heapq.heappop(self._to_master)
                self._air = [other for other in self._air if other is not tx]
                out.append(Output(0.0, self._garble(tx.data) if tx.garbled else tx.data))
        return out

    def _hear(self, at: float, data: bytes, garbled: bool) -> None:
        """Master bytes reach every station at ``at``."""
        if garbled:
            self._rx.clear()  # a collision: whatever was half-heard is lost with it
            tokens = [data]
        else:
            self._rx += data
            tokens = self._tokens()
        for token in tokens:
            if not garbled and self._one_in(self.options.ignore):
                self.counters.ignored += 1
                continue
            for number, slave in self.slaves.items():
                slave.receive_data(token, at)
                answer = slave.data_to_send()
                if answer:
                    self._transmit(number, at, answer)

    def _transmit(self, number: int, heard_at: float, answer: bytes) -> None:
        options = self.options
        if len(answer) > 2 and answer[1] == Symbol.STX and self._one_in(options.corrupt):
            self.counters.corrupted += 1
            answer = corrupt_frame(answer, options.checksum, self._rng)
        elif len(answer) == 2 and self._one_in(options.lose_symbol):
            self.counters.lost_symbols += 1  # the slave sent it (and acts on it), the master never hears it
            return
        start = max(heard_at + options.turnaround + options.slow.get(number, 0.0), self._medium_free)
        end = start + len(answer) * options.char_time
        self._medium_free = end
        self.counters.slave_bytes += len(answer)
        self.counters.busy_time += end - start
        tx = _Transmission(start, end, answer)
        for other in self._air:  # two slaves at once (a misconfigured line): both garbled
            if start < other.end and other.start < end:
                other.garbled = tx.garbled = True
        self._air.append(tx)
        heapq.heappush(self._to_master, (end + options.latency, next(self._seq), tx))

    def _tokens(self) -> list[bytes]:
        """Whole master frames and symbols off the front of ``_rx`` (a partial one stays)."""
        rx, check = self._rx, self.options.checksum.size
        tokens: list[bytes] = []
        i = 0
        while i < len(rx):
            if rx[i] != Symbol.DLE:
                j = rx.find(Symbol.DLE, i)
                j = len(rx) if j < 0 else j
                tokens.append(bytes(rx[i:j]))
                i = j
                continue
            if i + 1 >= len(rx):
                break
            kind = rx[i + 1]
            end: int | None
            if kind == Symbol.ENQ:  # DLE ENQ STN BCC, STN 10 doubled
                stn_len = 2 if i + 2 < len(rx) and rx[i + 2] == Symbol.DLE else 1
                end = i + 2 + stn_len + 1
                end = end if end <= len(rx) else None
            elif kind == Symbol.SOH:
                end = None
                j = i + 2
                while j + 1 < len(rx):
                    if rx[j] != Symbol.DLE:
                        j += 1
                    elif rx[j + 1] in (Symbol.DLE, Symbol.STX):
                        j += 2
                    elif rx[j + 1] == Symbol.ETX:
                        end = j + 2 + check if j + 2 + check <= len(rx) else None
                        break
                    else:  # another symbol starts: the frame was cut short
                        end = j
                        break
            else:
                end = i + 2
            if end is None:
                break
            tokens.append(bytes(rx[i:end]))
            i = end
        del rx[:i]
        return tokens

    def _garble(self, data: bytes) -> bytes:
        """What two transmitters at once leave on the medium: every byte changed."""
        return bytes(b ^ (1 + self._rng.randrange(255)) for b in data)

    def _one_in(self, n: int) -> bool:
        return n > 0 and self._rng.randrange(n) == 0
