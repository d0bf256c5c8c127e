"""The processor of the simulated SLC 5/04 (``gateway.kinds.df1.sim.slc500``): data table, ladder, PCCC commands.

:class:`Slc500Processor` is the controller without its serial port: ``execute(packet)`` takes a
PCCC command packet and returns the reply packet (or None).  :class:`~gateway.kinds.df1.sim.slc500.Slc500Simulator`
puts it behind a DF1 full-duplex link with fault injection; the multi-drop line simulator
(``gateway.kinds.df1.sim.df1_multidrop``) puts it behind a half-duplex one.  No I/O, no clock: the ladder
runs up to the ``now`` given to :meth:`Slc500Processor.advance`.

Written from the manuals beside the code ("S4516-DF1 Program Development Manual", "SLC 500
PCCC command notes", the SLC 500 addressing reference):

* commands (CMD 0F unless noted): protected typed logical read / write / masked write with three
  address fields (FNC A2 / AA / AB), typed read / write on logical binary addresses (FNC 68 / 67),
  read file info (FNC 94), set processor mode (FNC 80), diagnostic status (CMD 06 FNC 03).
  Word range read / write (FNC 01 / 00) are PLC-5 commands the SLC does not have: STS 0x10;
* data table (deterministic initial contents, see :meth:`Slc500Processor.reset_data`)::

    O0   4 slots x 8 words     O:s.w = 0x0100 * s + w
    I1   4 slots x 8 words     I:s.w = 0x1000 + 0x0100 * s + w
    S2   164 words             S:1 = mode (bits 0-4) | keyswitch REM (bits 11, 12)
    B3   64 words              B3:1 = 0xA5A5, B3:2 = 1, others 0
    T4   20 timers             PRE 10, 20, 50, 100 for T4:0-3 (time base 0.1 s), 100 + k after
    C5   20 counters           C5:0 PRE 100, C5:k PRE 10 * k
    R6   10 controls           LEN 10 * (k + 1)
    N7   256 words             N7:k = k, except N7:200 = -1, N7:201 = 32767, N7:202 = -32768,
                               N7:255 = 0x1234
    F8   64 floats             F8:k = 1.5 * k
    N10  100 words, B12 16 words, F13 10 floats: all 0

* a small ladder (``ladder=True``, RUN and TEST-continuous modes only, 0.1 s time base, driven
  by the ``now`` given to :meth:`~Slc500Processor.advance`, which ``receive`` / ``poll`` call):
  T4:0-3 time (EN set, ACC + 1 per tick up to PRE, then DN), B3:0/0 toggles every tick, C5:0
  counts its rising edges (CU follows it; DN at PRE; OV and wrap past 32767), N7:0 counts ticks
  (wrapping at 16 bits).  Everything else changes only when written.

Memory layout: every file is a ``bytearray``, the flat byte image the protected typed logical
commands address: little-endian 16-bit words, structures as 3 consecutive words (control,
PRE / LEN, ACC / POS), I/O images as slot after slot of 8 words.  A protected typed logical
command reads or writes ``size`` bytes starting at ``element * element_bytes + sub_element * 2``
(for I/O, element = slot, sub-element = word in the slot).

Floats: a float element is the IEEE 754 single in 4 little-endian bytes (``struct '<f'``); on
the wire that is two little-endian 16-bit words, the low-order word first.  That is the
layout of PCCC replies from the SLC 5/03-5/05 and what ``gateway.unit`` decodes.

Errors (STS / EXT STS):

* unknown file, file type not matching the file, element or sub-element past the end:
  STS 0xF0, EXT STS 0x06 (address doesn't point to something usable);
* start inside the file but ``size`` bytes run past its end: STS 0xF0, EXT STS 0x07 (file is
  wrong size);
* more than 236 bytes read, or more than 228 bytes written (less 2 per 3-byte address field;
  notes §4.36): STS 0xF0, EXT STS 0x09 (data too large);
* typed write whose type/data does not match the file: STS 0xF0, EXT STS 0x11 (illegal data type);
* read file info of a missing file: STS 0x50 (notes §7.5);
* unsupported command, malformed packet with a readable header, unknown mode: STS 0x10.

Packets whose DST is not our station, replies, and packets shorter than a PCCC header are
ignored (``execute`` answers None; the link layer still ACKs their frames).  As on a real SLC,
data reads and writes are accepted in program mode too; only the ladder stops.
"""

from __future__ import annotations

import enum
import math
import struct
from typing import Final

from gateway.errors import GatewayError
from gateway.kinds.df1.sim.slc500_data import FILE_NAME_RE, SLOTS, TYPED_ID, WORDS_PER_SLOT, DataFile, data_files
from gateway.kinds.df1.sim.slc500_options import Slc500Counters, Slc500Options
from gateway.protocols.df1.address import FileType
from gateway.protocols.df1.pccc import (
    DiagnosticStatus,
    DiagnosticStatusInfo,
    FileInfo,
    LogicalBinaryAddress,
    PcccHeader,
    ProcessorMode,
    ProtectedTypedLogicalMaskedWrite,
    ProtectedTypedLogicalRead,
    ProtectedTypedLogicalWrite,
    ReadFileInfo,
    Request,
    SetProcessorMode,
    Sts,
    TypedRead,
    TypedWrite,
    WordRangeRead,
    WordRangeWrite,
    decode_command,
    encode_reply,
    encode_typed_data,
)
from gateway.protocols.df1.pccc.limits import SLC_MODULAR
from gateway.protocols.df1.pccc.slc import Echo, ProtectedTypedLogicalTwoFieldRead, ProtectedTypedLogicalTwoFieldWrite

__all__ = ["CATALOG", "FRN", "MAX_READ_BYTES", "MAX_WRITE_BYTES", "PROCESSOR_TYPE", "SERIES", "TICK", "ExtSts",
           "Slc500Processor"]

#: Processor type byte of the diagnostic status reply (notes §6.0: 5B hex = SLC 5/04).
PROCESSOR_TYPE: Final = 0x5B
CATALOG: Final = "1747-L542"
SERIES: Final = "C"
FRN: Final = 3

#: Data bytes per packet, SLC 5/03-5/04 channel 0 without the Internet field (notes §4.36).
MAX_READ_BYTES: Final = SLC_MODULAR.max_read_bytes
MAX_WRITE_BYTES: Final = SLC_MODULAR.max_write_bytes

#: Ladder time base, seconds.
TICK: Final = 0.1

#: S:1 bits 11-12: keyswitch position (both set: REM).
_KEYSWITCH_REM: Final = 0x1800
_MODE_BITS: Final = 0x1F
_RUNNING_MODES: Final = frozenset({ProcessorMode.RUN, ProcessorMode.TEST_CONTINUOUS})

_EN: Final = 1 << 15  # timer enable / counter CU
_TT: Final = 1 << 14  # timer timing
_DN: Final = 1 << 13  # done
_OV: Final = 1 << 12  # counter overflow


class ExtSts(enum.IntEnum):
    """EXT STS codes for CMD 0F used here (S4516-DF1 manual, Appendix A)."""

    FEWER_LEVELS = 0x02
    MORE_LEVELS = 0x03
    NOT_USABLE = 0x06
    WRONG_SIZE = 0x07
    TOO_LARGE = 0x09
    ILLEGAL_DATA_TYPE = 0x11


class _AnswerSts(Exception):
    """Internal: answer with this STS (and EXT STS)."""

    def __init__(self, sts: int, ext_sts: int | None = None) -> None:
        super().__init__(sts, ext_sts)
        self.sts = sts
        self.ext_sts = ext_sts


def _not_usable() -> _AnswerSts:
    return _AnswerSts(Sts.EXTENDED, ExtSts.NOT_USABLE)


def _signed(value: int) -> int:
    return value - 0x10000 if value & 0x8000 else value


class Slc500Processor:
    """The SLC 5/04's data table, ladder and command execution (module docstring).  Not thread-safe."""

    def __init__(self, options: Slc500Options | None = None, *, ladder: bool = True) -> None:
        self.options = options or Slc500Options()
        self.ladder = ladder
        self.counters = Slc500Counters()
        #: Every write executed, in order: (kind, address of the first element, data).
        #: Kinds: "write" (FNC AA), "masked_write" (AB), "typed_write" (67), "mode" (80).
        self.applied_writes: list[tuple[str, str, bytes]] = []
        self._files = data_files()
        self._ladder_origin: float | None = None
        self._ladder_ticks = 0
        self.reset_data()

    # --- data table -------------------------------------------------------------------------

    def reset_data(self) -> None:
        """Restore the initial data table (module docstring) and RUN mode."""
        for data_file in self._files.values():
            data_file.data[:] = bytes(len(data_file.data))
        output, inputs = self._files[0], self._files[1]
        for slot in range(SLOTS):
            for word in range(WORDS_PER_SLOT):
                offset = (slot * WORDS_PER_SLOT + word) * 2
                output.set_word(offset, 0x0100 * slot + word)
                inputs.set_word(offset, 0x1000 + 0x0100 * slot + word)
        self.set_word("S2", 1, _KEYSWITCH_REM | ProcessorMode.RUN)
        self.set_word("B3", 1, 0xA5A5)
        self.set_word("B3", 2, 1)
        for k, preset in enumerate((10, 20, 50, 100)):
            self.set_word("T4", k, preset, sub=1)
        for k in range(4, 20):
            self.set_word("T4", k, 100 + k, sub=1)
        for k in range(20):
            self.set_word("C5", k, 100 if k == 0 else 10 * k, sub=1)
        for k in range(10):
            self.set_word("R6", k, 10 * (k + 1), sub=1)
        for k in range(256):
            self.set_word("N7", k, k)
        for k, value in ((200, -1), (201, 32767), (202, -32768), (255, 0x1234)):
            self.set_word("N7", k, value)
        for k in range(64):
            self.set_float("F8", k, 1.5 * k)

    def _file(self, name: str) -> DataFile:
        """The file named like ``N7``, ``F8``, ``T4``, ``O0`` / ``O``, ``I1`` / ``I``, ``S2`` / ``S``."""
        match = FILE_NAME_RE.fullmatch(name.strip().upper())
        if match is None:
            raise KeyError(f"{name!r}: expected a file name like N7, F8, T4, O0, I1, S2")
        letter, number_text = match["letter"], match["number"]
        number = int(number_text) if number_text else {"O": 0, "I": 1, "S": 2}.get(letter, -1)
        data_file = self._files.get(number)
        if data_file is None or data_file.file_type.letter != letter:
            raise KeyError(f"{name!r}: no such file in the simulated data table")
        return data_file

    def _offset(self, data_file: DataFile, element: int, sub: int) -> int:
        if not (0 <= element < data_file.elements and 0 <= sub < data_file.element_words):
            raise IndexError(f"{data_file.name}: element {element} sub-element {sub} out of range")
        return element * data_file.element_bytes + sub * 2

    def word(self, file: str, element: int, sub: int = 0) -> int:
        """Word ``sub`` of ``element`` (for I/O: slot, word) of ``file``, unsigned 16 bits."""
        data_file = self._file(file)
        return data_file.word(self._offset(data_file, element, sub))

    def set_word(self, file: str, element: int, value: int, sub: int = 0) -> None:
        """Set a word (signed or unsigned 16-bit value); not recorded in ``applied_writes``."""
        if not -0x8000 <= value <= 0xFFFF:
            raise ValueError(f"{value} does not fit in 16 bits")
        data_file = self._file(file)
        data_file.set_word(self._offset(data_file, element, sub), value)

    def float_value(self, file: str, element: int) -> float:
        data_file = self._file(file)
        offset = self._offset(data_file, element, 0)
        value: float = struct.unpack_from("<f", data_file.data, offset)[0]
        return value

    def set_float(self, file: str, element: int, value: float) -> None:
        data_file = self._file(file)
        struct.pack_into("<f", data_file.data, self._offset(data_file, element, 0), value)

    def file_bytes(self, file_type: FileType | int, file_number: int) -> bytes:
        """A copy of the flat byte image of a file; KeyError if there is no such file."""
        data_file = self._files.get(file_number)
        if data_file is None or data_file.file_type != file_type:
            raise KeyError(f"no file {file_number} of type 0x{int(file_type):02X}")
        return bytes(data_file.data)

    @property
    def mode(self) -> int:
        """Processor mode, S:1 bits 0-4 (the set processor mode codes: 1 program, 6 run ...)."""
        return self.word("S2", 1) & _MODE_BITS

    def set_mode(self, mode: int) -> None:
        status = self.word("S2", 1)
        self.set_word("S2", 1, (status & ~_MODE_BITS & 0xFFFF) | (mode & _MODE_BITS))
        self._ladder_origin = None

    # --- ladder -----------------------------------------------------------------------------

    def advance(self, now: float) -> None:
        """Run the ladder up to ``now`` (seconds); frozen with ``ladder=False`` or when not running."""
        if not self.ladder or self.mode not in _RUNNING_MODES:
            self._ladder_origin = None
            return
        if self._ladder_origin is None:
            self._ladder_origin, self._ladder_ticks = now, 0
            return
        total = math.floor((now - self._ladder_origin) / TICK + 1e-9)
        if total > self._ladder_ticks:
            self._scan(total - self._ladder_ticks)
            self._ladder_ticks = total

    def _scan(self, ticks: int) -> None:
        """``ticks`` scans of the ladder at once (module docstring)."""
        timers = self._files[4]
        for k in range(4):
            base = k * timers.element_bytes
            control, preset, acc = timers.word(base), _signed(timers.word(base + 2)), _signed(timers.word(base + 4))
            if acc < preset:
                acc = min(preset, acc + ticks)
            control |= _EN
            control = (control | _DN) & ~_TT if acc >= preset else (control | _TT) & ~_DN
            timers.set_word(base, control)
            timers.set_word(base + 4, acc)
        bits = self._files[3]
        clock = bits.word(0) & 1
        rising = (ticks + 1) // 2 if clock == 0 else ticks // 2
        clock ^= ticks & 1
        bits.set_word(0, (bits.word(0) & ~1) | clock)
        counters = self._files[5]
        control, preset, acc = counters.word(0), _signed(counters.word(2)), _signed(counters.word(4)) + rising
        if acc > 0x7FFF:
            control |= _OV
            acc = (acc + 0x8000) % 0x10000 - 0x8000
        control = (control | _EN) if clock else (control & ~_EN)
        control = (control | _DN) if acc >= preset else (control & ~_DN)
        counters.set_word(0, control)
        counters.set_word(4, acc)
        integers = self._files[7]
        integers.set_word(0, integers.word(0) + ticks)

    # --- commands ---------------------------------------------------------------------------

    def execute(self, packet: bytes) -> bytes | None:
        """A command packet -> its reply packet, or None when it is not answered."""
        return self._handle(packet)

    def _count(self, kind: str) -> None:
        self.counters.commands[kind] = self.counters.commands.get(kind, 0) + 1

    def _handle(self, packet: bytes) -> bytes | None:
        """A command packet -> the reply packet, or None when it is not answered (module docstring:
        not for our station, a reply, shorter than a header)."""
        try:
            header = PcccHeader.decode(packet)
        except GatewayError:
            self.counters.ignored += 1
            return None
        if header.dst != self.options.station or header.is_reply:
            self.counters.ignored += 1
            return None
        return self._answer(header, packet)

    def _answer(self, header: PcccHeader, packet: bytes) -> bytes:
        """The reply packet to a command for this station."""
        try:
            command = decode_command(packet)
        except GatewayError:
            self._count("malformed")
            self.counters.refusals += 1
            return encode_reply(header, sts=Sts.ILLEGAL_COMMAND_OR_FORMAT)
        try:
            data = self._execute(command.request)
        except _AnswerSts as refusal:
            self.counters.refusals += 1
            return encode_reply(header, sts=refusal.sts, ext_sts=refusal.ext_sts)
        return encode_reply(header, data=data)

    def _execute(self, request: Request) -> bytes:
        match request:
            case ProtectedTypedLogicalRead():
                self._count("read")
                return self._logical_read(request)
            case ProtectedTypedLogicalWrite():
                self._count("write")
                self._logical_write(request)
            case ProtectedTypedLogicalMaskedWrite():
                self._count("masked_write")
                self._masked_write(request)
            case TypedRead():
                self._count("typed_read")
                return self._typed_read(request)
            case TypedWrite():
                self._count("typed_write")
                self._typed_write(request)
            case ReadFileInfo():
                self._count("file_info")
                return self._file_info(request)
            case SetProcessorMode():
                self._count("set_mode")
                self._set_processor_mode(request)
            case DiagnosticStatus():
                self._count("diagnostic_status")
                info = DiagnosticStatusInfo.build(
                    processor_type=PROCESSOR_TYPE, series=SERIES, frn=FRN, catalog=CATALOG, mode_status=self.mode
                )
                return info.raw
            case WordRangeRead() | WordRangeWrite():
                self._count("unsupported")  # PLC-5 commands (notes §4.0 command table)
                raise _AnswerSts(Sts.ILLEGAL_COMMAND_OR_FORMAT)
            case ProtectedTypedLogicalTwoFieldRead() | ProtectedTypedLogicalTwoFieldWrite() | Echo():
                self._count("unsupported")  # commands this simulator does not model
                raise _AnswerSts(Sts.ILLEGAL_COMMAND_OR_FORMAT)
        return b""

    def _logical_target(
        self,
        request: ProtectedTypedLogicalRead | ProtectedTypedLogicalWrite | ProtectedTypedLogicalMaskedWrite,
        size: int,
        limit: int,
    ) -> tuple[DataFile, int]:
        """(file, byte offset) of a three-address-field command moving ``size`` bytes."""
        if size > limit:
            raise _AnswerSts(Sts.EXTENDED, ExtSts.TOO_LARGE)
        data_file = self._files.get(request.file_number)
        if data_file is None or data_file.file_type != request.file_type:
            raise _not_usable()
        if not (request.element < data_file.elements and request.sub_element < data_file.element_words):
            raise _not_usable()
        offset = request.element * data_file.element_bytes + request.sub_element * 2
        if offset + size > len(data_file.data):
            raise _AnswerSts(Sts.EXTENDED, ExtSts.WRONG_SIZE)
        return data_file, offset

    def _logical_read(self, request: ProtectedTypedLogicalRead) -> bytes:
        data_file, offset = self._logical_target(request, request.size, MAX_READ_BYTES)
        return bytes(data_file.data[offset : offset + request.size])

    def _logical_write(self, request: ProtectedTypedLogicalWrite) -> None:
        limit = MAX_WRITE_BYTES - 2 * request.expanded_fields
        data_file, offset = self._logical_target(request, len(request.data), limit)
        data_file.data[offset : offset + len(request.data)] = request.data
        self.applied_writes.append(
            ("write", data_file.address_text(request.element, request.sub_element), request.data)
        )

    def _masked_write(self, request: ProtectedTypedLogicalMaskedWrite) -> None:
        """new = (old & ~mask) | (data & mask), the mask's low byte on even bytes (notes §7.3)."""
        limit = MAX_WRITE_BYTES - 2 * request.expanded_fields
        data_file, offset = self._logical_target(request, len(request.data), limit)
        mask = request.mask.to_bytes(2, "little")
        for i, byte in enumerate(request.data):
            m = mask[i % 2]
            data_file.data[offset + i] = (data_file.data[offset + i] & ~m & 0xFF) | (byte & m)
        self.applied_writes.append(
            ("masked_write", data_file.address_text(request.element, request.sub_element), request.data)
        )

    def _typed_target(self, address: LogicalBinaryAddress, packet_offset: int) -> tuple[DataFile, int]:
        """(file, element) of a logical binary address: levels section, file, element, sub-element."""
        if address.mask & ~0x0F:
            raise _AnswerSts(Sts.EXTENDED, ExtSts.MORE_LEVELS)
        if not address.mask & 0x02:
            raise _AnswerSts(Sts.EXTENDED, ExtSts.FEWER_LEVELS)
        levels = iter(address.levels)
        section, file_number, element, sub_element = (next(levels) if address.mask & (1 << n) else 0 for n in range(4))
        data_file = self._files.get(file_number)
        # "Sub-element addressing is not supported in SLC in typed read and typed write" (notes §7.4).
        if section != 0 or data_file is None or sub_element != 0:
            raise _not_usable()
        return data_file, element + packet_offset

    def _typed_span(self, data_file: DataFile, element: int, size: int) -> int:
        if size > MAX_READ_BYTES:
            raise _AnswerSts(Sts.EXTENDED, ExtSts.TOO_LARGE)
        offset = element * data_file.typed_element_bytes
        if offset >= len(data_file.data):
            raise _not_usable()
        if offset + size > len(data_file.data):
            raise _AnswerSts(Sts.EXTENDED, ExtSts.WRONG_SIZE)
        return offset

    def _typed_read(self, request: TypedRead) -> bytes:
        data_file, element = self._typed_target(request.address, request.packet_offset)
        if data_file.file_type is FileType.INPUT:  # "typed read, you can not read inputs" (notes §4.0)
            raise _not_usable()
        element_bytes = data_file.typed_element_bytes
        size = request.count * element_bytes
        offset = self._typed_span(data_file, element, size)
        return encode_typed_data(
            TYPED_ID[data_file.file_type], element_bytes, bytes(data_file.data[offset : offset + size])
        )

    def _typed_write(self, request: TypedWrite) -> None:
        data_file, element = self._typed_target(request.address, request.packet_offset)
        if data_file.file_type is FileType.OUTPUT:  # "typed write, you can not write outputs" (notes §4.0)
            raise _not_usable()
        if len(request.data) > MAX_WRITE_BYTES:
            raise _AnswerSts(Sts.EXTENDED, ExtSts.TOO_LARGE)
        element_bytes = data_file.typed_element_bytes
        if request.data_type != TYPED_ID[data_file.file_type] or request.element_size != element_bytes:
            raise _AnswerSts(Sts.EXTENDED, ExtSts.ILLEGAL_DATA_TYPE)
        offset = self._typed_span(data_file, element, len(request.data))
        data_file.data[offset : offset + len(request.data)] = request.data
        sub = 0
        if data_file.is_io:
            element, sub = divmod(element, data_file.element_words)
        self.applied_writes.append(("typed_write", data_file.address_text(element, sub), request.data))

    def _file_info(self, request: ReadFileInfo) -> bytes:
        data_file = self._files.get(request.file_number)
        if data_file is None:
            raise _AnswerSts(Sts.ADDRESSING_PROBLEM)  # "50h bad address; file doesn't exist" (notes §7.5)
        count = len(data_file.data) // data_file.typed_element_bytes
        return FileInfo(len(data_file.data), count, data_file.file_type).encode()

    def _set_processor_mode(self, request: SetProcessorMode) -> None:
        if request.mode not in tuple(ProcessorMode):
            raise _AnswerSts(Sts.ILLEGAL_COMMAND_OR_FORMAT)
        self.set_mode(request.mode)
        self.applied_writes.append(("mode", "S:1", bytes((request.mode,))))
