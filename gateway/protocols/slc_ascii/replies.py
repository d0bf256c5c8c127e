"""SLC 100/150 ASCII data replies: the parser of each command's reply body ("Specific Commands").

``framing`` hands back the hex text between ``:`` and the ID; these functions turn it into
values.  :func:`parse_reply` is the one place that decides whether a data reply answers a
command.
"""

from __future__ import annotations

import re
from typing import NamedTuple

from gateway.errors import InvalidRequest, ProtocolError
from gateway.frozen import frozen
from gateway.protocols.slc_ascii.command_types import BLOCK_SIZE, Command, CommandCode, ControllerType, ReplyKind
from gateway.protocols.slc_ascii.memory_map import PROTECT_BIT, WORD_VALUE_MASK, check_readable

__all__ = [
    "FRN_ADDRESS",
    "FrnInfo",
    "Reply",
    "UploadBlock",
    "WordReply",
    "answers",
    "parse_frn_reply",
    "parse_read_reply",
    "parse_reply",
    "parse_upload_reply",
    "parse_word_reply",
]

FRN_ADDRESS = 0x1FFE
"""Address echoed by the FRN reply ``:021FFE`` ("Read Device FRN ID Tag")."""

_HEX = re.compile(r"[0-9A-Fa-f]*")


def _hex_body(body_hex: object, what: str) -> str:
    if not isinstance(body_hex, str):
        raise ProtocolError(f"{what}: body must be hex text, not {type(body_hex).__name__}")
    if not _HEX.fullmatch(body_hex) or len(body_hex) % 2:
        raise ProtocolError(f"{what}: body {body_hex!r} is not an even number of hex digits")
    return body_hex


def _split_data_reply(body_hex: object, what: str) -> tuple[int, int, bytes]:
    """``<count><address><data>`` with a 2- or 4-digit count -> (count, address, data).

    The two layouts never both fit one text: with a 2-digit count c the text has 6 + 2c digits;
    read as 4 digits the count would be at least 256c and need 8 + 512c digits.
    """
    text = _hex_body(body_hex, what)
    for digits in (2, 4):
        if len(text) >= digits + 4:
            count = int(text[:digits], 16)
            if len(text) == digits + 4 + 2 * count:
                return count, int(text[digits:digits + 4], 16), bytes.fromhex(text[digits + 4:])
    raise ProtocolError(
        f"{what}: body {text!r} is not <count><address><data> with a 2- or 4-digit byte count")


def parse_read_reply(cmd_address: int, count: int, body_hex: str) -> bytes:
    """The data bytes of the reply to ``read_bytes(cmd_address, count)`` ("Reading Data").

    Body: ``<number of bytes> <address> <data byte(s)>``; the count may have 2 or 4 digits.
    Raises :class:`ProtocolError` unless the reply echoes the requested count and address.
    """
    check_readable(cmd_address, count)
    what = f"reply to read {count} at 0x{cmd_address:04X}"
    got_count, got_address, data = _split_data_reply(body_hex, what)
    if got_count != count or got_address != cmd_address:
        raise ProtocolError(f"{what}: reply echoes {got_count} byte(s) at 0x{got_address:04X}")
    return data


@frozen
class FrnInfo:
    """Answer to ``#0108`` ("Read Device FRN ID Tag")."""

    device_type: int
    """Device type byte, e.g. 0x10 (SLC 100) or 0x15 (SLC 150)."""
    frn: int
    """FRN release number: the two characters read as decimal ("05 for FRN 5; 47 for FRN 47");
    if they are not decimal digits, the byte's value."""
    controller: ControllerType | None
    """The controller type of ``device_type``; ``None`` for a code the manual does not name."""
    frn_code: int
    """The FRN byte as sent."""


def parse_frn_reply(body_hex: str) -> FrnInfo:
    """Parse ``021FFE <device type> <FRN #>`` ("Read Device FRN ID Tag"); 2- or 4-digit count."""
    what = "FRN reply"
    count, address, data = _split_data_reply(body_hex, what)
    if count != 2 or address != FRN_ADDRESS:
        raise ProtocolError(
            f"{what}: expected 2 bytes at 0x{FRN_ADDRESS:04X}, got {count} at 0x{address:04X}")
    device_type, frn_code = data
    digits = f"{frn_code:02X}"
    frn = int(digits) if digits.isdigit() else frn_code
    return FrnInfo(device_type, frn, ControllerType.from_device_type(device_type), frn_code)


class UploadBlock(NamedTuple):
    """One uploaded program block ("Upload and Download")."""

    block: int
    data: bytes
    """15 bytes; in the last block the final 8 are fill, to be ignored."""


def parse_upload_reply(body_hex: str, *, controller: ControllerType | None = None) -> UploadBlock:
    """Parse ``<block #> <15 bytes>`` (the answer to ``#0100``, "Upload and Download").

    With ``controller``, the block number is checked against its block count.
    """
    what = "upload reply"
    text = _hex_body(body_hex, what)
    if len(text) != 2 * (1 + BLOCK_SIZE):
        raise ProtocolError(f"{what}: body has {len(text)} hex digits, expected {2 * (1 + BLOCK_SIZE)}")
    raw = bytes.fromhex(text)
    block = raw[0]
    if controller is not None and block > controller.last_block:
        raise ProtocolError(
            f"{what}: block 0x{block:02X} is beyond the last {controller.name} block "
            f"0x{controller.last_block:02X}")
    return UploadBlock(block, raw[1:])


class WordReply(NamedTuple):
    """Answer to read sequencer preset / read reset accumulator: ``:02 <user address> <word>``."""

    user_address: int
    """The user address field as sent (hex-coded binary, "All numbers are in hexadecimal coded
    binary format")."""
    value: int
    """The word with the protect bit (bit 7 of the MSB) masked out."""
    protected: bool
    """The protect bit."""


def parse_word_reply(body_hex: str) -> WordReply:
    """Parse ``02 <user address> <word>`` ("Reading Sequencer Preset", "Reading Reset Accumulator").

    The count may have 2 or 4 digits. Bit 7 of the MSB is the protect bit and is masked out of
    ``value`` as both sections' notes require.
    """
    what = "word reply"
    count, user_address, data = _split_data_reply(body_hex, what)
    if count != 2:
        raise ProtocolError(f"{what}: expected a 2-byte word, got {count} byte(s)")
    word = int.from_bytes(data, "big")
    return WordReply(user_address, word & WORD_VALUE_MASK, bool(word & PROTECT_BIT))


Reply = bytes | FrnInfo | UploadBlock | WordReply


def parse_reply(command: Command, body_hex: str) -> Reply:
    """The data reply ``body_hex`` to ``command``, parsed by that command's one parser.

    The single place deciding whether a data reply answers a command: the transaction core takes
    a reply as the answer exactly when this parses it.  Raises :class:`ProtocolError` for a
    reply that does not answer ``command`` (or a command that expects ``;R``, not data), and
    :class:`InvalidRequest` for a hand-built read that :func:`read_bytes` would not build (its
    parameters not a 2-byte count and a 2-byte address, or a range that is not readable).
    """
    code, params = command.code, command.params
    if command.reply is not ReplyKind.DATA:
        raise ProtocolError(f"{command.name} is answered by ;R, not by data")
    if code == CommandCode.READ:
        if len(params) != 4:
            raise InvalidRequest(f"{command.name}: a read's parameters are 4 bytes (count, address), not {len(params)}")
        return parse_read_reply(int.from_bytes(params[2:], "big"), int.from_bytes(params[:2], "big"), body_hex)
    if code == CommandCode.READ_FRN:
        return parse_frn_reply(body_hex)
    if code == CommandCode.UPLOAD:
        return parse_upload_reply(body_hex)
    if code in (CommandCode.READ_SEQUENCER_PRESET, CommandCode.READ_RESET_ACCUMULATOR):
        return parse_word_reply(body_hex)
    raise ProtocolError(f"{command.name}: no data reply is defined")


def answers(command: Command, body_hex: str) -> bool:
    """Whether the data reply ``body_hex`` answers ``command`` (:func:`parse_reply` parses it)."""
    try:
        parse_reply(command, body_hex)
    except ProtocolError:
        return False
    return True
