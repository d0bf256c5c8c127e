"""The simulated SLC 5/04's side of the wire (``gateway.kinds.df1.sim.slc500``): cutting bytes into frames
and symbols, and the damage its fault injection does to them.  No I/O; the randomness comes from
the simulator's seeded generator.
"""

from __future__ import annotations

import random
from typing import Final

from gateway.protocols.df1.framing import Checksum, Frame, Symbol
from gateway.protocols.df1.framing.decoder import FrameDecoder
from gateway.protocols.df1.pccc import PcccFormatError, decode_command, is_write

__all__ = ["NOISE_BYTES", "REPLY_ADDRESSES", "address_reply", "corrupt_frame",
           "frame_message", "garbage", "is_write_packet", "split_incoming",
           "split_output"]

NOISE_BYTES: Final = tuple(b for b in range(256) if b != Symbol.DLE)

#: How a controller fills DST / SRC of a reply (1770-6.5.16 p. 6-4 says: interchange the command's;
#: the same page lets a module overwrite SRC 0 with its own node number, and an SLC on full duplex
#: ignores DST): ``swapped`` (the manual), ``unswapped`` (the command's DST / SRC as they came),
#: ``own_station`` (DST = the command's SRC, SRC = the controller's own address).
REPLY_ADDRESSES: Final = ("swapped", "unswapped", "own_station")


def address_reply(command: bytes, reply: bytes, reading: str, own_station: int) -> bytes:
    """``reply`` (built with DST / SRC swapped) with the DST / SRC of ``reading``."""
    if reading == "swapped" or len(reply) < 2 or len(command) < 2:
        return reply
    if reading == "unswapped":
        return command[:2] + reply[2:]
    return bytes((command[1], own_station)) + reply[2:]


def is_write_packet(packet: bytes) -> bool:
    """A PCCC command packet that changes the controller (:func:`~gateway.protocols.df1.pccc.is_write`)."""
    try:
        return is_write(decode_command(packet).request)
    except PcccFormatError:
        return False


def frame_message(frame: bytes, checksum: Checksum) -> bytes | None:
    """The message of one whole, valid frame, else None."""
    decoder = FrameDecoder(checksum)
    decoder.feed(frame)
    event = decoder.next_event()
    return event.message if isinstance(event, Frame) else None


def split_incoming(rx: bytearray, checksum: Checksum) -> list[tuple[bytes, bool]]:
    """Take whole frames and symbols off the front of ``rx`` (a partial one stays).

    Returns ``(token, whole_frame)`` pairs; ``whole_frame`` is False for symbols, garbage between
    frames and a frame cut short by a control symbol inside it (which the link judges as it is).
    """
    tokens: list[tuple[bytes, bool]] = []
    check = checksum.size
    i = 0
    while i < len(rx):
        if rx[i] != Symbol.DLE:  # garbage between frames: the link skips it
            j = i
            while j < len(rx) and rx[j] != Symbol.DLE:
                j += 1
            tokens.append((bytes(rx[i:j]), False))
            i = j
            continue
        if i + 1 >= len(rx):
            break
        if rx[i + 1] != Symbol.STX:
            tokens.append((bytes(rx[i : i + 2]), False))
            i += 2
            continue
        j, end, aborted = i + 2, None, False
        while j + 1 < len(rx):
            if rx[j] != Symbol.DLE:
                j += 1
            elif rx[j + 1] == Symbol.DLE:
                j += 2
            elif rx[j + 1] == Symbol.ETX:
                end = j + 2 + check if j + 2 + check <= len(rx) else None
                break
            else:  # DLE STX / DLE ENQ ... inside the frame
                end, aborted = j, True
                break
        if end is None:
            break  # not whole yet
        tokens.append((bytes(rx[i:end]), not aborted))
        i = end
    del rx[:i]
    return tokens


def corrupt_frame(frame: bytes, checksum: Checksum, rng: random.Random) -> bytes:
    """Change one message byte (never a DLE, never into a DLE): the check no longer matches."""
    body = bytearray(frame)
    end = len(body) - 2 - checksum.size  # index of the closing DLE
    candidates = [i for i in range(2, end) if body[i] != Symbol.DLE]
    if not candidates:  # a message of nothing but DLEs: damage the check instead
        body[-1] ^= 0x01
        return bytes(body)
    index = rng.choice(candidates)
    while True:
        value = body[index] ^ (1 << rng.randrange(8))
        if value != Symbol.DLE:
            body[index] = value
            return bytes(body)


def garbage(rng: random.Random) -> bytes:
    """1-8 random bytes without DLE, which a receiver hunting for DLE STX discards."""
    return bytes(rng.choice(NOISE_BYTES) for _ in range(rng.randint(1, 8)))


def split_output(data: bytes, checksum: Checksum) -> list[bytes]:
    """Split well-formed link output into frames (``DLE STX .. DLE ETX check``) and ``DLE x`` symbols."""
    tokens: list[bytes] = []
    i = 0
    while i < len(data):
        if data[i] != Symbol.DLE or i + 1 >= len(data):  # cannot happen with Df1DataLink output; keep it whole
            tokens.append(data[i:])
            break
        if data[i + 1] != Symbol.STX:
            tokens.append(data[i : i + 2])
            i += 2
            continue
        j = i + 2
        while j + 1 < len(data) and not (data[j] == Symbol.DLE and data[j + 1] == Symbol.ETX):
            j += 2 if data[j] == Symbol.DLE else 1
        end = min(len(data), j + 2 + checksum.size)
        tokens.append(data[i:end])
        i = end
    return tokens
