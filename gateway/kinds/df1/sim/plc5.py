"""A simulated PLC-5 on DF1 full duplex: word range read / write and read-modify-write.

The PLC-5 command set (1770-6.5.16 chapter 7; 1770-KF2 user manual chapter 5) addresses the data
table with PLC-5 system addresses - logical binary (mask byte + levels, 1770-6.5.16 p. 13-11) or
logical ASCII (``NUL $ N7:30 NUL``, p. 13-15) - parsed by :mod:`gateway.protocols.df1.plc5_address`.
This model answers:

* word range read, ``CMD 0F FNC 01``: ``PACKET OFFSET(2) TOTAL TRANS(2) ADDRESS SIZE(1)``; the reply
  carries SIZE data bytes, words low byte first, starting ``PACKET OFFSET`` words after the address
  (KF2 p. 5-57; S4516 §2.6.1; the 1785-KE line monitor examples, chapter 5 p. 5-5/5-6);
* word range write, ``CMD 0F FNC 00``: ``PACKET OFFSET(2) TOTAL TRANS(2) ADDRESS DATA``; reply
  ``4F STS TNS`` (KF2 p. 5-57);
* read-modify-write, ``CMD 0F FNC 26``: repeated ``ADDRESS AND(2) OR(2)``, each word becomes
  ``(word & AND) | OR``; "the PLC-5 system address must point to a word" (KF2 p. 5-48;
  1770-6.5.16 p. 7-20).  Every set is checked before any is applied, so a refused RMW changes nothing;
* typed read / write (``0F 68`` / ``0F 67``, PLC-5 commands too), diagnostic status: as the SLC model
  (the diagnostic status reply still carries the SLC 5/04 processor type: a known limit);
* SLC typed logical read / write / masked write (``0F A2 / AA / AB``) per the ``typed_logical``
  variant (below); read file info (``0F 94``) and set processor mode (``0F 80``) are SLC commands:
  STS 10 hex.

Data table: the same files and initial contents as the SLC 5/04 model (``gateway.kinds.df1.sim.slc500``):
O0, I1, S2, B3 (64 words), T4 (20), C5 (20), R6 (10), N7 (256), F8 (64 floats), N10, B12, F13.  A
logical binary address's levels are 1 data table (must be 0), 2 file, 3 element, 4 sub-element
(p. 13-13); the word it names is ``element * words per element + sub-element`` of the file.  A float
element is two words, the low-order word first (the SLC model's layout).

Errors (STS / EXT STS, 1770-6.5.16 chapter 8 and the EXT STS table for CMD 0F): a command the
processor does not have - STS 10 ("illegal command or format"); a malformed address or packet - STS
10; a level 1 other than 0, a missing file, an element, sub-element or bit that is not there - STS
F0 EXT 06 ("address doesn't point to something usable"); more than four levels - EXT 03; no file
level - EXT 02; a range running past the file's end - EXT 07 ("file is wrong size"); more than 244
bytes read or 239 bytes of address + data written - EXT 09 ("data or file is too large").

Variants (the first value is the default; ``variants={"typed_logical": "accept"}``), besides the
DF1 link variants of the SLC model (duplicate detection, ACK order, bad frames, ENQ answers):

* ``typed_logical`` ``refuse`` | ``accept``: 1770-6.5.16 lists the protected typed logical commands
  (A2 / AA / AB) among the SLC 500 and MicroLogix commands, not the PLC-5's, so the manual's reading
  is a PLC-5 that answers them STS 10 hex (illegal command or format).  Some PLC-5 firmware and every
  PLC-5 emulation in third-party gateways answers them as an SLC would: ``accept`` serves them from
  the same data table (the address fields are file number, file type, element, sub-element).

The link layer, fault injection and ``Output`` are the SLC model's (subclass): this module only
replaces the command execution.  No I/O.
"""

from __future__ import annotations

from typing import ClassVar, Final

from gateway.kinds.df1.sim.slc500 import ExtSts, Output, Slc500Simulator
from gateway.kinds.df1.sim.slc500_data import DataFile
from gateway.kinds.df1.sim.slc500_processor import _AnswerSts, _not_usable  # the SLC processor's refusal, one class
from gateway.protocols.df1.pccc import Function, PcccHeader, Sts, encode_reply
from gateway.protocols.df1.pccc.limits import PLC5_WORD_RANGE
from gateway.protocols.df1.pccc.plc5 import ReadModifyWrite, WordRangeReadParams, WordRangeWriteParams
from gateway.protocols.df1.plc5_address import (
    AddressError,
    decode_logical_ascii,
    decode_logical_binary,
    parse_plc5_address,
)

__all__ = ["MAX_WORD_RANGE_READ", "MAX_WORD_RANGE_WRITE", "Output", "Plc5Simulator"]

#: Word range read: data bytes in the reply; write: address + data bytes (``pccc/limits.py``).
MAX_WORD_RANGE_READ: Final = PLC5_WORD_RANGE.max_read_bytes
MAX_WORD_RANGE_WRITE: Final = PLC5_WORD_RANGE.max_write_bytes

_EXTENDED_CMD: Final = 0x0F
#: SLC protected typed logical read / write / masked write (the ``typed_logical`` variant).
_TYPED_LOGICAL: Final = frozenset({0xA2, 0xAA, 0xAB})
#: SLC-only functions a PLC-5 does not have: read file info, set processor mode (SLC form).
_SLC_ONLY: Final = frozenset({0x94, 0x80})


class Plc5Simulator(Slc500Simulator):
    """A PLC-5 on DF1 full duplex (module docstring).  Not thread-safe."""

    VARIANTS: ClassVar[dict[str, tuple[str, ...]]] = {
        **Slc500Simulator.VARIANTS,
        "typed_logical": ("refuse", "accept"),
    }

    @property
    def accept_typed_logical(self) -> bool:
        """The ``typed_logical`` variant: SLC typed logical commands are served (else STS 10)."""
        return self.variants["typed_logical"] == "accept"

    # --- commands ---------------------------------------------------------------------------

    def _answer(self, header: PcccHeader, packet: bytes) -> bytes:
        fnc = packet[6] if len(packet) > 6 else None
        if header.cmd != _EXTENDED_CMD or fnc is None:
            return super()._answer(header, packet)  # diagnostic status; malformed packets: STS 10
        if fnc in _TYPED_LOGICAL and self.accept_typed_logical:
            return super()._answer(header, packet)
        params = packet[7:]
        try:
            if fnc == Function.WORD_RANGE_READ:
                self._count("word_range_read")
                return encode_reply(header, data=self._word_range_read(params))
            if fnc == Function.WORD_RANGE_WRITE:
                self._count("word_range_write")
                self._word_range_write(params)
            elif fnc == Function.READ_MODIFY_WRITE:
                self._count("read_modify_write")
                self._read_modify_write(params)
            elif fnc in _TYPED_LOGICAL or fnc in _SLC_ONLY:
                self._count("unsupported")
                raise _AnswerSts(Sts.ILLEGAL_COMMAND_OR_FORMAT)
            else:
                return super()._answer(header, packet)  # typed read / write (67 / 68) and the rest
        except _AnswerSts as refusal:
            self.counters.refusals += 1
            return encode_reply(header, sts=refusal.sts, ext_sts=refusal.ext_sts)
        except (AddressError, IndexError):
            self.counters.refusals += 1
            return encode_reply(header, sts=Sts.ILLEGAL_COMMAND_OR_FORMAT)
        return encode_reply(header)

    def _target(self, address: bytes) -> tuple[DataFile, int]:
        """(file, byte offset of the word) of a PLC-5 system address (logical binary or ASCII)."""
        if address[:2] == b"\x00$":
            text, _end = decode_logical_ascii(address)
            parsed = parse_plc5_address(text)
            if parsed.bit is not None:
                raise _not_usable()  # word commands: the address must point to a word
            levels: tuple[int, ...] = parsed.levels
        else:
            mask = address[0]
            if mask & ~0x0F:
                raise _AnswerSts(Sts.EXTENDED, ExtSts.MORE_LEVELS)
            if not mask & 0x02:
                raise _AnswerSts(Sts.EXTENDED, ExtSts.FEWER_LEVELS)
            levels, _end = decode_logical_binary(address)
        section, file_number, element, sub = (*levels, 0, 0, 0, 0)[:4]
        data_file = self._files.get(file_number)
        if section != 0 or data_file is None:
            raise _not_usable()
        if element >= data_file.elements or sub >= data_file.element_words:
            raise _not_usable()
        return data_file, (element * data_file.element_words + sub) * 2

    @staticmethod
    def _check_mask(mask: bytes) -> None:
        """Level count first: a mask naming levels past 4 is EXT STS 03, even when the rest is garbled."""
        if mask and mask[0] != 0 and mask[0] & ~0x0F:
            raise _AnswerSts(Sts.EXTENDED, ExtSts.MORE_LEVELS)

    @staticmethod
    def _span(data_file: DataFile, offset: int, size: int) -> None:
        if offset + size > len(data_file.data):
            raise _AnswerSts(Sts.EXTENDED, ExtSts.WRONG_SIZE)

    def _word_range_read(self, params: bytes) -> bytes:
        self._check_mask(params[4:5])
        request = WordRangeReadParams.decode(params)
        if request.size > MAX_WORD_RANGE_READ:
            raise _AnswerSts(Sts.EXTENDED, ExtSts.TOO_LARGE)
        if request.size % 2 or request.size == 0:
            raise _AnswerSts(Sts.ILLEGAL_COMMAND_OR_FORMAT)
        data_file, offset = self._target(request.address)
        offset += request.packet_offset * 2
        self._span(data_file, offset, request.size)
        return bytes(data_file.data[offset : offset + request.size])

    def _word_range_write(self, params: bytes) -> None:
        self._check_mask(params[4:5])
        request = WordRangeWriteParams.decode(params)
        if len(request.address) + len(request.data) > MAX_WORD_RANGE_WRITE:
            raise _AnswerSts(Sts.EXTENDED, ExtSts.TOO_LARGE)
        if not request.data or len(request.data) % 2:
            raise _AnswerSts(Sts.ILLEGAL_COMMAND_OR_FORMAT)
        data_file, offset = self._target(request.address)
        offset += request.packet_offset * 2
        self._span(data_file, offset, len(request.data))
        data_file.data[offset : offset + len(request.data)] = request.data
        self.applied_writes.append(("word_range_write", self._text(data_file, offset), request.data))

    def _read_modify_write(self, params: bytes) -> None:
        self._check_mask(params[0:1])
        request = ReadModifyWrite.decode(params)
        if not request.sets:
            raise _AnswerSts(Sts.ILLEGAL_COMMAND_OR_FORMAT)
        targets = [(self._target(address), and_mask, or_mask) for address, and_mask, or_mask in request.sets]
        for (data_file, offset), and_mask, or_mask in targets:  # all checked above: apply every set
            word = data_file.word(offset)
            data_file.set_word(offset, (word & and_mask) | or_mask)
            masks = and_mask.to_bytes(2, "little") + or_mask.to_bytes(2, "little")
            self.applied_writes.append(("read_modify_write", self._text(data_file, offset), masks))

    @staticmethod
    def _text(data_file: DataFile, offset: int) -> str:
        element, sub = divmod(offset // 2, data_file.element_words)
        return data_file.address_text(element, sub)
