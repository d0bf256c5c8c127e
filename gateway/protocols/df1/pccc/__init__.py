"""PCCC, the application layer of DF1 for SLC 500 and PLC-5: one module per concern.

* :mod:`.codes` - CMD / FNC codes and the reply bit (S4516-DF1 manual §2.2; notes §4.0)
* :mod:`.status` - STS / EXT STS tables, :func:`describe_status`, :class:`PcccError` (Appendix A)
* :mod:`.codec` - header, replies, field encodings, logical binary addresses, TNS (§2.2, §2.6)
* :mod:`.slc` - SLC 500 commands: typed logical read / write (two and three address fields) /
  masked write, file info, set mode, diagnostic status, echo, packet size limits (§2.6.2; notes
  §4.36, §6.0, §7.3, §7.5, §7.6)
* :mod:`.plc5` - PLC-5 commands: word range read / write, typed read / write, read-modify-write
  (§2.6.1; notes §5.0, §7.4; 1770-6.5.16 p. 7-20)
* :mod:`.params` - the fields of a command's parameters, listed once per request class; encoding,
  decoding and range checks come from that list
* :mod:`.commands` - the :data:`Request` union and the command encoder / decoder
* :mod:`.target` (with :mod:`.target_table`, :mod:`.target_transfer`) - the other side: the gateway
  answering the commands a PLC's MSG instructions send it (DF1 target mode); not re-exported here

Manuals: "S4516-DF1 Program Development Manual" (after A-B 1770-6.5.16) and the "SLC 500 PCCC
command notes".  This package re-exports the names importers used when PCCC was one module.
Nothing here does I/O.
"""

from gateway.protocols.df1.pccc.codec import (
    LogicalBinaryAddress,
    PcccFormatError,
    PcccHeader,
    PcccReply,
    TnsAllocator,
    decode_reply,
    encode_reply,
    reply_matches,
)
from gateway.protocols.df1.pccc.codes import (
    REPLY_BIT,
    CmdByte,
    DiagnosticFunction,
    Function,
)
from gateway.protocols.df1.pccc.commands import (
    WRITE_REQUESTS,
    PcccCommand,
    Request,
    decode_command,
    encode_command,
    is_write,
)
from gateway.protocols.df1.pccc.plc5 import (
    DataType,
    ReadModifyWriteRequest,
    TypeData,
    TypedData,
    TypedRead,
    TypedWrite,
    WordRangeRead,
    WordRangeWrite,
    decode_type_data,
    decode_typed_data,
    encode_type_data,
    encode_typed_data,
)
from gateway.protocols.df1.pccc.slc import (
    DiagnosticStatus,
    DiagnosticStatusInfo,
    Echo,
    FileInfo,
    ProcessorFamily,
    ProcessorMode,
    ProtectedTypedLogicalMaskedWrite,
    ProtectedTypedLogicalRead,
    ProtectedTypedLogicalTwoFieldRead,
    ProtectedTypedLogicalTwoFieldWrite,
    ProtectedTypedLogicalWrite,
    ReadFileInfo,
    SetProcessorMode,
    SizeLimits,
    slc_read_request,
    slc_write_request,
)
from gateway.protocols.df1.pccc.status import (
    PcccError,
    Sts,
    describe_status,
)

__all__ = [
    "REPLY_BIT",
    "WRITE_REQUESTS",
    "CmdByte",
    "DataType",
    "DiagnosticFunction",
    "DiagnosticStatus",
    "DiagnosticStatusInfo",
    "Echo",
    "FileInfo",
    "Function",
    "LogicalBinaryAddress",
    "PcccCommand",
    "PcccError",
    "PcccFormatError",
    "PcccHeader",
    "PcccReply",
    "ProcessorFamily",
    "ProcessorMode",
    "ProtectedTypedLogicalMaskedWrite",
    "ProtectedTypedLogicalRead",
    "ProtectedTypedLogicalTwoFieldRead",
    "ProtectedTypedLogicalTwoFieldWrite",
    "ProtectedTypedLogicalWrite",
    "ReadFileInfo",
    "ReadModifyWriteRequest",
    "Request",
    "SetProcessorMode",
    "SizeLimits",
    "Sts",
    "TnsAllocator",
    "TypeData",
    "TypedData",
    "TypedRead",
    "TypedWrite",
    "WordRangeRead",
    "WordRangeWrite",
    "decode_command",
    "decode_reply",
    "decode_type_data",
    "decode_typed_data",
    "describe_status",
    "encode_command",
    "encode_reply",
    "encode_type_data",
    "encode_typed_data",
    "is_write",
    "reply_matches",
    "slc_read_request",
    "slc_write_request",
]
