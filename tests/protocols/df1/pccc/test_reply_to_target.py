"""A reply frame sent to the gateway gets no answer, in every path that answers a PLC's message.

A PCCC reply (CMD bit 6 set, 1770-6.5.16 p. 6-4: "the reply bit") is the end of a transaction, not a
command: there is nothing to reply to, and a reply to a reply would be taken by the peer as the
answer to a command of its own with that TNS.  The link layer still ACKs the frame (it arrived
intact, p. 4-8), and it does not hold a place in the target's message sink.

Paths: the PCCC target (``pccc/target.py``), the half-duplex slave-message path
(``slave_messages.py``) and the full-duplex target link (``kinds/df1/target/driver.py``), the last
one driven over a real loopback socket as the PLC.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable

from gateway.app import Gateway
from gateway.config import parse_config
from gateway.protocols.df1.framing import ACK_SYMBOL, NEED_DATA, Checksum, Frame, encode_frame
from gateway.protocols.df1.framing.decoder import FrameDecoder
from gateway.protocols.df1.half_duplex.slave_messages import RegisterTable, SlaveMessageVerdict, answer_slave_message
from gateway.protocols.df1.pccc.target import PcccTarget
from gateway.protocols.df1.pccc.target_table import DataTable

GATEWAY = 0
PLC = 1

#: Replies, as a PLC would send them: an SLC typed logical read reply (0F | 40 = 4F, STS 0, TNS,
#: data), a write reply, a refusal with EXT STS, a diagnostic reply (06 | 40 = 46).
REPLIES = [
    bytes((GATEWAY, PLC, 0x4F, 0x00, 0x01, 0x00, 0x34, 0x12)),
    bytes((GATEWAY, PLC, 0x4F, 0x00, 0x02, 0x00)),
    bytes((GATEWAY, PLC, 0x4F, 0xF0, 0x03, 0x00, 0x06)),
    bytes((GATEWAY, PLC, 0x46, 0x00, 0x04, 0x00, 0x00)),
    bytes((GATEWAY, PLC, 0x4F, 0x10, 0x05, 0x00)),
]
#: A command after them: echo (CMD 06, FNC 00, notes §4.0) of two bytes.
ECHO = bytes((GATEWAY, PLC, 0x06, 0x00, 0x09, 0x00, 0x00, 0xAB, 0xCD))
ECHO_REPLY = bytes((PLC, GATEWAY, 0x46, 0x00, 0x09, 0x00, 0xAB, 0xCD))


def test_the_pccc_target_answers_no_reply() -> None:
    target = PcccTarget(DataTable.of("N7:10"))
    for packet in REPLIES:
        assert target.execute(packet, 0.0).reply is None


def test_the_half_duplex_slave_message_path_answers_no_reply() -> None:
    for packet in REPLIES:
        verdict, reply = answer_slave_message(packet, own_station=GATEWAY, table=RegisterTable(), now=0.0)
        assert (verdict, reply) == (SlaveMessageVerdict.NO_ANSWER, None)


CONFIG = """
[modbus]
listen = "127.0.0.1:0"

[[link]]
name = "plc"
protocol = "df1"
role = "target"
port = "socket://127.0.0.1:{port}"
unit = 5

[[link.file]]
file = 7
type = "N"
elements = 10
"""


async def test_the_target_link_acks_a_reply_frame_and_answers_nothing() -> None:
    """Five replies (more than the four commands the sink holds by default), then a command: each
    reply frame is ACKed and unanswered, and the command after them gets its own reply."""
    connected: asyncio.Queue[tuple[asyncio.StreamReader, asyncio.StreamWriter]] = asyncio.Queue()

    async def accept(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        await connected.put((reader, writer))

    server = await asyncio.start_server(accept, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    decoder = FrameDecoder(Checksum.CRC)
    received = bytearray()
    try:
        async with Gateway(parse_config(CONFIG.format(port=port))):
            reader, writer = await asyncio.wait_for(connected.get(), 10)

            async def read_until(done: Callable[[], bool], seconds: float) -> None:
                loop = asyncio.get_running_loop()
                end = loop.time() + seconds
                while not done() and (left := end - loop.time()) > 0:
                    try:
                        chunk = await asyncio.wait_for(reader.read(256), left)
                    except TimeoutError:
                        return
                    received.extend(chunk)

            def acked(n: int) -> Callable[[], bool]:
                return lambda: received.count(ACK_SYMBOL) >= n

            for n, packet in enumerate(REPLIES, 1):  # one at a time: each is ACKed before the next
                writer.write(encode_frame(packet, Checksum.CRC))
                await writer.drain()
                await read_until(acked(n), 10)
            await read_until(lambda: False, 0.5)  # a reply to a reply would come now
            assert bytes(received) == ACK_SYMBOL * len(REPLIES)

            writer.write(encode_frame(ECHO, Checksum.CRC))
            await writer.drain()
            frames: list[bytes] = []

            def echo_answered() -> bool:
                decoder.feed(bytes(received))
                received.clear()
                while (event := decoder.next_event()) is not NEED_DATA:
                    if isinstance(event, Frame):
                        frames.append(event.message)
                return bool(frames)

            await read_until(echo_answered, 10)
            assert frames == [ECHO_REPLY]
            writer.write(ACK_SYMBOL)
            await writer.drain()
            writer.close()
    finally:
        server.close()
        await server.wait_closed()
