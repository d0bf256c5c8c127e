"""PCCC command packets: every request type, and the command encoder / decoder over them.

Manuals: S4516-DF1 Program Development Manual §2.2 and §2.6 (``DST SRC CMD STS TNS FNC params``);
SLC 500 PCCC command notes §4.0 (which CMD / FNC pairs exist).  The request types themselves live
in :mod:`.slc` and :mod:`.plc5`; this module only dispatches on ``(CMD, FNC)``.  It does no I/O.
"""

from __future__ import annotations

from typing import Final, get_args

from gateway.errors import InvalidRequest
from gateway.frozen import frozen
from gateway.protocols.df1.pccc import plc5, slc
from gateway.protocols.df1.pccc.codec import HEADER_SIZE, PcccFormatError, PcccHeader, Reader

__all__ = ["WRITE_REQUESTS", "PcccCommand", "Request", "decode_command", "encode_command", "is_write"]


Request = (
    slc.ProtectedTypedLogicalRead
    | slc.ProtectedTypedLogicalWrite
    | slc.ProtectedTypedLogicalMaskedWrite
    | slc.ProtectedTypedLogicalTwoFieldRead
    | slc.ProtectedTypedLogicalTwoFieldWrite
    | slc.ReadFileInfo
    | slc.SetProcessorMode
    | slc.DiagnosticStatus
    | slc.Echo
    | plc5.WordRangeRead
    | plc5.WordRangeWrite
    | plc5.TypedRead
    | plc5.TypedWrite
    | plc5.ReadModifyWriteRequest
)

#: The commands that change the controller: a reply lost after one of them ran cannot be told from
#: one that never ran, so these are sent once and settled by a read-back, never resent.  Every
#: layer (both drivers, the transaction cores, the simulators' fault injection) asks :func:`is_write`.
WRITE_REQUESTS: Final = (
    slc.ProtectedTypedLogicalWrite,
    slc.ProtectedTypedLogicalMaskedWrite,
    slc.ProtectedTypedLogicalTwoFieldWrite,
    plc5.TypedWrite,
    plc5.WordRangeWrite,
    plc5.ReadModifyWriteRequest,
    slc.SetProcessorMode,
)


def is_write(request: object) -> bool:
    """Whether ``request`` changes the controller (:data:`WRITE_REQUESTS`)."""
    return isinstance(request, WRITE_REQUESTS)


#: Every request class by its ``(CMD, FNC)``: the members of :data:`Request`.
_REQUEST_TYPES: Final[dict[tuple[int, int], type[Request]]] = {(cls.CMD, cls.FNC): cls for cls in get_args(Request)}


@frozen
class PcccCommand:
    """A decoded command packet (controller side)."""

    header: PcccHeader
    request: Request


def encode_command(request: Request, *, dst: int, src: int, tns: int) -> bytes:
    """``DST SRC CMD 00 TNS FNC params`` for ``request``."""
    header = PcccHeader(dst, src, request.CMD, 0, tns)
    return header.encode() + bytes((request.FNC,)) + request.encode_params()


def decode_command(packet: bytes) -> PcccCommand:
    """Parse a command packet; :class:`PcccFormatError` (with ``header`` when known) otherwise."""
    header = PcccHeader.decode(packet)
    if header.is_reply:
        raise PcccFormatError(f"PCCC: CMD 0x{header.cmd:02X} is a reply, not a command", header=header)
    reader = Reader(packet, HEADER_SIZE, header=header)
    fnc = reader.u8("function code")
    request_type = _REQUEST_TYPES.get((header.cmd, fnc))
    if request_type is None:
        raise reader.fail(f"PCCC: unsupported command CMD 0x{header.cmd:02X} FNC 0x{fnc:02X}")
    try:
        return PcccCommand(header, request_type.decode_params(reader))
    except InvalidRequest as exc:
        raise reader.fail(str(exc)) from exc
