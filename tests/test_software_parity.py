"""The serial fallback for ports that refuse 7 data bits with parity: 8N1, parity computed here."""

from __future__ import annotations

import asyncio
import logging
import os
import tty
from collections.abc import Callable, Iterator

import pytest

from gateway import transport
from gateway.transport import ByteStream, SerialSettings, SoftwareParityStream, open_stream


class FakeStream(ByteStream):
    def __init__(self) -> None:
        self.written = b""
        self.incoming: list[bytes] = []

    async def read(self) -> bytes:
        return self.incoming.pop(0)

    def write(self, data: bytes) -> None:
        self.written += data

    async def close(self) -> None:
        pass

    def start_push(self, receive: Callable[[bytes], None], lost: Callable[[str], None]) -> bool:
        self.receive = receive
        return True


def even_parity_bit(byte: int) -> int:
    return bin(byte).count("1") & 1


async def test_every_7_bit_character_gets_its_parity_bit_as_bit_7() -> None:
    for parity, odd in (("E", 0), ("O", 1)):
        inner = FakeStream()
        stream = SoftwareParityStream(inner, parity)
        stream.write(bytes(range(128)))
        assert list(inner.written) == [c | (even_parity_bit(c) ^ odd) << 7 for c in range(128)]
        # every character on the wire has an even (odd) number of one bits, as 7E1 (7O1) sends it
        assert all(bin(b).count("1") % 2 == odd for b in inner.written)


async def test_bit_7_of_received_characters_is_dropped() -> None:
    inner = FakeStream()
    stream = SoftwareParityStream(inner, "E")
    inner.incoming.append(b"\xba\x30\x32")  # ':' with its even parity bit set, '0', '2'
    assert await stream.read() == b":02"
    got: list[bytes] = []
    assert stream.start_push(got.append, lambda reason: None)
    inner.receive(b"\xc3A")
    assert got == [b"CA"]


@pytest.fixture
def pty_pair() -> Iterator[tuple[int, str]]:
    master, slave = os.openpty()
    tty.setraw(master)
    path = os.ttyname(slave)
    os.close(slave)
    yield master, path
    os.close(master)


async def test_a_port_refusing_7e1_opens_at_8n1_and_says_so_once(
    pty_pair: tuple[int, str], caplog: pytest.LogCaptureFixture
) -> None:
    master, path = pty_pair
    transport._SOFTWARE_PARITY_LOGGED.discard(path)
    caplog.set_level(logging.INFO, logger="gateway.transport")
    for _ in range(2):
        stream = await open_stream(path, SerialSettings(9600, 7, "E", 1))
        try:
            if not isinstance(stream, SoftwareParityStream):
                pytest.skip(f"this machine's pseudo-terminals accept 7E1 ({path}): no fallback to test")
            stream.write(b"#C")  # 0x23 (3 ones) -> 0xA3, 0x43 (3 ones) -> 0xC3
            data = b""
            while len(data) < 2:
                data += await asyncio.to_thread(os.read, master, 16)
            assert data == b"\xa3\xc3"
            os.write(master, b"\xba\x30")
            assert await asyncio.wait_for(stream.read(), 5) == b":0"
        finally:
            await stream.close()
    messages = [r.getMessage() for r in caplog.records if "parity bit computed in software" in r.getMessage()]
    assert messages == [
        f"{path} refuses 7E1: using 8N1 with the parity bit computed in software (the same bits on the wire)"
    ]


async def test_settings_other_than_7_bits_with_parity_do_not_fall_back(pty_pair: tuple[int, str]) -> None:
    _, path = pty_pair
    stream = await open_stream(path, SerialSettings(9600, 8, "N", 1))
    try:
        assert not isinstance(stream, SoftwareParityStream)
    finally:
        await stream.close()
