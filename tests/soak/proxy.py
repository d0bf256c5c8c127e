"""A fault-injecting TCP proxy: a bad serial line (or a bad serial device server) in a box.

::

    gateway --socket://127.0.0.1:proxy.port--> FaultProxy --> upstream (a simulator on serve_tcp)

Bytes are forwarded in order in both directions, chunk by chunk as they are read.  With faults
enabled, each chunk, independently in each direction, may be:

===============  ==========================================================================
``drop``         lose one byte of the chunk (a character lost on the line)
``flip``         flip one bit of one byte (line noise)
``delay``        hold the chunk (and so everything behind it) for up to ``max_delay`` seconds
``split``        deliver the chunk as several writes, a few milliseconds apart
``merge``        hold the chunk until the next one arrives (at most ``merge_hold`` s), send both
                 as one write
``duplicate``    send the chunk twice (a repeated frame, e.g. a DF1 frame sent again)
``cut``          close both sides of the connection (the device server dropped the session)
===============  ==========================================================================

Scripted faults for deterministic tests: ``lose_next["up"] = n`` loses the next ``n`` chunks
going to the controller (``"down"``: coming from it), whether or not faults are enabled.

An *outage* closes every open connection and, until it ends, closes each newly accepted
connection at once (a device server that accepts and hangs up, as a busy or rebooting one
does).  Counters, by fault kind, count what was injected; ``connections`` and
``refused_during_outage`` count accepted connections.  The RNG is seeded: a run replays the
same fault decisions for the same sequence of chunks.

Only 127.0.0.1 is used: this proxy never connects anywhere else.
"""

from __future__ import annotations

import asyncio
import contextlib
import random
from collections import Counter
from dataclasses import dataclass, fields

__all__ = ["FaultProfile", "FaultProxy"]

HOST = "127.0.0.1"

FAULT_KINDS = ("drop", "flip", "delay", "split", "merge", "duplicate", "cut")


@dataclass
class FaultProfile:
    """Probability of each fault per forwarded chunk (0 = never)."""

    drop: float = 0.0
    flip: float = 0.0
    delay: float = 0.0
    split: float = 0.0
    merge: float = 0.0
    duplicate: float = 0.0
    cut: float = 0.0
    max_delay: float = 0.25
    merge_hold: float = 0.05

    def scaled(self, factor: float) -> FaultProfile:
        """The same profile with every probability multiplied by ``factor``."""
        values = {f.name: getattr(self, f.name) for f in fields(self)}
        for kind in FAULT_KINDS:
            values[kind] = min(1.0, values[kind] * factor)
        return FaultProfile(**values)


class _Session:
    """One client connection and its upstream connection, with one pump per direction."""

    def __init__(self, proxy: FaultProxy, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.proxy = proxy
        self.client_reader = reader
        self.client_writer = writer
        self.upstream_writer: asyncio.StreamWriter | None = None
        self.tasks: list[asyncio.Task[None]] = []
        self.closed = asyncio.Event()

    async def run(self) -> None:
        try:
            up_reader, up_writer = await asyncio.open_connection(HOST, self.proxy.upstream_port)
        except OSError:
            self.client_writer.close()
            return
        self.upstream_writer = up_writer
        self.tasks = [
            asyncio.create_task(self._pump(self.client_reader, up_writer, "up"), name="proxy-up"),
            asyncio.create_task(self._pump(up_reader, self.client_writer, "down"), name="proxy-down"),
        ]
        try:
            await asyncio.wait(self.tasks, return_when=asyncio.FIRST_COMPLETED)
        finally:
            await self.close()

    async def close(self) -> None:
        for task in self.tasks:
            task.cancel()
        for writer in (self.client_writer, self.upstream_writer):
            if writer is not None:
                writer.close()
        await asyncio.gather(*self.tasks, return_exceptions=True)
        for writer in (self.client_writer, self.upstream_writer):
            if writer is not None:
                with contextlib.suppress(OSError, asyncio.CancelledError):
                    await writer.wait_closed()
        self.closed.set()

    async def _pump(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, direction: str) -> None:
        proxy = self.proxy
        held = b""
        while True:
            try:
                if held:
                    try:
                        async with asyncio.timeout(proxy.profile.merge_hold):
                            data = await reader.read(4096)
                    except TimeoutError:
                        await self._write(writer, held)
                        held = b""
                        continue
                else:
                    data = await reader.read(4096)
            except OSError:
                return
            if not data:
                if held:
                    await self._write(writer, held)
                return
            proxy.forwarded[direction] += len(data)
            if not proxy.faults_enabled and not proxy.lose_next[direction]:
                await self._write(writer, held + data)
                held = b""
                continue
            if proxy.lose_next[direction] > 0:  # scripted: this chunk is lost on the line
                proxy.lose_next[direction] -= 1
                proxy.counters["lost"] += 1
                continue
            data = held + data
            held = b""
            rng, profile, counts = proxy.rng, proxy.profile, proxy.counters
            if rng.random() < profile.cut:
                counts["cut"] += 1
                return  # run() closes both sides
            if rng.random() < profile.drop and data:
                counts["drop"] += 1
                i = rng.randrange(len(data))
                data = data[:i] + data[i + 1 :]
            if rng.random() < profile.flip and data:
                counts["flip"] += 1
                i = rng.randrange(len(data))
                data = data[:i] + bytes((data[i] ^ (1 << rng.randrange(8)),)) + data[i + 1 :]
            if rng.random() < profile.merge:
                counts["merge"] += 1
                held = data
                continue
            if rng.random() < profile.delay:
                counts["delay"] += 1
                await asyncio.sleep(rng.uniform(0.0, profile.max_delay))
            copies = 1
            if rng.random() < profile.duplicate:
                counts["duplicate"] += 1
                copies = 2
            for _ in range(copies):
                if len(data) > 1 and rng.random() < profile.split:
                    counts["split"] += 1
                    cuts = sorted(rng.sample(range(1, len(data)), min(len(data) - 1, rng.randint(1, 3))))
                    for start, end in zip([0, *cuts], [*cuts, len(data)], strict=True):
                        await self._write(writer, data[start:end])
                        await asyncio.sleep(rng.uniform(0.0005, 0.003))
                else:
                    await self._write(writer, data)

    @staticmethod
    async def _write(writer: asyncio.StreamWriter, data: bytes) -> None:
        if data and not writer.is_closing():
            writer.write(data)
            await writer.drain()


class FaultProxy:
    """Forward ``127.0.0.1:port`` to ``127.0.0.1:upstream_port``, injecting faults."""

    def __init__(self, upstream_port: int, *, seed: int, profile: FaultProfile | None = None) -> None:
        self.upstream_port = upstream_port
        self.rng = random.Random(seed)
        self.profile = profile or FaultProfile()
        self.faults_enabled = False
        self.counters: Counter[str] = Counter({kind: 0 for kind in FAULT_KINDS})
        self.forwarded: Counter[str] = Counter(up=0, down=0)
        #: scripted faults: lose the next N chunks going "up" (to the controller) or "down"
        self.lose_next: Counter[str] = Counter(up=0, down=0)
        self.connections = 0
        self.refused_during_outage = 0
        self.outages = 0
        self._outage = False
        self._server: asyncio.Server | None = None
        self._sessions: set[_Session] = set()
        self._tasks: set[asyncio.Task[None]] = set()

    @property
    def port(self) -> int:
        assert self._server is not None, "start() first"
        port: int = self._server.sockets[0].getsockname()[1]
        return port

    @property
    def url(self) -> str:
        return f"socket://{HOST}:{self.port}"

    @property
    def in_outage(self) -> bool:
        return self._outage

    async def start(self) -> None:
        self._server = await asyncio.start_server(self._accept, HOST, 0)

    async def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        if task is not None:
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)
        self.connections += 1
        if self._outage:
            self.refused_during_outage += 1
            writer.close()
            with contextlib.suppress(OSError):
                await writer.wait_closed()
            return
        session = _Session(self, reader, writer)
        self._sessions.add(session)
        try:
            await session.run()
        finally:
            self._sessions.discard(session)

    async def cut_all(self) -> None:
        """Close every open connection (both sides)."""
        sessions = list(self._sessions)
        await asyncio.gather(*(s.close() for s in sessions), return_exceptions=True)

    async def begin_outage(self) -> None:
        """Cut every connection; from now on close each accepted connection at once."""
        self._outage = True
        self.outages += 1
        await self.cut_all()

    def end_outage(self) -> None:
        self._outage = False

    async def outage(self, seconds: float) -> None:
        await self.begin_outage()
        try:
            await asyncio.sleep(seconds)
        finally:
            self.end_outage()

    async def close(self) -> None:
        if self._server is not None:
            self._server.close()
        await self.cut_all()
        if self._tasks:
            await asyncio.wait(set(self._tasks), timeout=2.0)
        if self._server is not None:
            with contextlib.suppress(OSError):
                await self._server.wait_closed()
            self._server = None

    def summary(self) -> dict[str, int]:
        out = {kind: self.counters[kind] for kind in FAULT_KINDS}
        out["outages"] = self.outages
        out["connections"] = self.connections
        out["refused_during_outage"] = self.refused_during_outage
        return out
