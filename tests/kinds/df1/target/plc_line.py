"""The PLC's side of a DF1 full-duplex link to a target-mode gateway, for tests: the gateway's
link connects to a TCP port the test listens on (``socket://``), and the test sends MSG commands."""

from __future__ import annotations

import asyncio

from gateway.protocols.df1.address import FileType
from gateway.protocols.df1.framing import ACK_SYMBOL, NEED_DATA, AckReceived, Checksum, Frame, encode_frame
from gateway.protocols.df1.framing.decoder import FrameDecoder
from gateway.protocols.df1.pccc import PcccHeader, ProtectedTypedLogicalRead, Request, encode_command

#: the gateway's station and the PLC's node
STATION, PLC_NODE = 1, 9


class Plc:
    """The PLC's side of the DF1 link: one MSG at a time, each reply ACKed."""

    def __init__(self) -> None:
        self.line: asyncio.Future[tuple[asyncio.StreamReader, asyncio.StreamWriter]] = (
            asyncio.get_running_loop().create_future()
        )
        self.decoder = FrameDecoder(Checksum.CRC)
        self.tns = 0

    def connected(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if not self.line.done():
            self.line.set_result((reader, writer))

    async def msg(self, request: Request) -> bytes:
        """Send one command; its reply packet (DST .. data)."""
        reader, writer = await asyncio.wait_for(asyncio.shield(self.line), 10)
        self.tns += 1
        writer.write(encode_frame(encode_command(request, dst=STATION, src=PLC_NODE, tns=self.tns), Checksum.CRC))
        acked = False
        while True:
            data = await asyncio.wait_for(reader.read(4096), 10)
            assert data, "the gateway closed the DF1 line"
            self.decoder.feed(data)
            while (event := self.decoder.next_event()) is not NEED_DATA:
                if isinstance(event, AckReceived):
                    acked = True
                elif isinstance(event, Frame):
                    assert acked, "a reply before the DLE ACK of the command"
                    writer.write(ACK_SYMBOL)
                    assert PcccHeader.decode(event.message).tns == self.tns
                    return event.message

    async def sts(self, request: Request) -> int:
        return PcccHeader.decode(await self.msg(request)).sts

    async def read_n7(self, element: int, count: int) -> list[int]:
        """N7:element.. by SLC typed logical reads of at most 100 words (200 of the 236 bytes allowed)."""
        values: list[int] = []
        for first in range(element, element + count, 100):
            size = 2 * min(100, element + count - first)
            reply = await self.msg(ProtectedTypedLogicalRead(FileType.INTEGER, 7, first, 0, size))
            assert PcccHeader.decode(reply).sts == 0, reply.hex()
            data = reply[6:]
            values += [int.from_bytes(data[i : i + 2], "little", signed=True) for i in range(0, len(data), 2)]
        return values


