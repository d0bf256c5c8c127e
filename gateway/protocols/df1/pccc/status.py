"""PCCC status: the STS / EXT STS tables, their descriptions and the refusal error.

Manuals: S4516-DF1 Program Development Manual §2.2 (the STS byte of a reply) and Appendix A
(STS local / remote error codes, EXT STS for CMD 0x0F and 0x0E); SLC 500 PCCC command notes §6.5
/ §7.5 (read file info) and §7.6 (set processor mode) for command-specific wording.

``EXT STS`` follows STS only when ``STS == 0xF0``; for EXT STS 0x1A / 0x1B one more byte names the
node that owns the file / program.  This module does no I/O.
"""

from __future__ import annotations

import enum
from typing import Final

from gateway.errors import ControllerRefused
from gateway.protocols.df1.pccc.codes import REPLY_BIT, CmdByte, Function

__all__ = ["OWNER_EXT_STS", "PcccError", "Sts", "describe_status"]


class Sts(enum.IntEnum):
    """STS byte (S4516-DF1 manual Appendix A): low nibble local, high nibble remote errors."""

    SUCCESS = 0x00
    CANNOT_GUARANTEE_DELIVERY = 0x02
    DUPLICATE_TOKEN_HOLDER = 0x03
    LOCAL_PORT_DISCONNECTED = 0x04
    APPLICATION_TIMEOUT = 0x05
    DUPLICATE_NODE = 0x06
    STATION_OFFLINE = 0x07
    LOCAL_HARDWARE_FAULT = 0x08  # local nibble: "Hardware fault" (1770-6.5.16 p. 8-2)
    ILLEGAL_COMMAND_OR_FORMAT = 0x10
    HOST_PROBLEM = 0x20
    REMOTE_HOST_MISSING = 0x30
    HOST_HARDWARE_FAULT = 0x40  # remote nibble: the host could not complete the function (p. 8-3)
    ADDRESSING_PROBLEM = 0x50
    COMMAND_PROTECTION = 0x60
    PROGRAM_MODE = 0x70
    COMPATIBILITY_FILE_MISSING = 0x80
    CANNOT_BUFFER_COMMAND = 0x90
    DOWNLOAD_PROBLEM = 0xB0
    ACTIVE_IPBS = 0xC0
    EXTENDED = 0xF0  # the error code is in the EXT STS byte


_LOCAL_STS: Final = {
    0x01: "Not used",
    0x02: "Cannot guarantee delivery: link layer",
    0x03: "Duplicate token holder detected",
    0x04: "Local port is disconnected",
    0x05: "Application layer timed out waiting for a response",
    0x06: "Duplicate node detected",
    0x07: "Station is off-line",
    0x08: "Hardware fault",
}
_REMOTE_STS: Final = {
    0x10: "Illegal command or format",
    0x20: "Host has a problem and will not communicate",
    0x30: "Remote node host is missing, disconnected or shut down",
    0x40: "Host could not complete function due to hardware fault",
    0x50: "Addressing problem or memory protect rungs",
    0x60: "Function disallowed due to command protection selection",
    0x70: "Processor is in program mode",
    0x80: "Compatibility mode file missing or communication zone problem",
    0x90: "Remote node cannot buffer command",
    0xA0: "Not used",
    0xB0: "Remote node problem due to download",
    0xC0: "Cannot execute command due to active IPBs",
    0xD0: "Not used",
    0xE0: "Not used",
    0xF0: "There is an error code in the EXT STS byte",
}
#: EXT STS for CMD 0x0F (Appendix A).
_EXT_STS_0F: Final = {
    0x01: "A field has an illegal value",
    0x02: "Less levels specified in address than minimum for any address",
    0x03: "More levels specified in address than system supports",
    0x04: "Symbol not found",
    0x05: "Symbol is of improper format",
    0x06: "Address doesn't point to something usable",
    0x07: "File is wrong size",
    0x08: "Cannot complete request, situation has changed since the start of the command",
    0x09: "Data or file is too large",
    0x0A: "Transaction size plus word address is too large",
    0x0B: "Access denied, improper privilege",
    0x0C: "Condition cannot be generated - resource is not available",
    0x0D: "Condition already exists - resource is already available",
    0x0E: "CmdByte cannot be executed",
    0x0F: "Histogram overflow",
    0x10: "No access",
    0x11: "Illegal data type",
    0x12: "Invalid parameter or invalid data",
    0x13: "Address reference exists to deleted area",
    0x14: "CmdByte execution failure for unknown reason; possible PLC-3 histogram overflow",
    0x15: "Data conversion error",
    0x16: "Scanner not able to communicate with 1771 rack adapter",
    0x17: "Adapter cannot communicate with module",
    0x18: "1771 module response was not valid",
    0x19: "Duplicated label",
    0x1A: "File is open; another node owns it",
    0x1B: "Another node is the program owner",
}
#: EXT STS for CMD 0x0E (Appendix A).
_EXT_STS_0E: Final = {
    0x00: "Multi-defined processors on ring",
    0x01: "Processor is already allocated",
    0x02: "Processor must be allocated for this command",
    0x03: "Extended function in progress",
    0x04: "Function not available in this processor command set",
    0x05: "Function not available in this processor mode",
    0x06: "Processor number in program and hardware do not match",
    0x07: "Invalid address",
    0x08: "Memory protection access violation",
    0x09: "Invalid parameter",
    0x0A: "Search unsuccessful",
    0x0B: "Program needs to be stored - RAM and PROM do not match",
    0x0C: "External EEPROM is defective, cannot transfer contents correctly",
    0x0D: "Invalid user program",
    0x0F: "Device resource unavailable",
    0x20: "Processor already allocated by requesting node",
    0x21: "Processor already allocated by another remote node",
    0x22: "Processor not allocated",
    0x23: "Data length invalid",
    0x24: "Data size too large",
    0x25: "Data size too large",
    0x26: "Data size too small",
    0x27: "At least one of the addresses points to a read-only area",
    0x28: "Address past end of memory",
    0x29: "Memory protected, addresses to program area illegal",
    0x2A: "Memory protected, address to processor status area illegal",
    0x2B: "Memory protected, address to protected timer or counter",
    0x2C: "Processor not in program mode, address to program area",
    0x2D: "Address past 'end of used memory'",
    0x2E: "'Program valid' bit not set in PLC-4 program ID byte",
    0x2F: "Invalid PLC-4 select value",
    0x7C: "PLC-4 ring disconnected",
    0x7D: "No PLC-4 response",
    0x7F: "Invalid PLC-4 selected byte",
}
#: CmdByte-specific wording from the SLC notes (§7.5 read file info, §7.6 set processor mode).
_SPECIFIC: Final[dict[tuple[int, int, int | None], str]] = {
    (Function.READ_FILE_INFO, 0x50, None): "Bad address; file doesn't exist",
    (Function.READ_FILE_INFO, 0xF0, 0x1B): "File protection error",
    (Function.SET_PROCESSOR_MODE, 0xF0, 0x0B): "Access denied: channel read protect",
    (Function.SET_PROCESSOR_MODE, 0xF0, 0x0C): "Condition cannot be generated (keyswitch not in REM)",
}
#: EXT STS values followed by the owner's node address.
OWNER_EXT_STS: Final = frozenset({0x1A, 0x1B})


def describe_status(
    sts: int, ext_sts: int | None = None, *, cmd: int = CmdByte.EXTENDED, fnc: int | None = None
) -> str:
    """The manual's description of ``STS`` (and ``EXT STS``), e.g. for error messages."""
    if fnc is not None and (fnc, sts, ext_sts) in _SPECIFIC:
        return _SPECIFIC[fnc, sts, ext_sts]
    if sts == 0:
        return "Success - no error"
    parts = []
    if sts & 0x0F:
        parts.append(_LOCAL_STS.get(sts & 0x0F, f"Unknown local error 0x{sts & 0x0F:02X}"))
    remote = sts & 0xF0
    if remote == 0xF0:
        table = _EXT_STS_0E if (cmd & ~REPLY_BIT) == 0x0E else _EXT_STS_0F
        if ext_sts is None:
            parts.append("Error code in EXT STS, but the EXT STS byte is missing")
        else:
            parts.append(table.get(ext_sts, f"Unknown extended status 0x{ext_sts:02X}"))
    elif remote:
        parts.append(_REMOTE_STS[remote])
    return "; ".join(parts)


class PcccError(ControllerRefused):
    """The controller answered with a non-zero STS; ``description`` is the manual's text."""

    def __init__(
        self,
        message: str,
        *,
        command: str = "",
        sts: int,
        ext_sts: int | None = None,
        description: str = "",
        owner_node: int | None = None,
    ) -> None:
        super().__init__(message, command=command, reason=description, code=sts)
        self.sts = sts
        self.ext_sts = ext_sts
        self.description = description
        self.owner_node = owner_node
