"""CPU per controller transaction: codec + driver (+ poller and unit), unpaced, in-process.

The peer is a *canned* byte stream: a first pass records the real simulator's (``gateway.sim``)
reply to every request frame the gateway sends; the measured passes replay them (the message
ID / TNS sequence restarts with each driver, so the frames repeat exactly), so answering costs
one dict look-up and one ``Queue.put_nowait``: what is measured is the gateway's code, not the
simulator's.  The reply is delivered on a later
event-loop iteration, as a socket's would be.

Levels, for an SLC 100/150 two-byte read (ASCII protocol) and an SLC 5/04 protected typed
logical read (DF1 full duplex, CRC; the benchmark map's plan, 77 data bytes per read on average):

* ``codec``   the sans-I/O cores alone: build the command frame, feed the reply, get the
              event, parse the data (DF1: the link state machine, ACKs included);
* ``driver``  ``driver.read()`` / ``driver.execute()`` in a loop: + request queue, worker task,
              futures, timers, counters;
* ``poller``  the production path: ``Poller`` -> ``Unit.read_block`` -> driver, cache store.

CPU time is ``time.process_time()`` over the run, best of three (the canned peer's own cost
is included in the driver and poller levels; it is measured alone and shown).  Full mode adds
a cProfile top-15 (by own time) of the
poller level of each protocol.

    python bench/cpu_per_transaction.py [--quick] [--transactions N]
"""

from __future__ import annotations

import argparse
import asyncio
import cProfile
import io
import itertools
import pstats
import time
from collections.abc import Callable, Sequence
from typing import Any

from _benchlib import DF1_MAP, print_machine, result, table

from gateway.kinds.df1.full.driver import Df1Driver
from gateway.kinds.df1.plan import MapItem
from gateway.kinds.df1.unit import Df1Unit
from gateway.kinds.slc_ascii.driver import SlcAsciiDriver
from gateway.kinds.slc_ascii.unit import SlcAsciiUnit
from gateway.modbus.mapping import Block, Scan
from gateway.protocols.df1.framing import NEED_DATA as DF1_NEED_DATA
from gateway.protocols.df1.framing import Checksum, encode_frame
from gateway.protocols.df1.full_duplex.datalink import Df1DataLink, MessageReceived, SendComplete
from gateway.protocols.df1.pccc import ProtectedTypedLogicalRead, decode_reply
from gateway.protocols.df1.pccc import encode_command as encode_pccc
from gateway.protocols.slc_ascii import commands as cmds
from gateway.protocols.slc_ascii.framing import NEED_DATA, ReplyDecoder
from gateway.protocols.slc_ascii.framing import frame_command as encode_slc
from gateway.sim import create_simulator
from gateway.transport import ByteStream, SerialSettings

ACK = b"\x10\x06"


class CannedStream(ByteStream):
    """Answers each request frame with its recorded reply (a DF1 DLE ACK gets nothing).

    Recording (``replies`` is None): every byte written goes to a real simulator, whose answer
    is delivered and remembered.  Replaying: the answer is a dict look-up.  The drivers are
    deterministic (message IDs / TNS restart with each new driver), so a replay pass sends
    exactly the frames recorded; a frame not recorded counts as a miss (and gets no answer).
    """

    def __init__(self, model: str, replies: dict[bytes, bytes] | None = None) -> None:
        self.recording = replies is None
        self.replies: dict[bytes, bytes] = {} if replies is None else replies
        self.queue: asyncio.Queue[bytes] = asyncio.Queue()
        self.misses = 0
        self.device: Any = None
        self.now = 1.0
        if self.recording:
            options = {"ladder": "0"}
            if model == "slc504":
                options.update(checksum="crc", station="1")
            self.device = create_simulator(model, options)

    async def read(self) -> bytes:
        return await self.queue.get()

    def write(self, data: bytes) -> None:
        if self.recording:
            self.now += 0.05
            reply = b"".join(out.data for out in self.device.receive(data, self.now))
            if data != ACK:
                self.replies[data] = reply
            if reply:
                self.queue.put_nowait(reply)
            return
        reply = self.replies.get(data)
        if reply is not None:
            self.queue.put_nowait(reply)
        elif data != ACK:
            self.misses += 1

    async def close(self) -> None:
        pass


# --------------------------------------------------------------------------------------------
# request sequences and their replies (from the real simulators)


def slc_ids() -> itertools.cycle[int]:
    return itertools.chain([0], itertools.cycle(range(1, 0x80)))  # type: ignore[return-value]


def slc_sequence(blocks: Sequence[Block], n: int) -> list[bytes]:
    frames = []
    ids = slc_ids()
    for i in range(n):
        address, count = blocks[i % len(blocks)].request  # type: ignore[misc]
        frames.append(encode_slc(cmds.read_bytes(address, count), next(ids)))
    return frames


def df1_request(block: Block) -> ProtectedTypedLogicalRead:
    r = block.request
    return ProtectedTypedLogicalRead(r.file_type, r.file_number, r.element, r.sub_element, r.size)  # type: ignore[attr-defined]


def df1_sequence(blocks: Sequence[Block], n: int) -> list[bytes]:
    return [
        encode_frame(
            encode_pccc(df1_request(blocks[i % len(blocks)]), dst=1, src=0, tns=(i + 1) & 0xFFFF), Checksum.CRC
        )
        for i in range(n)
    ]


def canned_replies(model: str, frames: Sequence[bytes]) -> dict[bytes, bytes]:
    options = {"ladder": "0"}
    if model == "slc504":
        options.update(checksum="crc", station="1")
    device = create_simulator(model, options)
    replies: dict[bytes, bytes] = {}
    now = 1.0
    for frame in frames:
        now += 0.05
        reply = b"".join(out.data for out in device.receive(frame, now))
        if model == "slc504":
            device.receive(ACK, now)  # our ACK of its reply
        replies.setdefault(frame, reply)
    return replies


# --------------------------------------------------------------------------------------------
# the three levels


def slc_blocks() -> tuple[list[Block], list[Block]]:
    from gateway.kinds.slc_ascii.plan import slc_ascii_plan

    blocks = slc_ascii_plan().blocks
    return [b for b in blocks if b.scan is Scan.SLOW], [b for b in blocks if b.scan is Scan.FAST]


def df1_blocks() -> list[Block]:
    from gateway.kinds.df1.plan import plan_df1

    return plan_df1([MapItem(**e) for e in DF1_MAP], 236).blocks  # type: ignore[arg-type]


def codec_slc(frames: Sequence[bytes], replies: dict[bytes, bytes], blocks: Sequence[Block]) -> float:
    """Seconds of CPU per transaction for the SLC sans-I/O work."""
    n = len(frames)
    reply_list = [replies[f] for f in frames]
    decoder = ReplyDecoder()
    ids = slc_ids()
    start = time.process_time()
    for i in range(n):
        address, count = blocks[i % len(blocks)].request  # type: ignore[misc]
        encode_slc(cmds.read_bytes(address, count), next(ids))
        decoder.receive_data(reply_list[i])
        event = decoder.next_event()
        cmds.parse_read_reply(address, count, event.body_hex)  # type: ignore[union-attr]
        assert decoder.next_event() is NEED_DATA
    return (time.process_time() - start) / n


def codec_df1(frames: Sequence[bytes], replies: dict[bytes, bytes], blocks: Sequence[Block]) -> float:
    n = len(frames)
    reply_list = [replies[f] for f in frames]
    link = Df1DataLink(checksum=Checksum.CRC)
    start = time.process_time()
    for i in range(n):
        packet = encode_pccc(df1_request(blocks[i % len(blocks)]), dst=1, src=0, tns=(i + 1) & 0xFFFF)
        link.send(packet, 1.0)
        link.data_to_send()
        link.receive_data(reply_list[i], 1.0)
        link.data_to_send()  # our ACK
        got = False
        while (event := link.next_event()) is not DF1_NEED_DATA:
            if isinstance(event, MessageReceived):
                decode_reply(event.payload)
                got = True
            else:
                assert isinstance(event, SendComplete)
        assert got
    return (time.process_time() - start) / n


def opener_for(stream: CannedStream) -> Callable[..., Any]:
    async def opener(*args: object, **kwargs: object) -> ByteStream:
        return stream

    return opener


def make_driver(protocol: str, stream: CannedStream) -> Any:
    if protocol == "slc":
        return SlcAsciiDriver("canned://slc", opener=opener_for(stream))
    # The driver starts at a random TNS (so that a new session is never taken for a repeat of
    # the last); the replay needs the frames it recorded, so both passes start at TNS 1 here.
    return Df1Driver("canned://df1", opener=opener_for(stream), settings=SerialSettings(19200, 8, "N", 1),
                     first_tns=1)


async def driver_level(
    protocol: str, n: int, blocks: Sequence[Block], replies: dict[bytes, bytes] | None
) -> tuple[float, float, CannedStream]:
    """(CPU s per transaction, wall s per transaction, stream) of ``n`` driver reads in a loop."""
    stream = CannedStream("slc150" if protocol == "slc" else "slc504", replies)
    driver = make_driver(protocol, stream)
    if protocol == "slc":
        requests: list[Any] = [blocks[i % len(blocks)].request for i in range(n)]
    else:
        requests = [df1_request(blocks[i % len(blocks)]) for i in range(n)]
    await driver.start()
    try:
        start, wall = time.process_time(), time.perf_counter()
        if protocol == "slc":
            for address, count in requests:
                await driver.read(address, count)
        else:
            for request in requests:
                await driver.execute(request, "read")
        cpu, wall = time.process_time() - start, time.perf_counter() - wall
    finally:
        await driver.close()
    return cpu / n, wall / n, stream


async def poller_level(
    protocol: str, n: int, replies: dict[bytes, bytes] | None, profile: cProfile.Profile | None = None
) -> tuple[float, float, CannedStream]:
    """(CPU s per transaction, wall s per transaction, stream): the production path, ``n`` transactions."""
    stream = CannedStream("slc150" if protocol == "slc" else "slc504", replies)
    driver = make_driver(protocol, stream)
    if protocol == "slc":
        unit: Any = SlcAsciiUnit(driver=driver, unit_id=1, name="slc", slow_interval=1e9)
    else:
        unit = Df1Unit(driver=driver, items=[MapItem(**e) for e in DF1_MAP], max_read_bytes=236,  # type: ignore[arg-type]
                       unit_id=1, name="df1", slow_interval=1e9)
    await driver.start()
    counters = driver.counters
    poller = asyncio.create_task(unit.poller.run())
    try:
        while counters.transactions < 60:  # the slow class and the resync are not timed  # noqa: ASYNC110
            await asyncio.sleep(0.001)
        before, start, wall = counters.transactions, time.process_time(), time.perf_counter()
        if profile is not None:
            profile.enable()
        while counters.transactions < n and (stream.recording or not stream.misses):  # noqa: ASYNC110
            await asyncio.sleep(0.001)
        if profile is not None:
            profile.disable()
        cpu, wall = time.process_time() - start, time.perf_counter() - wall
        done = counters.transactions - before
    finally:
        poller.cancel()
        await driver.close()
    return cpu / done, wall / done, stream


def peer_cost(replies: dict[bytes, bytes]) -> float:
    """CPU per transaction of the canned peer alone (look-up + queue put + get)."""
    frames = [f for f in replies if f != ACK]

    async def run() -> float:
        stream = CannedStream("", replies)
        start = time.process_time()
        for frame in frames:
            stream.write(frame)
            await stream.read()
        return (time.process_time() - start) / len(frames)

    return asyncio.run(run())


def top15(profile: cProfile.Profile, title: str) -> None:
    out = io.StringIO()
    stats = pstats.Stats(profile, stream=out)
    stats.sort_stats("tottime").print_stats(15)
    print(f"\n--- cProfile, {title}: top 15 by own time ---")
    text = out.getvalue()
    print(text[text.find("   ncalls") :].rstrip())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="a few thousand transactions, no profile (CI)")
    parser.add_argument("--transactions", type=int, default=0, help="per measurement (default 20000; quick 1500)")
    args = parser.parse_args()
    n = args.transactions or (1500 if args.quick else 20000)
    print_machine()
    _, fast = slc_blocks()
    slc_frames = slc_sequence(fast, n)
    slc_replies = canned_replies("slc150", slc_frames)
    d_blocks = df1_blocks()
    df1_frames_ = df1_sequence(d_blocks, n)
    df1_replies = canned_replies("slc504", df1_frames_)
    print(f"SLC: {len(fast)} fast blocks, frames {len(slc_frames[0])} + {len(slc_replies[slc_frames[0]])} bytes; "
          f"DF1: {len(d_blocks)} blocks, mean reply {sum(len(df1_replies[f]) for f in df1_frames_[:4]) / 4:.0f} bytes")
    rows = []
    values: dict[str, object] = {"transactions": n}
    recorded: dict[str, dict[bytes, bytes]] = {}
    for name, protocol, frames, replies, blocks, codec in (
        ("slc-ascii read", "slc", slc_frames, slc_replies, fast, codec_slc),
        ("df1 read", "df1", df1_frames_, df1_replies, d_blocks, codec_df1),
    ):
        codec_cpu = min(codec(frames, replies, blocks) for _ in range(3))
        _, _, record = asyncio.run(driver_level(protocol, n, blocks, None))
        driver_runs = [asyncio.run(driver_level(protocol, n, blocks, record.replies)) for _ in range(3)]
        _, _, record_poll = asyncio.run(poller_level(protocol, n + 200, None))
        recorded[protocol] = record_poll.replies
        poller_runs = [asyncio.run(poller_level(protocol, n, record_poll.replies)) for _ in range(3)]
        misses = sum(run[2].misses for run in driver_runs + poller_runs)
        if misses:
            raise SystemExit(f"{name}: {misses} request frames were not recorded ones (driver not deterministic?)")
        driver_cpu = min(run[0] for run in driver_runs)
        poller_cpu, poller_wall, _ = min(poller_runs, key=lambda run: run[0])
        peer = peer_cost(record.replies)
        rows.append([name, codec_cpu * 1e6, driver_cpu * 1e6, poller_cpu * 1e6, peer * 1e6, 1 / poller_wall])
        values[f"{protocol}_codec_us"] = codec_cpu * 1e6
        values[f"{protocol}_driver_us"] = driver_cpu * 1e6
        values[f"{protocol}_poller_us"] = poller_cpu * 1e6
    print("CPU per transaction, best of 3 runs (process_time)")
    print(table(["transaction", "codec us", "driver us", "poller+unit+driver us", "canned peer us (included)",
                 "unpaced tx/s (poller)"], rows))
    if not args.quick:
        for protocol, title in (("slc", "SLC 100/150 poller path"), ("df1", "DF1 poller path")):
            profile = cProfile.Profile(time.process_time)
            asyncio.run(poller_level(protocol, n, recorded[protocol], profile))
            top15(profile, title)
    result(**values)


if __name__ == "__main__":
    main()
