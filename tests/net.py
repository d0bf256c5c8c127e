"""Sockets in tests: a free loopback port, and an MBAP (Modbus TCP) frame built by hand."""

from __future__ import annotations

import socket
import struct

HOST = "127.0.0.1"


def free_port(host: str = HOST) -> int:
    """A TCP port free on ``host`` now (the kernel's choice; the caller binds it soon after)."""
    with socket.socket() as sock:
        sock.bind((host, 0))
        port: int = sock.getsockname()[1]
        return port


def mbap(tid: int, unit: int, pdu: bytes, protocol: int = 0, length: int | None = None) -> bytes:
    """An MBAP header (transaction ``tid``, ``protocol``, ``length`` = PDU + 1 unless given, ``unit``) + ``pdu``."""
    return struct.pack(">HHHB", tid, protocol, len(pdu) + 1 if length is None else length, unit) + pdu
