"""SLC 100/150 ASCII command values: codes, modes, controller types and the :class:`Command` itself.

The builders that make checked commands are in :mod:`commands`; the parsers of their data
replies in :mod:`replies` ("Specific Commands").
"""

from __future__ import annotations

from enum import Enum, IntEnum

from gateway.errors import InvalidRequest
from gateway.frozen import frozen

__all__ = [
    "BLOCK_SIZE",
    "Command",
    "CommandCode",
    "ControllerType",
    "Mode",
    "ReplyKind",
    "TimeoutClass",
    "check_int",
]

BLOCK_SIZE = 15
"""Bytes of program data per upload/download block ("Upload and Download")."""


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


@frozen
class Command:
    """One validated command: ``#<1 + len(params)> <code> <params>`` ("Format of Transmission").

    Build commands with the functions of this module; they check the manual's rules.
    """

    code: int
    params: bytes
    name: str
    reply: ReplyKind
    timeout_class: TimeoutClass

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

    @property
    def is_write(self) -> bool:
        """Whether it changes the controller: a write is answered ``;R``, a read with data
        ("Specific Commands"); the reply is the one place this is stated."""
        return self.reply is ReplyKind.ACK

    @property
    def repeatable(self) -> bool:
        """Whether sending it twice does what sending it once does: not a write, and not an upload
        (each upload moves the controller's block pointer on: "Upload and Download")."""
        return not self.is_write and self.code != CommandCode.UPLOAD


def check_int(what: str, value: object, low: int, high: int, rule: str) -> int:
    """``value`` if it is an int (not a bool) in ``low..high``; else :class:`InvalidRequest` citing ``rule``."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise InvalidRequest(f"{what} {value!r} is not an integer")
    if not low <= value <= high:
        raise InvalidRequest(f"{what} {value} is out of range: {rule}")
    return value
