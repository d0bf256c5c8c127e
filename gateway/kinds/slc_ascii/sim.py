"""Simulated SLC 150 and SLC 100 controllers speaking the ASCII protocol, with fault injection.

Written from the manual ("SLC Programmable Controller Communications Protocol"):

* message IDs: 00 is always accepted and restarts numbering; otherwise the ID must be the
  next in sequence (01..7F, rolling over to 01) or the answer is ``;I<last valid ID>`` and the
  command is not executed.  After power-up the controller expects 00.
* ``;Z`` repeats the most recent reply to an accepted message (acknowledge, data or refusal)
  with the ID it carried, not a ``;I``; after power-up there is none, and ``;Z`` gets no answer.
  It does not use up an ID.
* reads and data writes only in run or continuous-test mode; upload/download only in program
  mode; mode selection in any mode; a transfer, once begun, must finish before a mode change.
* write word: even address 00-7E, value < 10000, the word overwritten must not be protected.
* write byte: 0xA6-0xB4 (relays 701-820) only, or 0x0101 (the mode byte: mode selection).
* a small ladder keeps some timers, a counter and inputs changing.

Where the manual leaves the controller's behaviour open, ``VARIANTS`` has a switch per reading
(``--variant name=value``; ``docs/develop/controller-variants.md``); the first value is the default:

* ``power_up_id``: ``;I`` after power-up reports 00 (``zero``) or the last ID valid before the
  power cycle (``retained``) ("{id} is the last valid [ID]");
* ``z_after_power_up``: ``;Z`` with no reply kept since power-up gets no answer (``silent``) or
  ``;E`` with the ``;Z``'s ID (``error``);
* ``late_replies``: ``none``, or ``some``: 1 reply in ``late_every`` (50) comes just after the
  0.3 s reply time (``late_delay``, 0.36 s by default), holding back the replies behind it;
* ``z_garbled_again``: the repetition of a garbled reply is clean (``no``) or garbled again once
  (``once``);
* ``transfer_after_power_up``: the upload/download block pointer restarts at block 0
  (``restart``) or is kept (``keep``);
* ``fault_report``: ``;T`` follows the reply to the command (``after_reply``) or comes between
  the command and its reply (``before_reply``);
* ``count_digits``: the ``<number of bytes>`` of a data reply has 2 digits (``2``, the manual's
  printed example ``:021FFE``) or 4 (``4``, as the command's own field);
* ``line_end``: a reply ends with CR (``cr``, "<cr>") or CR LF (``crlf``);
* ``z_repeats``: ``;Z`` repeats the last reply to an accepted message, ``;E`` included
  (``accepted``), only the last ``;R`` or data reply (``executed``, "its most recent acknowledge
  or data message"), or whatever was sent last, ``;I`` included (``any``);
* ``reply_time``: replies come at once (``prompt``); 1 in ``late_every`` comes late but inside the
  manual's 0.3 s (``late_inside``: 0.8-1 x ``reply_time``, "Normally the SLC will respond within
  0.3 seconds"); every reply anywhere within it (``spread``, a controller 100 times slower than
  the prompt one); or mode changes and writes take ``slow_delay`` (``slow_changes``, "The
  exceptions are edit commands and mode changes").

The ``scan`` option (``scan=0.05`` or ``scan=0.02-0.06`` seconds; :mod:`gateway.sim.scan`) gives the
controller a program scan: every reply then comes at the end of the scan in progress when its command
arrived, or later when the ``reply_time`` reading says so (the reading's time and the scan are not
added: both count from the command).  Without it replies come at once.

This class does no I/O: ``receive(data, now)`` returns the replies to send, each with a delay.
``gateway.sim.serve`` runs it in-process, over TCP or on a pty.
"""

from __future__ import annotations

import random
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import ClassVar, Final

from gateway.protocols.slc_ascii import framing
from gateway.protocols.slc_ascii import memory_map as mm
from gateway.protocols.slc_ascii.commands import VALUE_LIMIT, ControllerType, Mode
from gateway.protocols.slc_ascii.framing import (
    NEED_DATA,
    CommandFrame,
    Garbled,
    RetransmitRequest,
)
from gateway.protocols.slc_ascii.memory_map import (
    ERROR_BITS_REGION,
    MAP_SIZE,
    MODE_ADDRESS,
    PROTECT_BIT,
    WORD_VALUE_MASK,
    is_readable,
)
from gateway.sim.scan import ANSWER_BOUND, SCAN_OPTION, ScanTime, parse_scan, scan_clock
from gateway.sim.serve import Output
from gateway.sim.variants import resolve_variants

__all__ = ["FaultPlan", "Output", "SlcAsciiSimulator"]

#: Firmware revision the simulators report (FRN 5 for the SLC 100, the first the protocol supports).
SIMULATED_FRN: Final = {ControllerType.SLC100: 0x05, ControllerType.SLC150: 0x47}



#: (byte, bit) of the simulated program's input 1, output 11 and relay 821 (user bit addresses).
_INPUT_1, _OUTPUT_11, _RELAY_821 = (mm.user_bit_to_byte(user) for user in (1, 11, 821))


@dataclass
class FaultPlan:
    """Fault injection.  ``1 in N`` faults are drawn at random from a seeded generator (0 = off)."""

    garble: int = 0  # corrupt 1 in N replies (bad CRC, truncated or noisy)
    drop: int = 0  # drop 1 in N replies
    delay: float = 0.0  # added to every reply
    power_cycle_every: int = 0  # power-cycle before the N-th command frame (# frames, counted)
    fault_every: int = 0  # emit ;T and set an error bit after every N-th command
    seed: int = 1
    late_delay: float = 0.36  # late_replies=some: a late reply comes this long after its command
    late_every: int = 50  # late_replies=some: 1 reply in N is late
    reply_time: float = ANSWER_BOUND  # reply_time=spread / slow_changes: the longest normal reply time
    slow_delay: float = 0.6  # reply_time=slow_changes: a mode change or write takes this long
    scan: ScanTime | None = None  # the controller's scan: every reply at the end of the scan in progress

    @classmethod
    def from_options(cls, options: dict[str, str]) -> FaultPlan:
        plan = cls()
        for key, text in options.items():
            if key == SCAN_OPTION:
                plan.scan = parse_scan(text)
                continue
            if key not in ("garble", "drop", "delay", "power_cycle_every", "fault_every", "seed", "late_delay",
                           "late_every", "reply_time", "slow_delay"):
                raise ValueError(f"unknown simulator fault option {key!r}")
            try:
                value: float = float(text) if key in _SECONDS else int(text)
            except ValueError as exc:
                raise ValueError(f"simulator option {key}={text!r} is not a number") from exc
            if value < 0:
                raise ValueError(f"simulator option {key} must not be negative")
            setattr(plan, key, value)
        return plan


_SECONDS: Final = ("delay", "late_delay", "reply_time", "slow_delay")


@dataclass
class SimCounters:
    commands: int = 0
    retransmits: int = 0
    id_mismatches: int = 0
    refusals: int = 0
    garbled_in: int = 0
    garbled_out: int = 0
    dropped: int = 0
    power_cycles: int = 0
    faults: int = 0
    late: int = 0


@dataclass
class _Ladder:
    """A tiny program: timers 901-904 time, counter 905 counts input 1, relays follow timers."""

    enabled: bool = True
    last: float | None = None
    tick: float = 0.0


@dataclass
class _Sequencer:
    counter: int  # user address 901-932
    presets: list[int] = field(default_factory=list)


class SlcAsciiSimulator:
    """One SLC 100/150 controller.  Not thread-safe; drive it from one event loop."""

    VARIANTS: ClassVar[dict[str, tuple[str, ...]]] = {
        "power_up_id": ("zero", "retained"),
        "z_after_power_up": ("silent", "error"),
        "late_replies": ("none", "some"),
        "z_garbled_again": ("no", "once"),
        "transfer_after_power_up": ("restart", "keep"),
        "fault_report": ("after_reply", "before_reply"),
        "count_digits": ("2", "4"),
        "line_end": ("cr", "crlf"),
        "z_repeats": ("accepted", "executed", "any"),
        "reply_time": ("prompt", "late_inside", "spread", "slow_changes"),
    }

    def __init__(
        self,
        model: ControllerType = ControllerType.SLC150,
        *,
        faults: FaultPlan | None = None,
        ladder: bool = True,
        variants: Mapping[str, str] | None = None,
    ) -> None:
        self.variants = resolve_variants(model.name.lower(), self.VARIANTS, variants or {})
        self.model = model
        self.faults = faults or FaultPlan()
        self.counters = SimCounters()
        self.memory = bytearray(MAP_SIZE)
        self.program = bytearray(model.block_count * 15)
        #: Every write applied, in order: (kind, address or rung, value).  Tests count these.
        self.applied_writes: list[tuple[str, int, int]] = []
        self._rng = random.Random(self.faults.seed)
        self._scan_clock = scan_clock(self.faults.scan, self.faults.seed)
        self._decoder = framing.CommandDecoder()
        self._ladder = _Ladder(enabled=ladder)
        self._frames_seen = 0
        self._last_garbled = False
        self._line_busy_until = float("-inf")
        self._last_valid_id = 0
        self._transfer: str | None = None
        self._next_block = 0
        self._init_memory()
        self._power_up()

    # --- state ------------------------------------------------------------------------------

    def _init_memory(self) -> None:
        for n, number in enumerate(mm.TIMER_NUMBERS):
            self.set_word(mm.preset_address(number), 100 + 10 * n)
            self.memory[mm.step_counter_address(number)] = n % 5
        self.set_word(mm.preset_address(932), PROTECT_BIT | 500)  # 932: protected preset
        self.set_word(mm.accumulator_address(932), PROTECT_BIT | 7)  # 932: protected accumulator
        self.memory[MODE_ADDRESS] = Mode.RUN
        # A stored program: a recognisable pattern, with the preset table at the end.
        for i in range(len(self.program)):
            self.program[i] = (i * 7 + 3) & 0xFF
        # Rungs holding a sequencer and a reset instruction (for the rung-addressed commands).
        self.sequencers = {0x0010: _Sequencer(910, [100, 200, 300, 400]), 0x0011: _Sequencer(911, [5, 6, 7])}
        self.resets = {0x0020: 920, 0x0021: 921}

    def _power_up(self) -> None:
        self._expected_id: int | None = 0  # expects 00
        if self.variants["power_up_id"] == "zero":
            self._last_valid_id = 0  # else: ;I keeps reporting the ID valid before the power cycle
        self._last_reply: bytes | None = None
        if self.variants["transfer_after_power_up"] == "restart":
            self._transfer = None  # "upload" | "download" while a program transfer runs
            self._next_block = 0
        self._decoder = framing.CommandDecoder()

    def power_cycle(self) -> None:
        """Lose the message ID state and the last reply; memory is kept (NVRAM)."""
        self.counters.power_cycles += 1
        self._power_up()

    @property
    def mode(self) -> int:
        return self.memory[MODE_ADDRESS]

    def word(self, address: int) -> int:
        return (self.memory[address] << 8) | self.memory[address + 1]

    def set_word(self, address: int, value: int) -> None:
        self.memory[address] = (value >> 8) & 0xFF
        self.memory[address + 1] = value & 0xFF

    def set_bit(self, byte_address: int, bit: int, value: bool) -> None:
        if value:
            self.memory[byte_address] |= 1 << bit
        else:
            self.memory[byte_address] &= ~(1 << bit) & 0xFF

    # --- ladder -----------------------------------------------------------------------------

    def advance(self, now: float) -> None:
        """Run the ladder up to ``now`` (seconds): 0.1 s time base."""
        ladder = self._ladder
        if not ladder.enabled or self.mode not in (Mode.RUN, Mode.CONTINUOUS_TEST):
            ladder.last = now
            return
        if ladder.last is None:
            ladder.last = now
            return
        ladder.tick += now - ladder.last
        ladder.last = now
        steps = int(ladder.tick / 0.1)
        if steps <= 0:
            return
        ladder.tick -= steps * 0.1
        for _ in range(min(steps, 100)):
            self._scan()

    def _scan(self) -> None:
        # Timers 901-904: accumulate to the preset, set the done bit, restart.
        done_bits, overflow_bits = mm.TCS_OUTPUT_BITS.start, mm.TCS_OVERFLOW_BITS.start
        for n, number in enumerate(range(901, 905)):
            acc_address = mm.accumulator_address(number)
            preset = self.word(mm.preset_address(number)) & WORD_VALUE_MASK
            acc = self.word(acc_address) + 1
            done = acc >= preset
            self.set_bit(done_bits, n, done)
            self.set_word(acc_address, 0 if done else min(acc, 9999))
        # Input 1 toggles every scan; counter 905 counts its rising edges.
        input_one = not self.memory[_INPUT_1[0]] >> _INPUT_1[1] & 1
        self.set_bit(*_INPUT_1, input_one)
        if input_one:
            acc = self.word(mm.accumulator_address(905)) + 1
            overflow = acc > 9999
            self.set_bit(overflow_bits, 4, overflow)
            self.set_word(mm.accumulator_address(905), 0 if overflow else acc)
            self.set_bit(done_bits, 4, acc >= (self.word(mm.preset_address(905)) & WORD_VALUE_MASK))
        # Output 11 follows timer 901's done bit; relay 821 (read-only range) follows input 1.
        self.set_bit(*_OUTPUT_11, bool(self.memory[done_bits] & 1))
        self.set_bit(*_RELAY_821, input_one)

    # --- the line ---------------------------------------------------------------------------

    def receive(self, data: bytes, now: float) -> list[Output]:
        """Bytes from the host -> replies to send."""
        self.advance(now)
        self._decoder.receive_data(data)
        out: list[Output] = []
        while True:
            event = self._decoder.next_event()
            if event is NEED_DATA:
                break
            if isinstance(event, Garbled):
                self.counters.garbled_in += 1  # "The SLC does not respond to ... CRC, or incorrect format"
                continue
            if isinstance(event, RetransmitRequest):
                self.counters.retransmits += 1
                if self._last_reply is not None:
                    again = self._last_garbled and self.variants["z_garbled_again"] == "once"
                    self._last_garbled = False  # garbled again once, not for ever
                    self._emit(out, now, self._last_reply, garble=again)
                elif self.variants["z_after_power_up"] == "error":
                    self._emit(out, now, framing.encode_refused(event.msg_id))
                continue
            assert isinstance(event, CommandFrame)
            self._frames_seen += 1
            plan = self.faults
            if plan.power_cycle_every and self._frames_seen % plan.power_cycle_every == 0:
                self.power_cycle()
            executed_before = self.counters.commands
            reply = self._handle(event)
            executed = self.counters.commands != executed_before  # not for a frame answered ;I
            fault = bool(plan.fault_every and executed and self.counters.commands % plan.fault_every == 0)
            if fault and self.variants["fault_report"] == "before_reply":
                self.raise_fault()
                out.append(Output(plan.delay, framing.encode_fault(0)))
            remembered = self._remembers(reply, executed)
            if remembered:
                self._last_reply = reply
                self._last_garbled = False
            garbled = self._emit(out, now, reply, slow=executed and self._is_change(event))
            if remembered:
                self._last_garbled = garbled
            if fault and self.variants["fault_report"] == "after_reply":
                self.raise_fault()
                out.append(Output(plan.delay, framing.encode_fault(0)))
        return self._in_order(out, now)

    def _remembers(self, reply: bytes, executed: bool) -> bool:
        """Whether ``;Z`` will repeat ``reply`` (the ``z_repeats`` reading)."""
        reading = self.variants["z_repeats"]
        if reading == "any":
            return True
        if reading == "executed":
            return executed and not reply.startswith(b";E")
        return executed  # accepted: ;R, data or ;E, never ;I

    @staticmethod
    def _is_change(frame: CommandFrame) -> bool:
        """A mode change or a write (an "edit"): the commands the manual lets take longer."""
        return frame.code in (0x01, 0x03, 0x06, 0x07)

    def _in_order(self, out: list[Output], now: float) -> list[Output]:
        """The line keeps the order: a late reply holds back the replies after it."""
        ordered = []
        for item in out:
            delay = max(item.delay, self._line_busy_until - now)
            self._line_busy_until = now + delay
            ordered.append(item if delay == item.delay else Output(delay, item.data))
        return ordered

    def poll(self, now: float) -> list[Output]:
        """No timers: the SLC 100/150 only ever answers."""
        return []

    def next_deadline(self) -> float | None:
        return None

    def raise_fault(self, byte: int = ERROR_BITS_REGION.start, bit: int = 3) -> None:
        """Set an error bit (default 84H bit 3: error 8) as a ``;T`` will report."""
        self.counters.faults += 1
        self.set_bit(byte, bit, True)

    def fault_frame(self) -> bytes:
        return framing.encode_fault(0)

    def _emit(self, out: list[Output], now: float, reply: bytes, *, garble: bool = False, slow: bool = False) -> bool:
        """Put ``reply`` on the line through the faults, at the end of the scan in progress when the
        controller has a scan; True when it went out garbled."""
        plan = self.faults
        if plan.drop and self._rng.randrange(plan.drop) == 0:
            self.counters.dropped += 1
            return False
        garbled = garble or bool(plan.garble and self._rng.randrange(plan.garble) == 0)
        if garbled:
            self.counters.garbled_out += 1
            reply = self._garble(reply)
        delay = plan.delay + max(self._turnaround(slow), self._scan_delay(now))
        if self.variants["late_replies"] == "some" and self._rng.randrange(max(1, plan.late_every)) == 0:
            self.counters.late += 1
            delay = max(delay, plan.late_delay)
        if self.variants["line_end"] == "crlf":
            reply += b"\n"
        out.append(Output(delay, reply))
        return garbled

    def _scan_delay(self, now: float) -> float:
        """Seconds to the end of the scan in progress (``scan`` option), 0 without a scan."""
        return self._scan_clock.delay(now) if self._scan_clock is not None else 0.0

    def _turnaround(self, slow: bool) -> float:
        """The controller's time to answer, as the ``reply_time`` reading has it."""
        reading = self.variants["reply_time"]
        if reading == "prompt":
            return 0.0
        if reading == "slow_changes":
            return self.faults.slow_delay if slow else 0.0
        if reading == "late_inside":
            if self._rng.randrange(max(1, self.faults.late_every)) != 0:
                return 0.0
            return self._rng.uniform(0.8, 1.0) * self.faults.reply_time
        return self._rng.uniform(0.0, self.faults.reply_time)

    def _garble(self, reply: bytes) -> bytes:
        kind = self._rng.randrange(3)
        body = bytearray(reply)
        if kind == 0:  # flip a bit in a character after the leading one (CRC catches it)
            i = self._rng.randrange(1, len(body) - 1)
            body[i] ^= 1 << self._rng.randrange(4)
            if body[i] == 0x0D:
                body[i] = 0x3F
            return bytes(body)
        if kind == 1:  # truncated: the CR is lost, the next leading character ends it
            return bytes(body[: self._rng.randrange(1, len(body) - 1)])
        return b"\x07" + bytes(body[:-3]) + b"~" + bytes(body[-3:])  # noise: line noise in the frame

    # --- commands ---------------------------------------------------------------------------

    def _handle(self, frame: CommandFrame) -> bytes:
        msg_id = frame.msg_id
        if msg_id != 0 and msg_id != self._expected_id:
            self.counters.id_mismatches += 1
            return framing.encode_id_mismatch(self._last_valid_id)
        self._last_valid_id = msg_id
        self._expected_id = 1 if msg_id >= framing.MAX_ID else msg_id + 1
        self.counters.commands += 1
        try:
            body = self._execute(frame)
        except _AnswerE:
            self.counters.refusals += 1
            return framing.encode_refused(msg_id)
        if body is None:
            return framing.encode_ack(msg_id)
        return framing.encode_data_reply(body, msg_id)

    def _require(self, condition: bool) -> None:
        if not condition:
            raise _AnswerE

    def _require_run(self) -> None:
        self._require(self.mode in (Mode.RUN, Mode.CONTINUOUS_TEST) and self._transfer is None)

    def _execute(self, frame: CommandFrame) -> str | None:
        code, params = frame.code, frame.params
        if code == 0x08 and not params:  # read FRN ID tag, any mode
            return f"{self._count(2)}1FFE{self.model.device_type:02X}{SIMULATED_FRN[self.model]:02X}"
        if code == 0x02 and len(params) == 4:
            return self._read(int.from_bytes(params[0:2], "big"), int.from_bytes(params[2:4], "big"))
        if code == 0x03 and len(params) == 3:
            return self._write_byte(int.from_bytes(params[0:2], "big"), params[2])
        if code == 0x03 and len(params) == 4:
            return self._write_word(int.from_bytes(params[0:2], "big"), int.from_bytes(params[2:4], "big"))
        if code == 0x00 and not params:
            return self._upload()
        if code == 0x01 and len(params) == 16:
            return self._download(params[0], params[1:])
        if code == 0x04 and len(params) == 3:
            return self._read_sequencer(int.from_bytes(params[0:2], "big"), params[2])
        if code == 0x06 and len(params) == 5:
            rung, step, value = int.from_bytes(params[0:2], "big"), params[2], int.from_bytes(params[3:5], "big")
            return self._write_sequencer(rung, step, value)
        if code == 0x05 and len(params) == 2:
            return self._read_reset(int.from_bytes(params[0:2], "big"))
        if code == 0x07 and len(params) == 4:
            return self._write_reset(int.from_bytes(params[0:2], "big"), int.from_bytes(params[2:4], "big"))
        raise _AnswerE

    def _read(self, count: int, address: int) -> str:
        self._require_run()
        self._require(count in (1, 2))
        self._require(is_readable(address, count))
        data = self.memory[address : address + count]
        return f"{self._count(count)}{address:04X}{data.hex().upper()}"

    def _write_byte(self, address: int, value: int) -> str | None:
        if address == MODE_ADDRESS:
            self._require(value in tuple(Mode))
            self._require(self._transfer is None or value == Mode.PROGRAM)
            self._transfer = None  # re-entering program mode resets a transfer
            self._next_block = 0
            self.memory[MODE_ADDRESS] = value
            self.applied_writes.append(("mode", address, value))
            return None
        self._require_run()
        self._require(mm.is_byte_writable(address))
        self.memory[address] = value
        self.applied_writes.append(("byte", address, value))
        return None

    def _write_word(self, address: int, value: int) -> str | None:
        self._require_run()
        self._require(mm.is_word_writable(address))
        self._require(value < VALUE_LIMIT)
        self._require(not self.memory[address] & 0x80)  # protected
        self.set_word(address, value)
        self.applied_writes.append(("word", address, value))
        return None

    def _upload(self) -> str:
        self._require(self.mode == Mode.PROGRAM and self._transfer in (None, "upload"))
        self._transfer = "upload"
        block = self._next_block
        data = self.program[block * 15 : block * 15 + 15]
        if block == self.model.block_count - 1:
            data = data[:7] + bytes(8)  # last 7 bytes of the preset table plus 8 bytes of fill
        self._next_block += 1
        if self._next_block >= self.model.block_count:
            self._transfer, self._next_block = None, 0
        return f"{block:02X}{data.hex().upper()}"

    def _download(self, block: int, data: bytes) -> str | None:
        self._require(self.mode == Mode.PROGRAM and self._transfer in (None, "download"))
        self._require(block == self._next_block)
        if self._transfer is None:
            self.program[:] = bytes(len(self.program))  # a download clears NVRAM
        self._transfer = "download"
        self.program[block * 15 : block * 15 + 15] = data
        self._next_block += 1
        if self._next_block >= self.model.block_count:
            self._transfer, self._next_block = None, 0
            self.applied_writes.append(("program", 0, len(self.program)))
        return None

    def _count(self, count: int) -> str:
        """The ``<number of bytes>`` field of a data reply (the ``count_digits`` reading)."""
        return f"{count:0{int(self.variants['count_digits'])}X}"

    @staticmethod
    def _user(counter: int) -> str:
        return f"{counter:04X}"  # "All numbers are in hexadecimal coded binary format"

    def _read_sequencer(self, rung: int, step: int) -> str:
        self._require_run()
        seq = self.sequencers.get(rung)
        self._require(seq is not None and step < len(seq.presets))
        assert seq is not None
        return f"{self._count(2)}{self._user(seq.counter)}{seq.presets[step]:04X}"

    def _write_sequencer(self, rung: int, step: int, value: int) -> str | None:
        self._require_run()
        seq = self.sequencers.get(rung)
        self._require(seq is not None and step < len(seq.presets))
        assert seq is not None
        self._require(0 < value < 10000 and not seq.presets[step] & 0x8000)
        seq.presets[step] = value
        self.applied_writes.append(("sequencer", rung * 256 + step, value))
        return None

    def _read_reset(self, rung: int) -> str:
        self._require_run()
        counter = self.resets.get(rung)
        self._require(counter is not None)
        assert counter is not None
        return f"{self._count(2)}{self._user(counter)}{self.word(2 * (counter - 901)):04X}"

    def _write_reset(self, rung: int, value: int) -> str | None:
        self._require_run()
        counter = self.resets.get(rung)
        self._require(counter is not None and value < 10000)
        assert counter is not None
        address = 2 * (counter - 901)
        self._require(not self.memory[address] & 0x80)
        self.set_word(address, value)
        self.applied_writes.append(("reset", rung, value))
        return None


class _AnswerE(Exception):
    """Internal: answer ;E."""
