"""PCCC command and function codes shared by every PCCC module.

Manuals: S4516-DF1 Program Development Manual §2.2 (command and reply packet bytes: CMD bit 6 is
the reply bit) and §2.6 (message packet formats); SLC 500 PCCC command notes §4.0 (the PLC-5 / SLC
command set table).  This module does no I/O.
"""

from __future__ import annotations

import enum
from typing import Final

__all__ = ["REPLY_BIT", "CmdByte", "DiagnosticFunction", "Function"]

#: CMD bit 6: 0 in a command, 1 in a reply (S4516-DF1 manual §2.2, Appendix B block 1).
REPLY_BIT: Final = 0x40


class CmdByte(enum.IntEnum):
    """CMD byte (notes §4.0 command table)."""

    DIAGNOSTIC = 0x06
    EXTENDED = 0x0F  # PLC-5 / SLC 500 command set, FNC selects the function


class Function(enum.IntEnum):
    """FNC byte of CMD 0x0F (notes §4.0 command table; S4516-DF1 manual §2.6)."""

    WORD_RANGE_WRITE = 0x00
    WORD_RANGE_READ = 0x01
    READ_MODIFY_WRITE = 0x26  # PLC-5 (1770-6.5.16 p. 7-20)
    TYPED_WRITE = 0x67
    TYPED_READ = 0x68
    SET_PROCESSOR_MODE = 0x80
    READ_FILE_INFO = 0x94
    PROTECTED_TYPED_LOGICAL_READ_TWO_FIELDS = 0xA1
    PROTECTED_TYPED_LOGICAL_READ = 0xA2
    PROTECTED_TYPED_LOGICAL_WRITE_TWO_FIELDS = 0xA9
    PROTECTED_TYPED_LOGICAL_WRITE = 0xAA
    PROTECTED_TYPED_LOGICAL_MASKED_WRITE = 0xAB


class DiagnosticFunction(enum.IntEnum):
    """FNC byte of CMD 0x06 (notes §4.0 command table)."""

    ECHO = 0x00  # "diagnostic loop" in the notes and the 1770-KF2 manual
    DIAGNOSTIC_STATUS = 0x03
