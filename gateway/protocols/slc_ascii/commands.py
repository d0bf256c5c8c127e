"""SLC 100/150 ASCII protocol commands: the builders of validated :class:`Command` values.

Sans-I/O.  The command values themselves are in :mod:`command_types`, the parsers of data reply
bodies in :mod:`replies` and the ``;T`` error bits in :mod:`error_bits`; this module names them
all, so ``commands`` is the one import for callers.  ``framing`` turns a command into
``#<count><code><params>[ID][CRC]<cr>`` and hands back the hex text between ``:`` and the ID
("Format of Transmission").

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

from typing import Final

from gateway.errors import InvalidRequest
from gateway.protocols.slc_ascii.command_types import (
    BLOCK_SIZE,
    Command,
    CommandCode,
    ControllerType,
    Mode,
    ReplyKind,
    TimeoutClass,
    check_int,
)
from gateway.protocols.slc_ascii.error_bits import (
    ERROR_BITS,
    ERROR_DESCRIPTIONS,
    ErrorBit,
    controller_fault,
    decode_error_bits,
    error_description,
)
from gateway.protocols.slc_ascii.memory_map import (
    MODE_ADDRESS,
    Item,
    ItemKind,
    check_byte_writable,
    check_readable,
    check_word_writable,
)
from gateway.protocols.slc_ascii.replies import (
    FRN_ADDRESS,
    FrnInfo,
    Reply,
    UploadBlock,
    WordReply,
    answers,
    parse_frn_reply,
    parse_read_reply,
    parse_reply,
    parse_upload_reply,
    parse_word_reply,
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


VALUE_LIMIT = 10_000
"""Data words must be "less than 2710H (10,000D)" ("Writing Data Words" and following)."""

RUNG_MAX = 0xFFFF
"""Rung numbers are four ASCII hex characters ("Reading Sequencer Preset")."""

STEP_MAX = 0xFF
"""Step numbers are two ASCII hex characters ("Reading Sequencer Preset")."""


def _check_rung(rung: object) -> int:
    return check_int("rung", rung, 0, RUNG_MAX, "rung numbers are 0-65535 (four hex characters)")


def _check_step(step: object) -> int:
    return check_int("step", step, 0, STEP_MAX, "step numbers are 0-255 (two hex characters)")


def _word(value: int) -> bytes:
    return value.to_bytes(2, "big")


#: The codes of the commands that change the controller, each answered with ``;R``; every other
#: command reads and is answered with data ("Specific Commands").
_WRITE_CODES: Final = frozenset({
    CommandCode.DOWNLOAD, CommandCode.WRITE, CommandCode.WRITE_SEQUENCER_PRESET, CommandCode.WRITE_RESET_ACCUMULATOR,
})


def _command(code: CommandCode, params: bytes, name: str, timeout_class: TimeoutClass = TimeoutClass.NORMAL) -> Command:
    """Command ``code`` with ``params``: a write is answered ``;R``, a read with data."""
    return Command(code, params, name, ReplyKind.ACK if code in _WRITE_CODES else ReplyKind.DATA, timeout_class)


def read_bytes(address: int, count: int = 1) -> Command:
    """``#0502 <count> <address>``: read 1 or 2 bytes ("Reading Data - Run or Continuous Test Modes").

    Only the start addresses of the "Reading Data" list; every byte read must be readable and no
    ``**`` cell is ever read (see :func:`memory_map.check_readable`).
    """
    check_readable(address, count)
    return _command(
        CommandCode.READ,
        _word(count) + _word(address),
        f"read {count} byte{'s' if count == 2 else ''} at 0x{address:04X}",
    )


def write_word(address: int, value: int) -> Command:
    """``#0503 <address> <word>`` ("Writing Data Words - Run or Continuous Test Modes").

    Even address in 0000H-003EH (accumulators) or 0040H-007EH (presets); value 0-9999. The
    controller refuses (``;E``) when the word being overwritten is protected (bit 15 set).
    """
    check_word_writable(address)
    check_int("value", value, 0, VALUE_LIMIT - 1, "data words must be less than 2710H (0-9999)")
    return _command(CommandCode.WRITE, _word(address) + _word(value), f"write word {value} to 0x{address:04X}")


def write_byte(address: int, value: int) -> Command:
    """``#0403 <address> <byte>``: 00A6H-00B4H only, relays 701-820 ("Writing Data Bytes")."""
    check_byte_writable(address)
    check_int("value", value, 0, 0xFF, "a data byte is 0-255")
    return _command(CommandCode.WRITE, _word(address) + bytes([value]), f"write byte 0x{value:02X} to 0x{address:04X}")


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
    return _command(
        CommandCode.WRITE,
        _word(MODE_ADDRESS) + bytes([mode]),
        f"set mode {mode.name} (0x{mode.value:02X})",
        TimeoutClass.SLOW,
    )


def read_frn() -> Command:
    """``#0108``: read the device type and FRN ("Read Device FRN ID Tag - All Modes")."""
    return _command(CommandCode.READ_FRN, b"", "read FRN")


def upload_block() -> Command:
    """``#0100``: upload the next program block; Program mode only ("Upload and Download").

    The reply carries the block number (see :func:`parse_upload_reply`). Send it once per block,
    in order, until all blocks of the controller type are transferred.
    """
    return _command(
        CommandCode.UPLOAD,
        b"",
        "upload next program block",
        TimeoutClass.SLOW,
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
    check_int(
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
    return _command(CommandCode.DOWNLOAD, bytes([block]) + data, f"download block 0x{block:02X}", TimeoutClass.SLOW)


def read_sequencer_preset(rung: int, step: int) -> Command:
    """``#0404 <rung> <step>`` ("Reading Sequencer Preset"); reply: :func:`parse_word_reply`."""
    rung, step = _check_rung(rung), _check_step(step)
    return _command(
        CommandCode.READ_SEQUENCER_PRESET,
        _word(rung) + bytes([step]),
        f"read sequencer preset rung {rung} step {step}",
    )


def read_reset_accumulator(rung: int) -> Command:
    """``#0305 <rung>`` ("Reading Reset Accumulator"); reply: :func:`parse_word_reply`."""
    rung = _check_rung(rung)
    return _command(CommandCode.READ_RESET_ACCUMULATOR, _word(rung), f"read reset accumulator rung {rung}")


def write_sequencer_preset(rung: int, step: int, value: int) -> Command:
    """``#0606 <rung> <step> <preset>``: preset 1-9999, "less than 2710H and non-zero"
    ("Writing Sequencer Preset")."""
    rung, step = _check_rung(rung), _check_step(step)
    check_int(
        "preset", value, 1, VALUE_LIMIT - 1,
        "a sequencer preset is non-zero and less than 2710H (1-9999)")
    return _command(
        CommandCode.WRITE_SEQUENCER_PRESET,
        _word(rung) + bytes([step]) + _word(value),
        f"write sequencer preset {value} to rung {rung} step {step}",
    )


def write_reset_accumulator(rung: int, value: int) -> Command:
    """``#0507 <rung> <accumulator>``: value 0-9999, "less than 2710H" ("Writing Reset Accumulator")."""
    rung = _check_rung(rung)
    check_int(
        "accumulator", value, 0, VALUE_LIMIT - 1,
        "an accumulator is less than 2710H (0-9999)")
    return _command(
        CommandCode.WRITE_RESET_ACCUMULATOR,
        _word(rung) + _word(value),
        f"write reset accumulator {value} to rung {rung}",
    )
