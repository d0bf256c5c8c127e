"""SLC 100/150 ASCII protocol commands: builders, reply-body parsers and ``;T`` error bits.

Sans-I/O: this module builds validated :class:`Command` values and parses the hex text of data
replies; ``framing`` turns a command into ``#<count><code><params>[ID][CRC]<cr>`` and hands back
the hex text between ``:`` and the ID ("Format of Transmission").

Commands ("Specific Commands")::

    code  wire format                          builder                   reply
    00    #0100                                 upload_block()            :<block><15 bytes>
    01    #1101 <block> <15 bytes>              download_block()          ;R
    02    #0502 <count 0001|0002> <address>     read_bytes()              :<count><address><data>
    03    #0503 <address> <word>                write_word()              ;R
    03    #0403 <address> <byte>                write_byte()              ;R
    03    #04030101 <mode>                      set_mode()                ;R
    04    #0404 <rung> <step>                   read_sequencer_preset()   :02 <user address> <word>
    05    #0305 <rung>                          read_reset_accumulator()  :02 <user address> <word>
    06    #0606 <rung> <step> <preset>          write_sequencer_preset()  ;R
    07    #0507 <rung> <accumulator>            write_reset_accumulator() ;R
    08    #0108                                 read_frn()                :021FFE <device type> <FRN>

The byte count is 1 (the code) plus the parameter bytes; words and addresses are MSB first.
Mode selection is the byte write at 0101H, the controller mode byte ("The Memory Map").
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from enum import Enum, IntEnum
from types import MappingProxyType
from typing import NamedTuple

from gateway.errors import ControllerFault, InvalidRequest, ProtocolError
from gateway.protocols.slc_ascii.memory_map import (
    PROTECT_BIT,
    WORD_VALUE_MASK,
    Item,
    ItemKind,
    check_byte_writable,
    check_readable,
    check_word_writable,
)

__all__ = [
    "BLOCK_SIZE",
    "ERROR_BITS",
    "ERROR_DESCRIPTIONS",
    "FRN_ADDRESS",
    "MODE_ADDRESS",
    "Command",
    "CommandCode",
    "ControllerType",
    "ErrorBit",
    "FrnInfo",
    "Mode",
    "Reply",
    "ReplyKind",
    "TimeoutClass",
    "UploadBlock",
    "WordReply",
    "answers",
    "controller_fault",
    "decode_error_bits",
    "download_block",
    "error_description",
    "parse_frn_reply",
    "parse_read_reply",
    "parse_reply",
    "parse_upload_reply",
    "parse_word_reply",
    "read_bytes",
    "read_frn",
    "read_reset_accumulator",
    "read_sequencer_preset",
    "set_mode",
    "upload_block",
    "write_byte",
    "write_item",
    "write_item_bit",
    "write_reset_accumulator",
    "write_sequencer_preset",
    "write_word",
]

BLOCK_SIZE = 15
"""Bytes of program data per upload/download block ("Upload and Download")."""

MODE_ADDRESS = 0x0101
"""Mode selection writes the controller mode byte: ``#0403 0101 <mode>`` ("Mode Selection")."""

FRN_ADDRESS = 0x1FFE
"""Address echoed by the FRN reply ``:021FFE`` ("Read Device FRN ID Tag")."""

VALUE_LIMIT = 10_000
"""Data words must be "less than 2710H (10,000D)" ("Writing Data Words" and following)."""

RUNG_MAX = 0xFFFF
"""Rung numbers are four ASCII hex characters ("Reading Sequencer Preset")."""

STEP_MAX = 0xFF
"""Step numbers are two ASCII hex characters ("Reading Sequencer Preset")."""


class CommandCode(IntEnum):
    """Command code byte ("Specific Commands")."""

    UPLOAD = 0x00
    """``#0100``: upload the next program block ("Upload and Download")."""
    DOWNLOAD = 0x01
    """``#1101``: download one program block ("Upload and Download")."""
    READ = 0x02
    """``#0502``: read 1 or 2 bytes ("Reading Data")."""
    WRITE = 0x03
    """``#0503`` word / ``#0403`` byte / ``#04030101`` mode ("Writing Data Words/Bytes", "Mode Selection")."""
    READ_SEQUENCER_PRESET = 0x04
    """``#0404`` ("Reading Sequencer Preset")."""
    READ_RESET_ACCUMULATOR = 0x05
    """``#0305`` ("Reading Reset Accumulator")."""
    WRITE_SEQUENCER_PRESET = 0x06
    """``#0606`` ("Writing Sequencer Preset")."""
    WRITE_RESET_ACCUMULATOR = 0x07
    """``#0507`` ("Writing Reset Accumulator")."""
    READ_FRN = 0x08
    """``#0108`` ("Read Device FRN ID Tag")."""


class Mode(IntEnum):
    """Data byte of the mode selection command ("Mode Selection - All Modes")."""

    RUN = 0x80
    """80H - Run mode."""
    SAVE_TO_EEPROM = 0x8C
    """8CH - Save to EEPROM mode."""
    CONTINUOUS_TEST = 0x82
    """82H - Continuous test mode."""
    PROGRAM = 0x06
    """06H - Program mode for upload and download."""


class ControllerType(IntEnum):
    """Controller family; the value is the FRN reply's device type code ("Read Device FRN ID Tag")."""

    SLC100 = 0x10
    """"10 for SLC": 7BH program blocks (00H-7AH)."""
    SLC150 = 0x15
    """"15 for SLC 150": A5H program blocks (00H-A4H)."""

    @property
    def device_type(self) -> int:
        """Device type code of the FRN reply."""
        return int(self)

    @property
    def block_count(self) -> int:
        """Number of upload/download blocks: 7BH (SLC 100), A5H (SLC 150) ("Upload and Download")."""
        return 0x7B if self is ControllerType.SLC100 else 0xA5

    @property
    def last_block(self) -> int:
        """Number of the last block (7AH / A4H): 7 preset-table bytes plus 8 bytes of zero fill."""
        return self.block_count - 1

    @property
    def program_bytes(self) -> int:
        """User program size: 1770 (SLC 100) or 2400 (SLC 150) bytes ("The Memory Map")."""
        return 1770 if self is ControllerType.SLC100 else 2400

    @classmethod
    def from_device_type(cls, code: int) -> ControllerType | None:
        """The controller type of a device type code, or ``None`` for a code the manual does not name."""
        try:
            return cls(code)
        except ValueError:
            return None


class ReplyKind(Enum):
    """What a valid answer to a command is ("Specific Commands")."""

    ACK = ";R"
    """``;R [ID] [CRC] <cr>``."""
    DATA = ":"
    """``:<data> [ID] [CRC] <cr>``."""


class TimeoutClass(Enum):
    """Reply time class ("Format of Transmission": "Normally the SLC will respond within 0.3
    seconds to any transmission. The exceptions are edit commands and mode changes")."""

    NORMAL = "normal"
    SLOW = "slow"
    """Mode changes and program upload/download."""


@dataclass(frozen=True, slots=True)
class Command:
    """One validated command: ``#<1 + len(params)> <code> <params>`` ("Format of Transmission").

    Build commands with the functions of this module; they check the manual's rules.
    """

    code: int
    params: bytes
    name: str
    reply: ReplyKind
    timeout_class: TimeoutClass
    is_write: bool

    def __post_init__(self) -> None:
        if isinstance(self.code, bool) or not isinstance(self.code, int) or not 0 <= self.code <= 0xFF:
            raise InvalidRequest(f"command code {self.code!r} is not a byte")
        if not isinstance(self.params, bytes):
            raise InvalidRequest(f"params must be bytes, not {type(self.params).__name__}")
        if self.byte_count > 0xFF:
            raise InvalidRequest(f"byte count {self.byte_count} does not fit two hex characters")
        if not self.name:
            raise InvalidRequest("a command needs a name")

    @property
    def byte_count(self) -> int:
        """The <byte count> field: command code plus parameter bytes."""
        return 1 + len(self.params)


# --------------------------------------------------------------------------------------------------
# Builders


def _check_int(what: str, value: object, low: int, high: int, rule: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise InvalidRequest(f"{what} {value!r} is not an integer")
    if not low <= value <= high:
        raise InvalidRequest(f"{what} {value} is out of range: {rule}")
    return value


def _check_rung(rung: object) -> int:
    return _check_int("rung", rung, 0, RUNG_MAX, "rung numbers are 0-65535 (four hex characters)")


def _check_step(step: object) -> int:
    return _check_int("step", step, 0, STEP_MAX, "step numbers are 0-255 (two hex characters)")


def _word(value: int) -> bytes:
    return value.to_bytes(2, "big")


def read_bytes(address: int, count: int = 1) -> Command:
    """``#0502 <count> <address>``: read 1 or 2 bytes ("Reading Data - Run or Continuous Test Modes").

    Only the start addresses of the "Reading Data" list; every byte read must be readable and no
    ``**`` cell is ever read (see :func:`memory_map.check_readable`).
    """
    check_readable(address, count)
    return Command(
        CommandCode.READ,
        _word(count) + _word(address),
        f"read {count} byte{'s' if count == 2 else ''} at 0x{address:04X}",
        ReplyKind.DATA,
        TimeoutClass.NORMAL,
        is_write=False,
    )


def write_word(address: int, value: int) -> Command:
    """``#0503 <address> <word>`` ("Writing Data Words - Run or Continuous Test Modes").

    Even address in 0000H-003EH (accumulators) or 0040H-007EH (presets); value 0-9999. The
    controller refuses (``;E``) when the word being overwritten is protected (bit 15 set).
    """
    check_word_writable(address)
    _check_int("value", value, 0, VALUE_LIMIT - 1, "data words must be less than 2710H (0-9999)")
    return Command(
        CommandCode.WRITE,
        _word(address) + _word(value),
        f"write word {value} to 0x{address:04X}",
        ReplyKind.ACK,
        TimeoutClass.NORMAL,
        is_write=True,
    )


def write_byte(address: int, value: int) -> Command:
    """``#0403 <address> <byte>``: 00A6H-00B4H only, relays 701-820 ("Writing Data Bytes")."""
    check_byte_writable(address)
    _check_int("value", value, 0, 0xFF, "a data byte is 0-255")
    return Command(
        CommandCode.WRITE,
        _word(address) + bytes([value]),
        f"write byte 0x{value:02X} to 0x{address:04X}",
        ReplyKind.ACK,
        TimeoutClass.NORMAL,
        is_write=True,
    )


def write_item(item: Item, value: int) -> Command:
    """The command that writes ``value`` to ``item`` (not for bits: see :func:`write_item_bit`)."""
    if item.kind in (ItemKind.ACCUMULATOR, ItemKind.PRESET):
        return write_word(item.read_address, value)
    if item.kind is ItemKind.BYTE and item.writable:
        return write_byte(item.read_address, value)
    if item.kind is ItemKind.BIT and item.writable:
        raise InvalidRequest(f"{item.text} is a bit: read byte 0x{item.read_address:04X} and use write_item_bit()")
    raise InvalidRequest(f"{item.text} is read only: {item.write_rule()}")


def write_item_bit(item: Item, current: int, value: bool) -> Command:
    """The byte write that sets bit ``item`` to ``value``, keeping the other bits of ``current``.

    ``current`` is the byte just read at ``item.read_address``. Only relays 701-820 are writable.
    """
    if item.kind is not ItemKind.BIT or item.bit is None:
        raise InvalidRequest(f"{item.text} is not a bit item")
    if not item.writable:
        raise InvalidRequest(f"{item.text} is read only: {item.write_rule()}")
    if isinstance(current, bool) or not isinstance(current, int) or not 0 <= current <= 0xFF:
        raise InvalidRequest(f"current byte {current!r} is not in 0-255")
    mask = 1 << item.bit
    new = current | mask if value else current & ~mask
    return write_byte(item.read_address, new)


def set_mode(mode: Mode) -> Command:
    """``#04030101 <mode>``: select the controller mode ("Mode Selection - All Modes").

    A mode change is slow ("The exceptions are edit commands and mode changes"). Entering
    :attr:`Mode.PROGRAM` during a download clears the user program ("Upload and Download").
    """
    try:
        if isinstance(mode, bool) or not isinstance(mode, int):
            raise ValueError
        mode = Mode(mode)
    except ValueError:
        allowed = ", ".join(f"{m.name} (0x{m.value:02X})" for m in Mode)
        raise InvalidRequest(f"mode {mode!r} is not allowed: the data byte is limited to {allowed}") from None
    return Command(
        CommandCode.WRITE,
        _word(MODE_ADDRESS) + bytes([mode]),
        f"set mode {mode.name} (0x{mode.value:02X})",
        ReplyKind.ACK,
        TimeoutClass.SLOW,
        is_write=True,
    )


def read_frn() -> Command:
    """``#0108``: read the device type and FRN ("Read Device FRN ID Tag - All Modes")."""
    return Command(CommandCode.READ_FRN, b"", "read FRN", ReplyKind.DATA, TimeoutClass.NORMAL, is_write=False)


def upload_block() -> Command:
    """``#0100``: upload the next program block; Program mode only ("Upload and Download").

    The reply carries the block number (see :func:`parse_upload_reply`). Send it once per block,
    in order, until all blocks of the controller type are transferred.
    """
    return Command(
        CommandCode.UPLOAD,
        b"",
        "upload next program block",
        ReplyKind.DATA,
        TimeoutClass.SLOW,
        is_write=False,
    )


def download_block(
    block: int, data: bytes | bytearray | memoryview, *, controller: ControllerType
) -> Command:
    """``#1101 <block> <15 bytes>``: download one program block; Program mode only.

    ``block`` is 00H-7AH (SLC 100) or 00H-A4H (SLC 150), sent in sequential order (the caller keeps
    the order). The last block holds 7 preset-table bytes and 8 bytes of fill that must be zero
    ("User ignores fill on upload and must send zero fill on download").
    """
    if not isinstance(controller, ControllerType):
        raise InvalidRequest(f"controller {controller!r} is not a ControllerType")
    _check_int(
        "block", block, 0, controller.last_block,
        f"{controller.name} blocks are 0x00-0x{controller.last_block:02X}",
    )
    if not isinstance(data, bytes | bytearray | memoryview):
        raise InvalidRequest(f"block data must be bytes, not {type(data).__name__}")
    data = bytes(data)
    if len(data) != BLOCK_SIZE:
        raise InvalidRequest(
            f"block data is {len(data)} bytes: each block carries exactly {BLOCK_SIZE} bytes")
    if block == controller.last_block and any(data[7:]):
        raise InvalidRequest(
            f"block 0x{block:02X} is the last {controller.name} block: "
            "its last 8 bytes are fill and must be zero")
    return Command(
        CommandCode.DOWNLOAD,
        bytes([block]) + data,
        f"download block 0x{block:02X}",
        ReplyKind.ACK,
        TimeoutClass.SLOW,
        is_write=True,
    )


def read_sequencer_preset(rung: int, step: int) -> Command:
    """``#0404 <rung> <step>`` ("Reading Sequencer Preset"); reply: :func:`parse_word_reply`."""
    rung, step = _check_rung(rung), _check_step(step)
    return Command(
        CommandCode.READ_SEQUENCER_PRESET,
        _word(rung) + bytes([step]),
        f"read sequencer preset rung {rung} step {step}",
        ReplyKind.DATA,
        TimeoutClass.NORMAL,
        is_write=False,
    )


def read_reset_accumulator(rung: int) -> Command:
    """``#0305 <rung>`` ("Reading Reset Accumulator"); reply: :func:`parse_word_reply`."""
    rung = _check_rung(rung)
    return Command(
        CommandCode.READ_RESET_ACCUMULATOR,
        _word(rung),
        f"read reset accumulator rung {rung}",
        ReplyKind.DATA,
        TimeoutClass.NORMAL,
        is_write=False,
    )


def write_sequencer_preset(rung: int, step: int, value: int) -> Command:
    """``#0606 <rung> <step> <preset>``: preset 1-9999, "less than 2710H and non-zero"
    ("Writing Sequencer Preset")."""
    rung, step = _check_rung(rung), _check_step(step)
    _check_int(
        "preset", value, 1, VALUE_LIMIT - 1, "a sequencer preset is non-zero and less than 2710H (1-9999)")
    return Command(
        CommandCode.WRITE_SEQUENCER_PRESET,
        _word(rung) + bytes([step]) + _word(value),
        f"write sequencer preset {value} to rung {rung} step {step}",
        ReplyKind.ACK,
        TimeoutClass.NORMAL,
        is_write=True,
    )


def write_reset_accumulator(rung: int, value: int) -> Command:
    """``#0507 <rung> <accumulator>``: value 0-9999, "less than 2710H" ("Writing Reset Accumulator")."""
    rung = _check_rung(rung)
    _check_int("accumulator", value, 0, VALUE_LIMIT - 1, "an accumulator is less than 2710H (0-9999)")
    return Command(
        CommandCode.WRITE_RESET_ACCUMULATOR,
        _word(rung) + _word(value),
        f"write reset accumulator {value} to rung {rung}",
        ReplyKind.ACK,
        TimeoutClass.NORMAL,
        is_write=True,
    )


# --------------------------------------------------------------------------------------------------
# Reply bodies

_HEX = re.compile(r"[0-9A-Fa-f]*")


def _hex_body(body_hex: object, what: str) -> str:
    if not isinstance(body_hex, str):
        raise ProtocolError(f"{what}: body must be hex text, not {type(body_hex).__name__}")
    if not _HEX.fullmatch(body_hex) or len(body_hex) % 2:
        raise ProtocolError(f"{what}: body {body_hex!r} is not an even number of hex digits")
    return body_hex.upper()


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


@dataclass(frozen=True, slots=True)
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
    reply that does not answer ``command`` (or a command that expects ``;R``, not data).
    """
    code, params = command.code, command.params
    if command.reply is not ReplyKind.DATA:
        raise ProtocolError(f"{command.name} is answered by ;R, not by data")
    if code == CommandCode.READ:
        return parse_read_reply(int.from_bytes(params[2:4], "big"), int.from_bytes(params[0:2], "big"), body_hex)
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


# --------------------------------------------------------------------------------------------------
# ;T fault: error bits at 84H and 85H


@dataclass(frozen=True, slots=True)
class ErrorBit:
    """One bit of the error word ("Format of Transmission", format of the error word)."""

    address: int
    bit: int
    number: int
    """The error number displayed by the programmer."""


ERROR_BITS: tuple[ErrorBit, ...] = tuple(
    ErrorBit(address, bit, number)
    for address, numbers in (
        (0x84, (62, 4, 6, 3, 8, 5, 2, 1)),  # bits 7..0
        (0x85, (None, 26, 25, 24, 9, 51, 7, 51)),  # bits 7..0; bit 7 unused
    )
    for bit, number in zip(range(7, -1, -1), numbers, strict=True)
    if number is not None
)
"""The manual's error word table; error 51 has two bits (85H bits 2 and 0)."""

ERROR_DESCRIPTIONS: Mapping[int, str] = MappingProxyType({
    number: f"error {number} (" + ", ".join(
        f"{e.address:02X}H bit {e.bit}" for e in ERROR_BITS if e.number == number) + ")"
    for number in sorted({e.number for e in ERROR_BITS})
})
"""Short description of each error number. The manual names only the number the programmer
displays and its bit, so that is what the description says."""


def error_description(number: int) -> str:
    """Description of an error number, ``"error N"`` for a number not in the table."""
    return ERROR_DESCRIPTIONS.get(number, f"error {number}")


def decode_error_bits(b84: int, b85: int) -> tuple[int, ...]:
    """Error numbers, ascending and without repeats, of the bytes read at 84H and 85H.

    After ``;T`` "the user should read the bytes at addresses 84H and 85H". 85H bit 7 is unused
    and ignored.
    """
    values = {
        0x84: _check_int("byte 84H", b84, 0, 0xFF, "a byte is 0-255"),
        0x85: _check_int("byte 85H", b85, 0, 0xFF, "a byte is 0-255"),
    }
    return tuple(sorted({e.number for e in ERROR_BITS if values[e.address] >> e.bit & 1}))


def controller_fault(b84: int, b85: int) -> ControllerFault:
    """The :class:`ControllerFault` for a ``;T`` whose error bytes 84H and 85H were read."""
    numbers = decode_error_bits(b84, b85)
    reasons: Iterable[str] = (error_description(n) for n in numbers)
    detail = "; ".join(reasons) or "no error bit set"
    return ControllerFault(f"controller fault (84H=0x{b84:02X}, 85H=0x{b85:02X}): {detail}", errors=numbers)
