"""The diagnostic commands of the CLI for SLC 100/150 links (``--protocol slc-ascii``): probe, read,
write, mode, upload, download.

Program backup file (``upload`` writes it, ``download`` reads it): JSON, one object::

    {"format": "slc-gateway-program/1", "controller": "SLC150", "device_type": 21, "frn": 47,
     "blocks": ["<30 hex digits>", ...],            # every block in order, 15 bytes each
     "sha256": "<hex digest of the concatenated block bytes>"}

``download`` refuses a file whose controller differs from the connected one, a file with the
wrong block count, a bad checksum, or an unknown format.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import re
import sys
from pathlib import Path
from typing import Any

from gateway.errors import GatewayError, InvalidRequest, WriteOutcomeUnknown
from gateway.kinds.contract import ToolHints
from gateway.kinds.slc_ascii.config import SLC_ASCII_DEFAULTS
from gateway.kinds.slc_ascii.driver import SlcAsciiDriver
from gateway.line_driver import OpenStream
from gateway.protocols.slc_ascii import commands as cmds
from gateway.protocols.slc_ascii.commands import ControllerType, Mode
from gateway.protocols.slc_ascii.memory_map import Item, parse_item
from gateway.protocols.slc_ascii.transaction import MAX_RESYNCS
from gateway.tools_common import print_result, resolve_retries
from gateway.transport import LOW_7_BITS, SerialSettings

__all__ = [
    "PROGRAM_FORMAT",
    "SLC_ASCII_TOOL_HINTS",
    "add_slc_ascii_options",
    "add_slc_ascii_sim_options",
    "load_program_file",
    "run_slc_ascii_tool",
    "save_program_file",
]

PROGRAM_FORMAT = "slc-gateway-program/1"
#: Seconds a command-line write may take to reach its verdict.
WRITE_BUDGET = 10.0
_MODES = {"run": Mode.RUN, "program": Mode.PROGRAM, "test": Mode.CONTINUOUS_TEST, "save": Mode.SAVE_TO_EEPROM}

#: SLC 100/150 ASCII replies: ":" data / acknowledge or ";" status lines ending in CR.
_ASCII_REPLY = re.compile(rb"[:;][0-9A-Fa-f?]{1,80}\r")


def _looks_like_ascii(received: bytes) -> bool:
    # A 7E1 talker read at 8N1 arrives with its parity bit as bit 7.
    return _ASCII_REPLY.search(received.translate(LOW_7_BITS)) is not None


SLC_ASCII_TOOL_HINTS = ToolHints(
    looks_like=_looks_like_ascii,
    wire="the SLC 100/150 ASCII protocol (':'/';' lines):",
    controllers="an SLC 100 or 150",
    check="the cable, baud rate and parity (SLC 100/150: 9600 7E1)",
)


def add_slc_ascii_options(parser: argparse.ArgumentParser) -> None:
    """The options only SLC 100/150 commands take."""
    parser.add_argument(
        "--bytesize", type=int, choices=(7, 8),
        help="slc-ascii: data bits (default 7); with 8 and --parity N the even parity bit is sent as bit 7, "
        "the same bits on the wire as 7E1, for ports that cannot do 7E1 (e.g. a pseudo-terminal)",
    )
    parser.add_argument("--parity", choices=("E", "O", "N"), help="slc-ascii: parity (default E)")


async def run_slc_ascii_tool(command: str, args: argparse.Namespace, opener: OpenStream) -> int:
    defaults = SLC_ASCII_DEFAULTS
    settings = SerialSettings(
        args.baudrate or defaults.baudrate,
        args.bytesize or defaults.bytesize,
        args.parity or defaults.parity,
        defaults.stopbits,
    )
    # Validate everything the user typed before opening the port.
    if command == "read":
        items = [parse_item(text) for text in args.items]
    elif command == "write":
        writes = [_parse_assignment(text) for text in args.assignments]
    driver = SlcAsciiDriver(
        args.url,
        settings=settings,
        timeout=args.timeout or defaults.timeout,
        retries=resolve_retries(command, args.retries),
        # A probe asks "is an SLC 100/150 there?": a silent line fails at the first resync, so a
        # wrong guess fails in a second; a controller that answers garbled gets a few more.
        max_resyncs=3 if command == "probe" else MAX_RESYNCS,
        # a write asks again (;Z, a resync after proof) for as long as the budget lasts: on a
        # line that answers at all it gets its verdict, not "outcome unknown" after 3 ;Z
        write_budget=WRITE_BUDGET,
        trace=args.trace,
        reconnect_min=60.0,
        opener=opener,
    )
    async with driver:
        if command == "probe":
            info = await driver.probe()
            kind = info.controller.name if info.controller else f"unknown (device type 0x{info.device_type:02X})"
            print_result({"controller": kind, "device_type": info.device_type, "frn": info.frn}, args.json)
        elif command == "read":
            result: dict[str, Any] = {}
            for text, item in zip(args.items, items, strict=True):
                result[text] = item.decode(await driver.read(item.read_address, item.read_count))
            print_result(result, args.json)
        elif command == "write":
            for item_text, item, value in writes:
                if item.read_modify_write:
                    assert item.bit is not None
                    if value not in (0, 1):
                        raise InvalidRequest(f"{item_text}: a bit takes 0 or 1, not {value}")
                    if not item.writable:
                        cmds.write_item_bit(item, 0, bool(value))  # raises the read-only message
                    await driver.update_byte(item.read_address, item.bit, bool(value))
                else:
                    await _write_and_settle(driver, item_text, item, value)
            print_result({text: value for text, _, value in writes}, args.json)
        elif command == "mode":
            await driver.set_mode(_MODES[args.mode])
            print_result({"mode": args.mode}, args.json)
        elif command == "upload":
            info = await driver.probe()
            controller = _known(info.controller, info.device_type)
            program = await driver.upload_program(controller)
            save_program_file(args.file, controller, info.frn, program)
            print_result(_transfer_summary(args.file, controller), args.json)
        elif command == "download":
            info = await driver.probe()
            controller = _known(info.controller, info.device_type)
            program = load_program_file(args.file, controller)
            await driver.download_program(controller, program)
            print_result(_transfer_summary(args.file, controller), args.json)
        else:
            raise InvalidRequest(f"unknown command {command}")
    return 0


def _transfer_summary(path: Path, controller: ControllerType) -> dict[str, Any]:
    return {"file": str(path), "controller": controller.name, "blocks": controller.block_count}


def _parse_assignment(text: str) -> tuple[str, Any, int]:
    name, sep, value_text = text.partition("=")
    if not sep or not name or not value_text:
        raise InvalidRequest(f"{text!r}: expected ITEM=VALUE, e.g. 905.PRE=1234 or 701=1")
    item = parse_item(name)
    try:
        value = int(value_text, 0)
    except ValueError as exc:
        raise InvalidRequest(f"{text!r}: {value_text!r} is not a whole number") from exc
    if not item.read_modify_write:
        cmds.write_item(item, value)  # validate now, before the port is opened
    return name, item, value


def _known(controller: ControllerType | None, device_type: int) -> ControllerType:
    if controller is None:
        raise GatewayError(f"unknown controller type 0x{device_type:02X}: program transfer needs an SLC 100 or 150")
    return controller


def save_program_file(path: Path, controller: ControllerType, frn: int, program: bytes) -> None:
    blocks = [program[i : i + cmds.BLOCK_SIZE].hex().upper() for i in range(0, len(program), cmds.BLOCK_SIZE)]
    document = {
        "format": PROGRAM_FORMAT,
        "controller": controller.name,
        "device_type": controller.device_type,
        "frn": frn,
        "blocks": blocks,
        "sha256": hashlib.sha256(program).hexdigest(),
    }
    path.write_text(json.dumps(document, indent=1) + "\n", encoding="utf-8")


def load_program_file(path: Path, controller: ControllerType) -> bytes:
    """The program bytes of a backup file, checked against ``controller``."""
    try:
        document = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InvalidRequest(f"{path}: not a program backup file ({exc})") from exc
    if not isinstance(document, dict) or document.get("format") != PROGRAM_FORMAT:
        raise InvalidRequest(f"{path}: not a {PROGRAM_FORMAT} file")
    if document.get("controller") != controller.name:
        raise InvalidRequest(
            f"{path}: the program is for an {document.get('controller')}, the controller is an {controller.name}"
        )
    blocks = document.get("blocks")
    if not isinstance(blocks, list) or len(blocks) != controller.block_count:
        raise InvalidRequest(f"{path}: expected {controller.block_count} blocks")
    try:
        program = b"".join(bytes.fromhex(block) for block in blocks)
    except (TypeError, ValueError) as exc:
        raise InvalidRequest(f"{path}: a block is not hex") from exc
    if len(program) != controller.block_count * cmds.BLOCK_SIZE:
        raise InvalidRequest(f"{path}: every block must be {cmds.BLOCK_SIZE} bytes")
    if hashlib.sha256(program).hexdigest() != document.get("sha256"):
        raise InvalidRequest(f"{path}: checksum mismatch: the file is damaged")
    return program


def add_slc_ascii_sim_options(parser: argparse.ArgumentParser) -> None:
    """The fault options of the SLC 100/150 simulators (``slc-gateway simulate``)."""
    parser.add_argument("--power-cycle-every", type=int, default=0, metavar="N",
                        help="slc100/150: power-cycle every N commands")
    parser.add_argument("--fault-every", type=int, default=0, metavar="N", help="slc100/150: emit ;T every N commands")


#: writes sent again after a read-back proved an earlier one did not apply
WRITE_TRIES = 3


async def _write_and_settle(driver: SlcAsciiDriver, text: str, item: Item, value: int) -> None:
    """Write ``item``; a write whose outcome is unknown is settled by reading the item back.

    The line keeps order and the controller runs a command before it answers the next, so a read
    sent after the write's last copy sees the write if it ran.  The value read back: the written
    one -> done; another -> the write did not apply, and it is sent again (as a new write).  The
    value is absolute, so a write that ran and was then changed by the ladder before the read-back
    is written again with the same value: the state the user asked for, never a sum.
    """
    for attempt in range(1, WRITE_TRIES + 1):
        try:
            await driver.execute(cmds.write_item(item, value))
            return
        except WriteOutcomeUnknown:
            found = item.decode(await driver.read(item.read_address, item.read_count))
            if found == value:
                print(f"slc-gateway write: {text}: outcome unknown, read back {found}: applied", file=sys.stderr)
                return
            if attempt == WRITE_TRIES:
                raise
            print(f"slc-gateway write: {text}: outcome unknown, read back {found}: not applied; sending it again",
                  file=sys.stderr)
