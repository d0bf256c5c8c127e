"""A fake line and clock for the SLC 100/150 transaction core: no real timers.

The controller is the simulator (sans-I/O as well); a *fault script* decides the fate of each
reply the controller sends (delivered, dropped, garbled, truncated, late) and when the
controller power-cycles.  The line keeps the order: a late reply holds back those after it.
"""

from __future__ import annotations

import heapq
import itertools
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

from gateway.kinds.slc_ascii.sim import SlcAsciiSimulator
from gateway.protocols.slc_ascii.commands import Command
from gateway.protocols.slc_ascii.transaction import Result, SlcSession

#: what happens to one reply
FATES = ("ok", "drop", "garble", "truncate", "late")


@dataclass
class FakeLine:
    sim: SlcAsciiSimulator
    session: SlcSession
    fates: Iterator[str]
    power_cycles: Iterator[bool]
    #: per frame we send: lost on the way (the controller "does not respond to any message which
    #: is received with a parity, CRC, or incorrect format error")
    lost_commands: Iterator[bool] = field(default_factory=lambda: iter(()))
    now: float = 0.0
    transit: float = 0.001
    late: float = 0.0  # a late reply arrives this long after its command (default: 1.2 x timeout)
    steps: int = 0
    _queue: list[tuple[float, int, bytes]] = field(default_factory=list)
    _seq: Iterator[int] = field(default_factory=itertools.count)
    _line_free: float = 0.0
    sent: list[bytes] = field(default_factory=list)

    def _to_controller(self, data: bytes) -> None:
        for frame in data.split(b"\r"):
            if not frame:
                continue
            frame += b"\r"
            self.sent.append(frame)
            if frame.startswith(b"#") and next(self.power_cycles, False):
                self.sim.power_cycle()
            if next(self.lost_commands, False):
                continue
            for out in self.sim.receive(frame, self.now):
                fate = next(self.fates, "ok")
                reply = out.data
                arrival = self.now + self.transit + out.delay
                if fate == "drop":
                    continue
                if fate == "garble":
                    middle = len(reply) // 2
                    reply = reply[:middle] + bytes([reply[middle] ^ 0x01]) + reply[middle + 1 :]
                elif fate == "truncate":
                    reply = reply[: max(1, len(reply) - 3)]
                elif fate == "late":
                    arrival = self.now + (self.late or 1.2 * self.session.timeout)
                arrival = max(arrival, self._line_free)
                self._line_free = arrival
                heapq.heappush(self._queue, (arrival, next(self._seq), reply))

    def run(self, command: Command, timeout: float | None = None) -> Result:
        session = self.session
        session.start(command, self.now, timeout)
        while session.result is None:
            self.steps += 1
            if self.steps > 100_000:
                raise AssertionError("the core does not finish")
            data = session.data_to_send()
            if data:
                self._to_controller(data)
                continue
            deadline = session.next_deadline()
            assert deadline is not None, "a running transaction always has a deadline"
            if self._queue and self._queue[0][0] <= deadline:
                self.now = max(self.now, self._queue[0][0])
                _, _, reply = heapq.heappop(self._queue)
                session.receive_data(reply, self.now)
            else:
                self.now = max(self.now, deadline)
                session.handle_timeout(self.now)
        data = session.data_to_send()
        if data:
            self._to_controller(data)
        return session.take_result()

    def drain(self) -> None:
        """Deliver whatever is still on the line (late replies) to the idle core."""
        while self._queue:
            arrival, _, reply = heapq.heappop(self._queue)
            self.now = max(self.now, arrival)
            self.session.receive_data(reply, self.now)

    def idle(self, seconds: float) -> None:
        """Time passes with no transaction; replies still on the line arrive."""
        end = self.now + seconds
        while self._queue and self._queue[0][0] <= end:
            arrival, _, reply = heapq.heappop(self._queue)
            self.now = max(self.now, arrival)
            self.session.receive_data(reply, self.now)
        self.now = end


def script(items: Sequence[str]) -> Iterator[str]:
    return iter(items)
