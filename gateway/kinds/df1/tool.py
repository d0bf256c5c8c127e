"""The diagnostic commands of the CLI for DF1 links (``--protocol df1``): probe, read, write, mode.

Items of an SLC 500 are SLC 500 logical addresses, read and written with the typed logical
commands: ``N7:0`` (signed 16-bit), ``B3:0/3`` (a bit), ``F8:2`` (a float), ``T4:1.ACC``,
``C5:0/DN``, ``I:1.0``, ``S:1/5``; a whole structure (``T4:1``) reads as its three words.

With ``--processor plc5`` items are PLC-5 addresses (``N7:0``, ``B3/5``, ``T4:1.ACC``, ``F8:2``,
octal ``I:010``, elements above 255), read with word range read ``0F 01`` and written with word
range write ``0F 00``; a bit is written with read-modify-write ``0F 26`` (only that bit changes, in
the controller: :mod:`gateway.protocols.df1.plc5_commands`), as the PLC-5 unit does.

``--duplex half --station N`` talks to station N of a half-duplex multi-drop line or radio channel:
a :class:`~gateway.kinds.df1.half.driver.Df1HalfDuplexLine` master with that one station, the commands
through ``line.station(N)`` (the same ``execute`` API as the full-duplex
:class:`~gateway.kinds.df1.full.driver.Df1Driver`).  ``--poll-timeout`` and ``--ack-timeout`` are the line's
answer timers (radio: raise them); ``--timeout`` is from the station's ACK to its reply.
"""

from __future__ import annotations

import argparse
import contextlib
import re
import struct
from collections.abc import AsyncIterator, Callable
from dataclasses import replace
from typing import Any, Protocol

from gateway.errors import InvalidRequest, LinkTimeout
from gateway.frozen import frozen
from gateway.kinds.contract import ToolHints
from gateway.kinds.df1.config import DF1_DEFAULTS
from gateway.kinds.df1.full.driver import Df1Driver
from gateway.kinds.df1.half.driver import Df1HalfDuplexLine, PcccRequestLike
from gateway.kinds.df1.unit import PROCESSORS
from gateway.line_driver import OpenStream
from gateway.protocols.df1.address import SIGNED_FILE_TYPES, FileType, SlcAddress, parse_address
from gateway.protocols.df1.framing import DEFAULT_CHECKSUM, Checksum
from gateway.protocols.df1.half_duplex.events import StationConfig
from gateway.protocols.df1.pccc import (
    DiagnosticStatusInfo,
    PcccReply,
    ProcessorFamily,
    ProcessorMode,
    ProtectedTypedLogicalMaskedWrite,
    ProtectedTypedLogicalRead,
    ProtectedTypedLogicalWrite,
    SetProcessorMode,
)
from gateway.protocols.df1.plc5_address import (
    PLC5_SIGNED,
    PLC5_STRUCTURES,
    AddressError,
    Plc5Address,
    parse_plc5_address,
)
from gateway.protocols.df1.plc5_commands import plc5_bit_write, plc5_read, plc5_write
from gateway.tools_common import print_result, resolve_retries

__all__ = [
    "DF1_TOOL_HINTS",
    "add_df1_options",
    "add_df1_sim_options",
    "decode_plc5_value",
    "decode_value",
    "encode_plc5_write",
    "encode_value",
    "run_df1_tool",
]

#: DF1 link-layer symbols: DLE followed by STX, ETX, ENQ, ACK or NAK (1770-6.5.16, full duplex).
_DLE_FRAMED = re.compile(rb"\x10[\x02\x03\x05\x06\x15]")

DF1_TOOL_HINTS = ToolHints(
    looks_like=lambda received: _DLE_FRAMED.search(received) is not None,
    wire="DF1 (DLE-framed): an SLC 500 or PLC-5?",
    controllers="an SLC 500 or PLC-5",
    check="the cable, baud rate, --checksum, --station and --duplex",
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
    signed = address.file_type in SIGNED_FILE_TYPES
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


def _plc5_address(text: str) -> Plc5Address:
    try:
        return parse_plc5_address(text)
    except AddressError as exc:
        raise InvalidRequest(f"{exc} (--processor plc5 reads PLC-5 addresses)") from exc


def _plc5_word(address: Plc5Address) -> Plc5Address:
    """The word holding a bit address (or the address itself)."""
    return Plc5Address(address.file_type, address.file_number, address.element, address.sub_element)


def decode_plc5_value(address: Plc5Address, data: bytes) -> Any:
    """The value of ``address`` from the bytes a word range read of ``_plc5_word(address)`` returned."""
    if address.bit is not None:
        return bool(int.from_bytes(data[:2], "little") >> address.bit & 1)
    if address.file_type == "F" and address.sub_element is None:
        return struct.unpack("<f", data[:4])[0]  # two words, the low-order word first
    words = [int.from_bytes(data[i : i + 2], "little") for i in range(0, len(data), 2)]
    if len(words) > 1:
        return words
    signed = address.file_type in PLC5_SIGNED
    return words[0] - 0x10000 if signed and words[0] & 0x8000 else words[0]


def encode_plc5_write(address: Plc5Address, text: str) -> PcccRequestLike:
    """The PLC-5 command that writes ``text`` to ``address``: word range write, or RMW for a bit."""
    if address.bit is not None:
        try:
            value = int(text, 0)
        except ValueError as exc:
            raise InvalidRequest(f"{address}={text}: a bit takes 0 or 1") from exc
        if value not in (0, 1):
            raise InvalidRequest(f"{address}={text}: a bit takes 0 or 1")
        return plc5_bit_write(address, bool(value))
    if address.file_type == "F":
        try:
            return plc5_write(address, struct.pack("<f", float(text)))
        except ValueError as exc:
            raise InvalidRequest(f"{address}={text}: not a number") from exc
    if address.file_type in PLC5_STRUCTURES and address.sub_element is None:
        raise InvalidRequest(f"{address}: write a member (.PRE, .ACC ...), not the whole structure")
    try:
        value = int(text, 0)
    except ValueError as exc:
        raise InvalidRequest(f"{address}={text}: not a whole number") from exc
    if not -0x8000 <= value <= 0xFFFF:
        raise InvalidRequest(f"{address}={text}: a word takes -32768..65535")
    return plc5_write(address, (value & 0xFFFF).to_bytes(2, "little"))


@frozen
class _Read:
    text: str
    request: PcccRequestLike
    decode: Callable[[bytes], Any]


@frozen
class _Write:
    text: str
    value: str
    request: PcccRequestLike


def _read_item(text: str, plc5: bool) -> _Read:
    if plc5:
        address = _plc5_address(text)
        return _Read(text, plc5_read(_plc5_word(address)), lambda data: decode_plc5_value(address, data))
    slc = parse_address(text)
    request = ProtectedTypedLogicalRead(slc.file_type, slc.file_number, slc.element, slc.sub_element, slc.byte_count)
    return _Read(text, request, lambda data: decode_value(slc, data))


def _write_item(text: str, plc5: bool) -> _Write:
    name, sep, value = text.partition("=")
    if not sep or not value:
        example = "N7:0=5 or B3/5=1" if plc5 else "N7:0=5 or B3:0/3=1"
        raise InvalidRequest(f"{text!r}: expected ADDRESS=VALUE, e.g. {example}")
    if plc5:
        return _Write(name, value, encode_plc5_write(_plc5_address(name), value))
    a = parse_address(name)
    data, mask = encode_value(a, value)
    if mask is None:
        return _Write(name, value, ProtectedTypedLogicalWrite(a.file_type, a.file_number, a.element, a.sub_element,
                                                              data))
    return _Write(name, value, ProtectedTypedLogicalMaskedWrite(a.file_type, a.file_number, a.element,
                                                                a.sub_element, mask, data))


class _Target(Protocol):
    """What the commands use: ``Df1Driver``, or a station of a half-duplex line (``Df1Station``)."""

    async def execute(self, request: Any, name: str = "") -> PcccReply: ...

    async def probe(self) -> DiagnosticStatusInfo: ...


def add_df1_options(parser: argparse.ArgumentParser) -> None:
    """The options only DF1 commands take."""
    parser.add_argument("--station", type=int, default=1, help="df1: destination node (default 1)")
    parser.add_argument("--source", type=int, default=0, help="df1: our node (default 0)")
    parser.add_argument("--checksum", choices=("bcc", "crc"), default=DEFAULT_CHECKSUM.value,
                        help=f"df1: bcc or crc (default {DEFAULT_CHECKSUM.value})")
    parser.add_argument("--processor", default="slc5/04", choices=tuple(PROCESSORS),
                        help="df1: processor family (default slc5/04; plc5: PLC-5 addresses, word range commands)")
    parser.add_argument("--duplex", choices=("full", "half"), default="full",
                        help="df1: full (point to point, default) or half (a station of a multi-drop line or "
                             "radio channel, polled by us)")
    parser.add_argument("--poll-timeout", type=float, default=0.5, metavar="S",
                        help="df1 half duplex: wait for the answer to a poll (default 0.5)")
    parser.add_argument("--ack-timeout", type=float, default=0.5, metavar="S",
                        help="df1 half duplex: wait for the DLE ACK of a command (default 0.5)")


async def run_df1_tool(command: str, args: argparse.Namespace, opener: OpenStream) -> int:
    if args.processor not in PROCESSORS:
        raise InvalidRequest(f"--processor {args.processor}: choose from {', '.join(PROCESSORS)}")
    plc5 = PROCESSORS[args.processor] is ProcessorFamily.PLC5
    reads: list[_Read] = []
    writes: list[_Write] = []
    if command == "read":
        reads = [_read_item(text, plc5) for text in args.items]
    elif command == "write":
        writes = [_write_item(text, plc5) for text in args.assignments]
    elif command == "mode":
        if plc5:
            raise InvalidRequest("mode: a PLC-5 has no SLC change-mode command (0F 80); "
                                 "use the keyswitch or the programming software")
    elif command != "probe":
        raise InvalidRequest(f"{command} is not available for DF1 links")
    async with _open_target(command, args, opener) as target:
        if command == "probe":
            info = await target.probe()
            family = info.family
            print_result({
                "processor": family.value if family else f"unknown (type 0x{info.processor_type or 0:02X})",
                "catalog": info.catalog,
                "series": info.series,
                "frn": info.frn,
            }, args.json)
        elif command == "read":
            result: dict[str, Any] = {}
            for item in reads:
                reply = await target.execute(item.request, f"read {item.text}")
                result[item.text] = item.decode(reply.data)
            print_result(result, args.json)
        elif command == "write":
            for write in writes:
                await target.execute(write.request, f"write {write.text}")
            print_result({write.text: write.value for write in writes}, args.json)
        else:
            modes = {"run": ProcessorMode.RUN, "program": ProcessorMode.PROGRAM, "test": ProcessorMode.TEST_CONTINUOUS}
            if args.mode not in modes:
                raise InvalidRequest(f"DF1 mode: choose run, program or test, not {args.mode}")
            await target.execute(SetProcessorMode(modes[args.mode]), f"mode {args.mode}")
            print_result({"mode": args.mode}, args.json)
    return 0


@contextlib.asynccontextmanager
async def _open_target(command: str, args: argparse.Namespace, opener: OpenStream) -> AsyncIterator[_Target]:
    """The full-duplex driver, or station ``--station`` of a half-duplex line master (``--duplex half``)."""
    settings = DF1_DEFAULTS.settings
    if args.baudrate:
        settings = replace(settings, baudrate=args.baudrate)
    checksum = Checksum.CRC if args.checksum == "crc" else Checksum.BCC
    timeout = args.timeout or DF1_DEFAULTS.timeout
    retries = resolve_retries(command, args.retries)
    if getattr(args, "duplex", "full") != "half":
        driver = Df1Driver(
            args.url, settings=settings, checksum=checksum, station=args.station, source=args.source,
            family=PROCESSORS[args.processor], timeout=timeout, retries=retries, trace=args.trace,
            reconnect_min=60.0, opener=opener,
        )
        async with driver:
            yield driver
        return
    if args.station == args.source:
        raise InvalidRequest(f"--station {args.station} is our own address (--source): give another station")
    try:
        station = StationConfig(args.station, poll_timeout=args.poll_timeout, reply_timeout=timeout)
        line = Df1HalfDuplexLine(
            args.url, [station], settings=settings, checksum=checksum, source=args.source,
            ack_timeout=args.ack_timeout, retries=retries, trace=args.trace, reconnect_min=60.0,
            reconnect_max=60.0, opener=opener,
        )
    except ValueError as exc:
        raise InvalidRequest(f"--duplex half: {exc}") from exc
    await line.start()
    try:
        yield line.station(args.station)
    except LinkTimeout as exc:
        raise _half_duplex_timeout(line, args.station, exc) from exc
    finally:
        await line.close()


def _half_duplex_timeout(line: Df1HalfDuplexLine, station: int, exc: LinkTimeout) -> LinkTimeout:
    """The station's failure in words for a one-shot command (the line's own speaks of slow polls)."""
    check = ("check its power and cable, --station, --checksum (bcc or crc), --baudrate, and on a radio or "
             "a slow modem --poll-timeout and --ack-timeout")
    core = line.core
    if core is not None and not core.is_active(station):
        return LinkTimeout(f"station {station} does not answer on {line.url}: {check}")
    return LinkTimeout(f"station {station} does not answer on {line.url} ({exc}): {check}")


def add_df1_sim_options(parser: argparse.ArgumentParser) -> None:
    """The fault options and line settings of the DF1 simulators (``slc-gateway simulate``)."""
    parser.add_argument("--withhold-ack", type=int, default=0, metavar="N", help="df1: withhold 1 in N ACKs")
    parser.add_argument("--duplicate", type=int, default=0, metavar="N", help="df1: send 1 in N replies twice")
    parser.add_argument("--noise", type=int, default=0, metavar="N", help="df1: garbage between frames, 1 in N")
    parser.add_argument("--checksum", choices=("bcc", "crc"), default=DEFAULT_CHECKSUM.value, help="df1: bcc or crc")
    parser.add_argument("--station", type=int, default=1, help="df1: our node number (default 1)")
