"""Helper process of the benchmarks: N simulated controllers on N TCP ports (not a benchmark).

    python bench/simfarm.py --model slc150 --count 64 --paced [--turnaround S] [--baudrate B]

Prints ``{"ports": [...]}`` on one line once listening, then answers commands read from stdin,
one JSON line each, and exits at end of input:

``stats``  CPU seconds of this process; the loop's timer lateness since the last ``stats``
           (p50/p99 of a probe timer: the pacing error of the line model); and per connection
           the *gateway reaction* since the last ``stats``: the time from the simulator handing
           the last byte of a reply to TCP until the next request's first bytes arrive
           (DF1: the host's DLE ACK alone does not count), which is the gateway's turnaround
           plus two loopback hops.

The event loop is ``select()``-based by default (``--selector select``): ``epoll`` rounds
timeouts up to whole milliseconds, so every paced burst would arrive ~0.5 ms late; and it
spins the last ``--spin`` seconds (default 0.3 ms) before a timer, since a sleeping wake-up
is another ~0.2 ms late on a virtual machine.  ``stats`` reports the remaining lateness.
Each simulator is a separate controller (``create_simulator``), its ladder frozen (``--ladder``: running,
so timers, counters and N7:0 change every 0.1 s).
``--jitter S`` adds a random 0..S seconds to each turnaround (real controllers answer at the end
of a ladder scan, so their turnaround varies; identical deterministic simulators do not).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import random
import resource
import selectors
import sys
import threading

import gateway.kinds  # noqa: F401  (registers the built-in kinds' sim:// models)
from gateway.sim import create_simulator
from gateway.sim.serve import LineModel, SimDevice
from gateway.transport import SerialSettings

_DF1_ACK = b"\x10\x06"
TRACE = ""


class PacedDeviceProtocol(asyncio.Protocol):
    """A simulator on a TCP connection, paced as ``gateway.sim.serve.serve_tcp`` paces it.

    The same line model (``LineModel``: characters leave one after another at the character
    time, each direction on its own) and the same order of events: host bytes reach the device
    when their last character has crossed the line; each device output leaves after the
    turnaround plus its own delay, then crosses the line.  Written here (not imported) so the
    benchmark can time the gateway's reaction: ``gaps`` holds, per reply, the time from its
    last byte leaving towards the gateway to the first bytes of the next request (a DF1 DLE
    ACK alone does not count).
    """

    registry: list[PacedDeviceProtocol] = []

    def __init__(self, device: SimDevice, settings: SerialSettings | None, turnaround: float,
                 jitter: float = 0.0, seed: int = 0) -> None:
        self.loop = asyncio.get_running_loop()
        self.jitter = jitter
        self.rng = random.Random(seed)
        self.device = device
        char_time = settings.char_time if settings is not None else 0.0
        self.to_device, self.to_host = LineModel(char_time), LineModel(char_time)
        self.turnaround = turnaround
        self.transport: asyncio.Transport | None = None
        self.timer: asyncio.TimerHandle | None = None
        self.last_out: float | None = None
        self.ack_pending = False
        self.gaps: list[float] = []
        self.ack_gaps: list[float] = []
        #: (loop time, event, bytes) of every step, when tracing (``--trace``)
        self.trace: list[tuple[float, str, int]] | None = [] if TRACE and not self.registry else None
        PacedDeviceProtocol.registry.append(self)

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport

    def connection_lost(self, exc: Exception | None) -> None:
        self.transport = None
        if self.timer is not None:
            self.timer.cancel()

    def _at(self, when: float, callback: object, data: bytes) -> None:
        if when <= self.loop.time():
            callback(data)  # type: ignore[operator]
        else:
            self.loop.call_at(when, callback, data)  # type: ignore[arg-type]

    def data_received(self, data: bytes) -> None:
        now = self.loop.time()
        if self.trace is not None:
            self.trace.append((now, "host data in", len(data)))
        if self.last_out is not None:
            if data == _DF1_ACK:
                if self.ack_pending:
                    self.ack_gaps.append(now - self.last_out)
                    self.ack_pending = False
            else:
                self.gaps.append(now - self.last_out)
                self.last_out = None
        self._at(self.to_device.schedule(now, len(data)), self._into_device, data)

    def _into_device(self, data: bytes) -> None:
        if self.transport is None:
            return
        now = self.loop.time()
        if self.trace is not None:
            self.trace.append((now, "device receives", len(data)))
        self._emit(now, self.device.receive(data, now))

    def _emit(self, now: float, outputs: object) -> None:
        turnaround = self.turnaround + (self.rng.uniform(0.0, self.jitter) if self.jitter else 0.0)
        for out in outputs:  # type: ignore[attr-defined]
            arrival = self.to_host.schedule(now + turnaround + out.delay, len(out.data))
            self._at(arrival, self._out, out.data)
        deadline = self.device.next_deadline()
        if self.timer is not None and (deadline is None or self.timer.when() != deadline):
            self.timer.cancel()
            self.timer = None
        if deadline is not None and self.timer is None:
            self.timer = self.loop.call_at(deadline, self._on_timer)

    def _on_timer(self) -> None:
        self.timer = None
        if self.transport is not None:
            now = self.loop.time()
            self._emit(now, self.device.poll(now))

    def _out(self, data: bytes) -> None:
        if self.transport is not None and not self.transport.is_closing():
            self.transport.write(data)
            if self.trace is not None:
                self.trace.append((self.loop.time(), "reply out", len(data)))
            if data != _DF1_ACK:
                self.last_out = self.loop.time()
                self.ack_pending = True


class SpinSelector(selectors.SelectSelector):
    """``select()`` that wakes ``spin`` seconds early and then polls: timers within ~20 us.

    A sleeping wake-up on this kind of (virtual) machine is ~0.2 ms late (timer slack does not
    change it); spinning only the last ``spin`` seconds costs ~1 % CPU per paced link.
    """

    def __init__(self, spin: float) -> None:
        super().__init__()
        self.spin = spin

    def select(self, timeout: float | None = None) -> list[tuple[selectors.SelectorKey, int]]:
        if timeout is not None and timeout > 0 and self.spin > 0:
            timeout = 0 if timeout <= self.spin else timeout - self.spin
        return super().select(timeout)


def _pct(values: list[float], q: float) -> float:
    if not values:
        return float("nan")
    values = sorted(values)
    return values[min(len(values) - 1, int(q / 100 * len(values)))]


async def main(args: argparse.Namespace) -> None:
    loop = asyncio.get_running_loop()
    df1 = args.model == "slc504"
    baud = args.baudrate or (19200 if df1 else 9600)
    settings = SerialSettings(baud, 8, "N", 1) if df1 else SerialSettings(baud, 7, "E", 1)
    paced = settings if args.paced else None
    servers = []
    ports = []
    for index in range(args.count):
        options = {"ladder": "1" if args.ladder else "0"}
        if df1:
            options.update(checksum="crc", station="1")
        device = create_simulator(args.model, options)
        server = await loop.create_server(
            lambda device=device, seed=index: PacedDeviceProtocol(device, paced, args.turnaround,
                                                                        args.jitter, seed),
            "127.0.0.1", 0,
        )
        servers.append(server)
        ports.append(server.sockets[0].getsockname()[1])

    lateness: list[float] = []

    def probe(when: float) -> None:
        lateness.append(loop.time() - when)
        nxt = loop.time() + 0.0037
        loop.call_at(nxt, probe, nxt)

    first = loop.time() + 0.0037
    loop.call_at(first, probe, first)

    commands: asyncio.Queue[str | None] = asyncio.Queue()

    def read_stdin() -> None:
        for line in sys.stdin:
            loop.call_soon_threadsafe(commands.put_nowait, line.strip())
        loop.call_soon_threadsafe(commands.put_nowait, None)

    threading.Thread(target=read_stdin, daemon=True).start()
    print(json.dumps({"ports": ports}), flush=True)
    while True:
        command = await commands.get()
        if command is None:
            break
        if command == "stats":
            usage = resource.getrusage(resource.RUSAGE_SELF)
            gaps = []
            for protocol in PacedDeviceProtocol.registry:
                values, acks = protocol.gaps, protocol.ack_gaps
                protocol.gaps, protocol.ack_gaps = [], []
                gaps.append({"n": len(values), "p50": _pct(values, 50), "p99": _pct(values, 99),
                             "mean": sum(values) / len(values) if values else float("nan"),
                             "ack_p50": _pct(acks, 50), "ack_p99": _pct(acks, 99)})
            answer = {
                "cpu": usage.ru_utime + usage.ru_stime,
                "lateness_p50": _pct(lateness, 50),
                "lateness_p99": _pct(lateness, 99),
                "gaps": gaps,
            }
            lateness.clear()
            print(json.dumps(answer), flush=True)
        else:
            print(json.dumps({"error": f"unknown command {command!r}"}), flush=True)
    for server in servers:
        server.close()
    if TRACE and PacedDeviceProtocol.registry and PacedDeviceProtocol.registry[0].trace:
        with open(TRACE, "w", encoding="ascii") as out:  # noqa: ASYNC230 - at exit, nothing else runs
            for when, what, size in PacedDeviceProtocol.registry[0].trace:
                out.write(f"{when:.6f} {what} {size}\n")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", default="slc150", choices=("slc150", "slc100", "slc504"))
    parser.add_argument("--count", type=int, default=1)
    parser.add_argument("--paced", action="store_true")
    parser.add_argument("--ladder", action="store_true", help="run each simulator's ladder (values change)")
    parser.add_argument("--turnaround", type=float, default=0.0)
    parser.add_argument("--jitter", type=float, default=0.0, help="add a random 0..S to each turnaround")
    parser.add_argument("--baudrate", type=int, default=0)
    parser.add_argument("--selector", choices=("select", "epoll"), default="select")
    parser.add_argument("--spin", type=float, default=0.0003, help="select loop: spin this long before a timer")
    parser.add_argument("--trace", default="", help="write the first connection's events to this file at exit")
    arguments = parser.parse_args()
    TRACE = arguments.trace
    selector = SpinSelector(arguments.spin) if arguments.selector == "select" else selectors.DefaultSelector()
    runner = asyncio.Runner(loop_factory=lambda: asyncio.SelectorEventLoop(selector))
    with runner:
        runner.run(main(arguments))
