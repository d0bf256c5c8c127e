"""The diagnostic commands of the CLI for DF1 links (``--protocol df1``): probe, read, write, mode.

Items are SLC 500 logical addresses: ``N7:0`` (signed 16-bit), ``B3:0/3`` (a bit), ``F8:2``
(a float), ``T4:1.ACC``, ``C5:0/DN``, ``I:1.0``, ``S:1/5``; a whole structure (``T4:1``) reads
as its three words.
"""

from __future__ import annotations

import argparse
import re
import struct
from dataclasses import replace
from typing import Any

from gateway.config.df1 import DF1_DEFAULTS
from gateway.drivers.base import OpenStream
from gateway.drivers.df1 import Df1Driver
from gateway.errors import InvalidRequest
from gateway.links.df1.unit import PROCESSORS
from gateway.links.kind import ToolHints
from gateway.protocols.df1.address import FileType, SlcAddress, parse_address
from gateway.protocols.df1.framing import Checksum
from gateway.protocols.df1.pccc import (
    ProcessorMode,
    ProtectedTypedLogicalMaskedWrite,
    ProtectedTypedLogicalRead,
    ProtectedTypedLogicalWrite,
    SetProcessorMode,
)
from gateway.tools_common import print_result, resolve_retries

__all__ = ["HINTS", "add_options", "decode_value", "encode_value", "run_df1_tool"]

#: DF1 link-layer symbols: DLE followed by STX, ETX, ENQ, ACK or NAK (1770-6.5.16, full duplex).
_DLE_FRAMED = re.compile(rb"\x10[\x02\x03\x05\x06\x15]")

HINTS = ToolHints(
    looks_like=lambda received: _DLE_FRAMED.search(received) is not None,
    wire="DF1 (DLE-framed): an SLC 500 or PLC-5?",
    controllers="an SLC 500 or PLC-5",
    check="the cable, baud rate, --checksum and --station",
)


def decode_value(address: SlcAddress, data: bytes) -> Any:
    """The value of ``address`` from the bytes a typed read returned."""
    if address.file_type is FileType.FLOAT:
        return struct.unpack("<f", data[:4])[0]
    words = [int.from_bytes(data[i : i + 2], "little") for i in range(0, len(data), 2)]
    if address.bit is not None:
        return bool(words[0] >> address.bit & 1)
    if len(words) > 1:
        return words
    signed = address.file_type in (FileType.INTEGER, FileType.TIMER, FileType.COUNTER, FileType.CONTROL)
    return words[0] - 0x10000 if signed and words[0] & 0x8000 else words[0]


def encode_value(address: SlcAddress, text: str) -> tuple[bytes, int | None]:
    """(data, mask) for writing ``text`` to ``address``; mask is set for bit writes."""
    if address.file_type is FileType.FLOAT:
        try:
            return struct.pack("<f", float(text)), None
        except ValueError as exc:
            raise InvalidRequest(f"{address}={text}: not a number") from exc
    try:
        value = int(text, 0)
    except ValueError as exc:
        raise InvalidRequest(f"{address}={text}: not a whole number") from exc
    if address.bit is not None:
        if value not in (0, 1):
            raise InvalidRequest(f"{address}={text}: a bit takes 0 or 1")
        mask = 1 << address.bit
        return (mask if value else 0).to_bytes(2, "little"), mask
    if address.is_structure:
        raise InvalidRequest(f"{address}: write a member (.PRE, .ACC ...), not the whole structure")
    if not -0x8000 <= value <= 0xFFFF:
        raise InvalidRequest(f"{address}={text}: a word takes -32768..65535")
    return (value & 0xFFFF).to_bytes(2, "little"), None


def add_options(parser: argparse.ArgumentParser) -> None:
    """The options only DF1 commands take."""
    parser.add_argument("--station", type=int, default=1, help="df1: destination node (default 1)")
    parser.add_argument("--source", type=int, default=0, help="df1: our node (default 0)")
    parser.add_argument("--checksum", choices=("bcc", "crc"), default="crc", help="df1: bcc or crc (default crc)")
    parser.add_argument("--processor", default="slc5/04", choices=tuple(PROCESSORS),
                        help="df1: processor family (default slc5/04)")


async def run_df1_tool(command: str, args: argparse.Namespace, opener: OpenStream) -> int:
    if args.processor not in PROCESSORS:
        raise InvalidRequest(f"--processor {args.processor}: choose from {', '.join(PROCESSORS)}")
    settings = DF1_DEFAULTS.settings
    if args.baudrate:
        settings = replace(settings, baudrate=args.baudrate)
    if command == "read":
        items = [(text, parse_address(text)) for text in args.items]
    elif command == "write":
        writes = []
        for text in args.assignments:
            name, sep, value = text.partition("=")
            if not sep or not value:
                raise InvalidRequest(f"{text!r}: expected ADDRESS=VALUE, e.g. N7:0=5 or B3:0/3=1")
            address = parse_address(name)
            writes.append((name, address, value, *encode_value(address, value)))
    elif command not in ("probe", "mode"):
        raise InvalidRequest(f"{command} is not available for DF1 links")
    driver = Df1Driver(
        args.url,
        settings=settings,
        checksum=Checksum.CRC if args.checksum == "crc" else Checksum.BCC,
        station=args.station,
        source=args.source,
        family=PROCESSORS[args.processor],
        timeout=args.timeout or DF1_DEFAULTS.timeout,
        retries=resolve_retries(command, args.retries),
        trace=args.trace,
        reconnect_min=60.0,
        opener=opener,
    )
    async with driver:
        if command == "probe":
            info = await driver.probe()
            family = info.family
            print_result({
                "processor": family.value if family else f"unknown (type 0x{info.processor_type or 0:02X})",
                "catalog": info.catalog,
                "series": info.series,
                "frn": info.frn,
            }, args.json)
        elif command == "read":
            result: dict[str, Any] = {}
            for text, address in items:
                request = ProtectedTypedLogicalRead(
                    address.file_type, address.file_number, address.element, address.sub_element, address.byte_count
                )
                reply = await driver.execute(request, f"read {address}")
                result[text] = decode_value(address, reply.data)
            print_result(result, args.json)
        elif command == "write":
            for name, a, _, data, mask in writes:
                if mask is None:
                    await driver.execute(
                        ProtectedTypedLogicalWrite(a.file_type, a.file_number, a.element, a.sub_element, data),
                        f"write {name}",
                    )
                else:
                    masked = ProtectedTypedLogicalMaskedWrite(
                        a.file_type, a.file_number, a.element, a.sub_element, mask, data
                    )
                    await driver.execute(masked, f"write {name}")
            print_result({name: value for name, _, value, _, _ in writes}, args.json)
        else:
            modes = {"run": ProcessorMode.RUN, "program": ProcessorMode.PROGRAM, "test": ProcessorMode.TEST_CONTINUOUS}
            if args.mode not in modes:
                raise InvalidRequest(f"DF1 mode: choose run, program or test, not {args.mode}")
            await driver.execute(SetProcessorMode(modes[args.mode]), f"mode {args.mode}", write=True)
            print_result({"mode": args.mode}, args.json)
    return 0
