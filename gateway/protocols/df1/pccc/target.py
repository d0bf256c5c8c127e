"""The DF1 target: the gateway answers the MSG instructions a PLC sends it (sans-I/O).

:class:`PcccTarget` takes a command packet (``DST SRC CMD STS TNS FNC ...``, the link layer's
payload) and the caller's ``now``, executes it against a :class:`~.target_table.DataTable`
(files N, B, F, L) and returns a :class:`TargetReply`: the reply packet (DST / SRC swapped, CMD |
40 hex, same TNS; 1770-6.5.16 p. 6-4) and what the command changed.  The link layer (ACK / NAK /
ENQ) is not here.  Every command decodes with the master side's own decoders
(:func:`~.commands.decode_command`), so both sides share one wire rule.

Commands answered:

=========  ==================================================  =====================================
CMD FNC    command                                             manual
=========  ==================================================  =====================================
0F A1 A9   protected typed logical read / write, 2 fields      1756-PM020F pp. 91-92
0F A2 AA   protected typed logical read / write, 3 fields      1770-6.5.16 pp. 7-17, 7-18
0F AB      protected typed logical masked write                notes §4.36, §7.3
0F 01 00   word range read / write, packet offset and total    S4516 §2.6.1; KF2 p. 5-57
0F 68 67   typed read / write (type/data parameter)            notes §7.4; 1770-6.5.16 p. 7-30
06 03      diagnostic status                                   1770-6.5.16 ch. 10
06 00      echo                                                KF2 p. 5-10; notes §4.0
=========  ==================================================  =====================================

Anything else - another CMD / FNC, or a packet that does not follow its format - is answered STS
10 hex "illegal command or format" (1770-6.5.16 p. 8-3, remote STS codes).  A packet too short for
a PCCC header, or a reply (CMD bit 6 set), gets no answer.  The DST byte is not checked: on a
point-to-point link a PLC addresses the gateway with whatever station its MSG names.

Refusals (:class:`Problem`), by command family.  The SLC typed logical commands (0F A1 / A2 / A9 /
AA / AB) have the STS the notes list for them (§4.36 (d): 10, 50, F0 0B / 1A / 1B; 6001-F2E Table
B.E for 0F A2); the PLC-5 commands (0F 00 / 01 / 67 / 68) have the EXT STS codes of 1770-6.5.16
p. 8-4 with the explanations of p. 8-9:

=============================================  =====================  ============================
problem                                        SLC typed logical      PLC-5 commands
=============================================  =====================  ============================
too large for a packet, odd word range size,   STS 10                 STS 10 (p. 8-9: size > 244,
offset + size past the total transaction                              odd size, past total)
file does not exist                            STS 50                 F0 / 06 address doesn't point
                                                                      to something usable
start element past the end, sub-element,       STS 50                 F0 / 06
section other than 0
data runs past the end of the file             STS 50                 F0 / 09 (p. 8-9: "read or
                                                                      write past the end of a file")
file type / data type not the file's           STS 50                 F0 / 11 illegal data type
address with too few / too many levels         -                      F0 / 02, F0 / 03
multi-packet write out of order                -                      F0 / 08 (see target_transfer)
read of a never-written element, with          F0 / 10 no access      F0 / 10 no access
``unwritten_reads=REFUSE``
=============================================  =====================  ============================

For a type mismatch both 1770-6.5.16 p. 8-4 (as stored: 17 "type mismatch") and the S4516 manual's
Appendix A (17 "adapter cannot communicate with module") print an EXT STS 17 that differs; 11
"illegal data type" is in both, so the target answers 11.

**Reads of never-written elements** (option ``unwritten_reads``, :class:`UnwrittenReads`).  A PLC
reading a data table expects an answer: a controller's new data file reads as zeros.  So by default
(``ZERO``) the read succeeds with 0 in those elements, and :attr:`TargetReply.unwritten` lists them
for the caller to log or count.  ``REFUSE`` answers STS F0 / EXT STS 10 "no access" instead (the
Modbus side's reading: a value nobody wrote is not served).

**Diagnostic status** (06 03) identifies the gateway as what it is, a computer interface, never as
a controller: the layout of the diagnostic status reply of A-B's own computer interfaces (1770-KF3
manual Table B.C; 1747-KFC15 Table C.9; 1784-KR, 6001-F2E Table C.C)::

    byte  0      00   mode/status: no modes (not a processor)
    byte  1      FE   bits 0-3 interface type E (extended), bits 4-7 processor type F (computer)
    byte  2      00   extended interface type: none assigned to this gateway
    byte  3      00   not used (where an SLC puts its processor type: DiagnosticStatusInfo.family is None)
    byte  4      00   series / revision: series A, revision A
    bytes 5-15        bulletin name, 11 ASCII characters: "DF1-GATEWAY" (``name``)
    bytes 16-23  00   product-specific information

Multi-packet writes, and what happens to one that is out of order or abandoned:
:mod:`.target_transfer`.  Every write is all-or-nothing: it is checked to fit before anything
changes.  No I/O, no clock.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Final

from gateway.errors import GatewayError
from gateway.frozen import frozen
from gateway.protocols.df1.pccc.codec import LogicalBinaryAddress, PcccFormatError, PcccHeader, encode_reply
from gateway.protocols.df1.pccc.commands import Request, decode_command
from gateway.protocols.df1.pccc.limits import PLC5_TYPED, SLC_MODULAR, SizeLimits
from gateway.protocols.df1.pccc.plc5 import (
    TypedRead,
    TypedWrite,
    WordRangeRead,
    WordRangeWrite,
    encode_typed_data,
)
from gateway.protocols.df1.pccc.slc import (
    DiagnosticStatus,
    Echo,
    ProtectedTypedLogicalMaskedWrite,
    ProtectedTypedLogicalRead,
    ProtectedTypedLogicalTwoFieldRead,
    ProtectedTypedLogicalTwoFieldWrite,
    ProtectedTypedLogicalWrite,
)
from gateway.protocols.df1.pccc.status import Sts
from gateway.protocols.df1.pccc.target_table import DataTable, ElementRef, TableFile
from gateway.protocols.df1.pccc.target_transfer import Transfer, Transfers

__all__ = [
    "GATEWAY_NAME",
    "PcccTarget",
    "Problem",
    "TargetReply",
    "UnwrittenReads",
    "diagnostic_status_reply",
    "refusal",
]

#: Bulletin name in the diagnostic status reply (11 ASCII characters).
GATEWAY_NAME: Final = "DF1-GATEWAY"


class UnwrittenReads(enum.Enum):
    """What a read of a never-written element answers (module docstring)."""

    ZERO = "zero"  #: the read succeeds, those elements read 0; TargetReply.unwritten names them
    REFUSE = "refuse"  #: STS F0 / EXT STS 10 "no access"


class Problem(enum.Enum):
    """Why a command is refused; the codes depend on the command family (module docstring)."""

    FORMAT = "illegal command or format"
    NO_FILE = "file does not exist"
    NOT_USABLE = "address past the end of the file or not an element"
    PAST_END = "data runs past the end of the file"
    TYPE = "file type or data type is not the file's"
    FEWER_LEVELS = "fewer address levels than a file"
    MORE_LEVELS = "more address levels than section, file, element, sub-element"
    OUT_OF_ORDER = "multi-packet write out of order"
    UNWRITTEN = "read of a never-written element"


_NO_ACCESS: Final = (Sts.EXTENDED, 0x10)
_SLC_CODES: Final[dict[Problem, tuple[int, int | None]]] = {
    Problem.FORMAT: (Sts.ILLEGAL_COMMAND_OR_FORMAT, None),
    Problem.NO_FILE: (Sts.ADDRESSING_PROBLEM, None),
    Problem.NOT_USABLE: (Sts.ADDRESSING_PROBLEM, None),
    Problem.PAST_END: (Sts.ADDRESSING_PROBLEM, None),
    Problem.TYPE: (Sts.ADDRESSING_PROBLEM, None),
    Problem.UNWRITTEN: _NO_ACCESS,
}
_PLC5_CODES: Final[dict[Problem, tuple[int, int | None]]] = {
    Problem.FORMAT: (Sts.ILLEGAL_COMMAND_OR_FORMAT, None),
    Problem.NO_FILE: (Sts.EXTENDED, 0x06),
    Problem.NOT_USABLE: (Sts.EXTENDED, 0x06),
    Problem.PAST_END: (Sts.EXTENDED, 0x09),
    Problem.TYPE: (Sts.EXTENDED, 0x11),
    Problem.FEWER_LEVELS: (Sts.EXTENDED, 0x02),
    Problem.MORE_LEVELS: (Sts.EXTENDED, 0x03),
    Problem.OUT_OF_ORDER: (Sts.EXTENDED, 0x08),
    Problem.UNWRITTEN: _NO_ACCESS,
}
_SlcRead = ProtectedTypedLogicalRead | ProtectedTypedLogicalTwoFieldRead
_SlcWrite = ProtectedTypedLogicalWrite | ProtectedTypedLogicalTwoFieldWrite | ProtectedTypedLogicalMaskedWrite


def refusal(request: Request | None, problem: Problem) -> tuple[int, int | None]:
    """STS and EXT STS of ``problem`` for ``request``'s command family (module docstring table): the
    one answer of every path that answers a PLC's message.  A packet that does not decode as a
    command (``None``) can only be ``FORMAT``: STS 10 in both families (1770-6.5.16 p. 8-3)."""
    codes = _SLC_CODES if request is None or isinstance(request, _SlcRead | _SlcWrite) else _PLC5_CODES
    return codes[problem]


def diagnostic_status_reply(name: str = GATEWAY_NAME) -> bytes:
    """The 24 data bytes of the diagnostic status reply (module docstring)."""
    return bytes((0x00, 0xFE, 0x00, 0x00, 0x00)) + name.encode("ascii")[:11].ljust(11) + bytes(8)


@frozen
class TargetReply:
    """What :meth:`PcccTarget.execute` did with one packet.

    ``reply`` is the packet to send back (None: not a command, no answer).  ``written``: the
    elements this packet changed (a multi-packet write: all of them, with its last packet).
    ``unwritten``: never-written elements this packet read (answered 0).  ``pending``: a packet of a
    multi-packet write was taken, nothing applied yet.  ``abandoned``: multi-packet writes dropped
    while handling it, nothing of them applied.
    """

    reply: bytes | None
    request: Request | None = None
    sts: int = 0
    ext_sts: int | None = None
    problem: Problem | None = None
    written: tuple[ElementRef, ...] = ()
    unwritten: tuple[ElementRef, ...] = ()
    pending: bool = False
    abandoned: tuple[Transfer, ...] = ()


class _Refused(Exception):
    """A command refused; :meth:`PcccTarget.execute` turns it into the reply (never raised further)."""

    def __init__(self, problem: Problem, abandoned: tuple[Transfer, ...] = ()) -> None:
        self.problem = problem
        self.abandoned = abandoned


@dataclass(slots=True)
class _Done:
    data: bytes = b""
    written: tuple[ElementRef, ...] = ()
    unwritten: tuple[ElementRef, ...] = ()
    pending: bool = False
    abandoned: tuple[Transfer, ...] = ()


class PcccTarget:
    """Executes the PCCC commands a PLC sends to the gateway (module docstring).  Not thread-safe."""

    def __init__(
        self,
        table: DataTable,
        *,
        unwritten_reads: UnwrittenReads = UnwrittenReads.ZERO,
        name: str = GATEWAY_NAME,
        slc_limits: SizeLimits = SLC_MODULAR,
        transfers: Transfers | None = None,
    ) -> None:
        diagnostic_status_reply(name)  # UnicodeEncodeError now, not at the first diagnostic status
        self.table = table
        self.unwritten_reads = unwritten_reads
        self.name = name
        #: Data bytes of the SLC typed logical commands; 5/03-5/05 on DF1 by default (notes §4.36).
        self.slc_limits = slc_limits
        self.transfers = transfers or Transfers()

    def execute(self, packet: bytes, now: float) -> TargetReply:
        """Answer one command packet (module docstring)."""
        try:
            header = PcccHeader.decode(packet)
        except PcccFormatError:
            return TargetReply(None)
        if header.is_reply:
            return TargetReply(None)
        expired = self.transfers.expire(now)
        try:
            request = decode_command(packet).request
        except GatewayError:
            return self._refuse(header, None, Problem.FORMAT, expired)
        try:
            done = self._run(request, header, now)
        except _Refused as refused:
            return self._refuse(header, request, refused.problem, expired + refused.abandoned)
        return TargetReply(
            encode_reply(header, data=done.data),
            request,
            written=done.written,
            unwritten=done.unwritten,
            pending=done.pending,
            abandoned=expired + done.abandoned,
        )

    @staticmethod
    def _refuse(
        header: PcccHeader,
        request: Request | None,
        problem: Problem,
        abandoned: tuple[Transfer, ...],
    ) -> TargetReply:
        sts, ext_sts = refusal(request, problem)
        reply = encode_reply(header, sts=sts, ext_sts=ext_sts)
        return TargetReply(reply, request, sts, ext_sts, problem, abandoned=abandoned)

    def _run(self, request: Request, header: PcccHeader, now: float) -> _Done:
        match request:
            case ProtectedTypedLogicalRead() | ProtectedTypedLogicalTwoFieldRead():
                if request.size > self.slc_limits.max_read_bytes:
                    raise _Refused(Problem.FORMAT)
                table_file, offset = self._slc_target(request, request.size)
                return self._read(table_file, offset, request.size)
            case ProtectedTypedLogicalWrite() | ProtectedTypedLogicalTwoFieldWrite():
                table_file, offset = self._slc_write_target(request)
                return self._write(table_file, offset, request.data, now)
            case ProtectedTypedLogicalMaskedWrite():
                table_file, offset = self._slc_write_target(request)
                return self._write(table_file, offset, request.data, now, request.mask.to_bytes(2, "little"))
            case WordRangeRead():
                if request.size % 2 or request.packet_offset + request.size // 2 > request.total_words:
                    raise _Refused(Problem.FORMAT)
                table_file, element = self._resolve(request.address)
                word = element * table_file.kind.words + request.packet_offset
                return self._read(table_file, word * 2, request.size)
            case WordRangeWrite():
                table_file, element = self._resolve(request.address)
                start = element * table_file.kind.element_bytes
                return self._multi_packet(header, request, table_file, start, 2, now)
            case TypedRead():
                table_file, element = self._resolve(request.address)
                type_id, unit = self._typed(table_file), table_file.kind.element_bytes
                size = request.count * unit
                if len(encode_typed_data(type_id, unit, bytes(size))) > PLC5_TYPED.max_read_bytes:  # the reply's data
                    raise _Refused(Problem.FORMAT)
                if request.packet_offset + request.count > request.total_elements:
                    raise _Refused(Problem.FORMAT)
                done = self._read(table_file, (element + request.packet_offset) * unit, size)
                done.data = encode_typed_data(type_id, unit, done.data)
                return done
            case TypedWrite():
                table_file, element = self._resolve(request.address)
                unit = table_file.kind.element_bytes
                if (request.data_type, request.element_size) != (self._typed(table_file), unit):
                    raise _Refused(Problem.TYPE)
                if len(request.encode_params()) - 4 > PLC5_TYPED.max_write_bytes:  # less packet offset and total
                    raise _Refused(Problem.FORMAT)
                return self._multi_packet(header, request, table_file, element * unit, unit, now)
            case DiagnosticStatus():
                return _Done(diagnostic_status_reply(self.name))
            case Echo():
                return _Done(request.data)
        raise _Refused(Problem.FORMAT)  # a command the gateway does not have (1770-6.5.16 p. 8-3)

    # --- addresses ---------------------------------------------------------------------------

    def _slc_target(self, request: _SlcRead | _SlcWrite, size: int) -> tuple[TableFile, int]:
        """(file, byte offset) of a typed logical command's file / type / element / sub-element."""
        table_file = self.table.get(request.file_number)
        if table_file is None:
            raise _Refused(Problem.NO_FILE)
        if request.file_type != table_file.kind.file_type:
            raise _Refused(Problem.TYPE)
        if getattr(request, "sub_element", 0) != 0 or request.element >= table_file.count:
            raise _Refused(Problem.NOT_USABLE)
        offset = request.element * table_file.kind.element_bytes
        if not table_file.fits(offset, size):
            raise _Refused(Problem.PAST_END)
        return table_file, offset

    def _slc_write_target(self, request: _SlcWrite) -> tuple[TableFile, int]:
        if len(request.data) > self.slc_limits.write_limit(request.expanded_fields):
            raise _Refused(Problem.FORMAT)  # notes §4.36: 2 bytes less per 3-byte address field
        return self._slc_target(request, len(request.data))

    def _resolve(self, address: LogicalBinaryAddress) -> tuple[TableFile, int]:
        """(file, element) of a logical binary address: section, file, element, sub-element (notes §6.0)."""
        if address.mask & ~0x0F:
            raise _Refused(Problem.MORE_LEVELS)
        if not address.mask & 0x02:
            raise _Refused(Problem.FEWER_LEVELS)
        levels = iter(address.levels)
        section, file_number, element, sub_element = (next(levels) if address.mask & 1 << n else 0 for n in range(4))
        table_file = self.table.get(file_number)
        if table_file is None:
            raise _Refused(Problem.NO_FILE)
        if section != 0 or sub_element != 0 or element >= table_file.count:
            raise _Refused(Problem.NOT_USABLE)
        return table_file, element

    @staticmethod
    def _typed(table_file: TableFile) -> int:
        if table_file.kind.type_id is None:
            raise _Refused(Problem.TYPE)
        return table_file.kind.type_id

    # --- data ----------------------------------------------------------------------------------

    def _read(self, table_file: TableFile, offset: int, size: int) -> _Done:
        if not table_file.fits(offset, size):
            raise _Refused(Problem.PAST_END)
        data, unwritten = table_file.read_bytes(offset, size)
        if unwritten and self.unwritten_reads is UnwrittenReads.REFUSE:
            raise _Refused(Problem.UNWRITTEN)
        return _Done(data, unwritten=tuple(ElementRef(table_file.number, e) for e in unwritten))

    def _write(self, table_file: TableFile, offset: int, data: bytes, now: float, mask: bytes = b"") -> _Done:
        if not data:  # a masked write of 0 bytes (notes §4.36 allows it) changes nothing
            return _Done()
        if not table_file.fits(offset, len(data)):
            raise _Refused(Problem.PAST_END)
        written = table_file.write_bytes(offset, data, now, mask)
        return _Done(written=tuple(ElementRef(table_file.number, e) for e in written))

    def _multi_packet(
        self,
        header: PcccHeader,
        request: WordRangeWrite | TypedWrite,
        table_file: TableFile,
        start: int,
        unit: int,
        now: float,
    ) -> _Done:
        """A write with packet offset and total, in ``unit``-byte words or elements (target_transfer)."""
        total = request.total if request.total is not None else 0
        if request.packet_offset + len(request.data) // unit > total:
            raise _Refused(Problem.FORMAT)  # past the total transaction (1770-6.5.16 p. 8-9)
        if not table_file.fits(start, total * unit):
            raise _Refused(Problem.PAST_END)
        key = (header.src, request.FNC, table_file.number, start, total)  # the element, however its address is written
        outcome = self.transfers.packet(key, table_file, start, unit, request.packet_offset, total, request.data, now)
        if outcome.out_of_order:
            raise _Refused(Problem.OUT_OF_ORDER, outcome.abandoned)
        if outcome.complete is None:
            return _Done(pending=True, abandoned=outcome.abandoned)
        done = self._write(table_file, start, outcome.complete, now)
        done.abandoned = outcome.abandoned
        return done
