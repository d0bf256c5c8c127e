"""A client that does not read its replies is paused, then dropped; other clients go on."""

from __future__ import annotations

import asyncio
import socket
import struct
from collections.abc import Sequence

from gateway.modbus.server import ModbusTcpServer

HOST = "127.0.0.1"


class Registers:
    def __init__(self) -> None:
        self.reads = 0

    def has_unit(self, unit: int) -> bool:
        return unit == 1

    async def read_holding_registers(self, unit: int, address: int, count: int) -> Sequence[int]:
        self.reads += 1
        return [address & 0xFFFF] * count

    async def read_input_registers(self, unit: int, address: int, count: int) -> Sequence[int]:
        return [0] * count

    async def read_coils(self, unit: int, address: int, count: int) -> Sequence[bool]:
        return [False] * count

    async def read_discrete_inputs(self, unit: int, address: int, count: int) -> Sequence[bool]:
        return [False] * count

    async def write_coils(self, unit: int, address: int, values: Sequence[bool]) -> None: ...

    async def write_registers(self, unit: int, address: int, values: Sequence[int]) -> None: ...


def fc3(tid: int) -> bytes:
    return struct.pack(">HHHBBHH", tid & 0xFFFF, 0, 6, 1, 3, 0, 125)


async def test_a_client_that_leaves_its_replies_unread_is_dropped_and_others_are_served() -> None:
    backend = Registers()
    server = ModbusTcpServer(backend, HOST, 0, write_stall_timeout=0.5)  # type: ignore[arg-type]
    await server.start()
    try:
        sock = socket.socket()
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        sock.setblocking(False)
        await asyncio.get_running_loop().sock_connect(sock, (HOST, server.port))
        greedy_reader, greedy = await asyncio.open_connection(sock=sock)
        greedy.write(b"".join(fc3(tid) for tid in range(40_000)))  # 10 MB of replies, never read
        polite_reader, polite = await asyncio.open_connection(HOST, server.port)
        async with asyncio.timeout(5):
            while not server.counters.connections_dropped:
                polite.write(fc3(1))
                header = await polite_reader.readexactly(9)
                await polite_reader.readexactly(struct.unpack(">H", header[4:6])[0] - 3)
                await asyncio.sleep(0.05)
        assert server.counters.connections_dropped == 1
        assert server.connection_count == 1  # the polite one
        # bounded work for the greedy one: socket buffers and the transport's, not 40,000 replies
        assert backend.reads < 5_000, backend.reads
        polite.close()
        greedy.close()
        del greedy_reader
    finally:
        await server.close()
