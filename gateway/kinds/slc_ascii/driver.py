"""Asyncio driver for the SLC 100/150 ASCII protocol: a thin loop around the sans-I/O core.

The transaction rules (``;Z``, ``;I``, resend after proof, ID 00 resync, the write verdict) live
in :mod:`gateway.protocols.slc_ascii.transaction`; this module moves bytes and time to it and
turns its verdicts into errors: ``REFUSED`` -> ``ControllerRefused``, ``UNKNOWN`` (a write that
may or may not have run, at most once) -> ``WriteOutcomeUnknown`` (as the DF1 driver), ``FAILED``
-> ``LinkTimeout``.
"""

from __future__ import annotations

import asyncio
import logging
from typing import Final, Unpack

from gateway.config.link import DEFAULT_RETRIES
from gateway.errors import (
    ControllerFault,
    ControllerRefused,
    GatewayError,
    LinkDown,
    LinkTimeout,
    ProtocolError,
    WriteOutcomeUnknown,
)
from gateway.kinds.slc_ascii.config import SLC_ASCII_DEFAULTS
from gateway.line_driver import LineDriver, LineDriverOptions, LineLease, Priority
from gateway.link_health import LineQuality
from gateway.protocols.slc_ascii import commands as cmds
from gateway.protocols.slc_ascii import memory_map as mm
from gateway.protocols.slc_ascii.commands import Command, ControllerType, FrnInfo, Mode, TimeoutClass
from gateway.protocols.slc_ascii.framing import Ack, DataReply, frame_command
from gateway.protocols.slc_ascii.transaction import MAX_RESYNCS, SlcSession, SlcVerdict
from gateway.protocols.slc_ascii.transfer import MAX_TRANSFER_RESTARTS, Download, Restart, Upload
from gateway.transport import SerialSettings

#: the retries-metric name of a message-ID resync (also the status block's kind counter)
ID_RESYNC: Final = "id_resync"
#: the retry kind of a reply asked for again (;Z)
RETRANSMIT: Final = "retransmit"

__all__ = ["ID_RESYNC", "MAX_TRANSFER_RESTARTS", "SLC_ASCII_SETTINGS", "SlcAsciiDriver"]

log = logging.getLogger("gateway.link")

#: The manual's line settings (9600 7E1), kept with the link model's defaults.
SLC_ASCII_SETTINGS: Final = SLC_ASCII_DEFAULTS.settings
#: The 0.3 s reply time of the manual, for commands other than mode changes and program edits.
DEFAULT_TIMEOUT: Final = SLC_ASCII_DEFAULTS.timeout
#: Mode changes and program transfer ("The exceptions are edit commands and mode changes").
DEFAULT_SLOW_TIMEOUT: Final = 3.0

Answer = Ack | DataReply

#: Characters of the longest reply: an upload block ``:<block><15 bytes><ID><CRC>CR``.
_LONGEST_REPLY: Final = 1 + 2 + 30 + 2 + 2 + 1

#: 7-bit character -> the same character with its even parity bit as bit 7.  On a port set to
#: 8 data bits and no parity this puts on the wire exactly what 7E1 would.
_EVEN_PARITY: Final = bytes((b & 0x7F) | ((bin(b & 0x7F).count("1") & 1) << 7) for b in range(256))


class SlcAsciiDriver(LineDriver):
    """One SLC 100/150 on one byte stream."""

    def __init__(
        self,
        url: str,
        *,
        settings: SerialSettings = SLC_ASCII_SETTINGS,
        timeout: float = DEFAULT_TIMEOUT,
        slow_timeout: float = DEFAULT_SLOW_TIMEOUT,
        retries: int = DEFAULT_RETRIES,
        max_resyncs: int = MAX_RESYNCS,
        write_budget: float | None = None,
        **line: Unpack[LineDriverOptions],
    ) -> None:
        super().__init__(url, settings=settings, **line)
        self.timeout = timeout
        self.slow_timeout = max(slow_timeout, timeout)
        self.retries = retries
        #: seconds a write may take to reach its verdict (``;Z`` and copies while they fit);
        #: None: ``retries`` ``;Z`` (the core's counts)
        self.write_budget = write_budget
        self.last_fault: ControllerFault | None = None
        self.session = SlcSession(timeout=timeout, retries=retries, max_resyncs=max_resyncs)
        self._waiter: asyncio.Future[None] | None = None
        # A port that cannot do 7E1 (some adapters, pseudo-terminals) can run at 8N1 with the
        # parity bit computed here; replies are read with bit 7 masked either way.
        self._software_parity = settings.bytesize == 8 and settings.parity == "N"
        self._aborted: GatewayError | None = None

    # --- protocol hooks ---------------------------------------------------------------------

    def on_connect(self) -> None:
        # Upon power up the controller expects ID 00: the first transaction resynchronises.
        self.session.connected()
        # The core's normal reply time (up to it the wait adapts; 1.5 x it is the late bound): the
        # configured one plus a frame of 2 x 8 + 9 characters, more than any normal command's (at
        # most 20), and the longest reply.
        self.session.timeout = self.timeout + (2 * 8 + 9 + _LONGEST_REPLY) * self.char_time
        self.session.late_bound = 1.5 * self.session.timeout
        # a frame's characters follow each other; a pause of 20 characters (50 ms at least, for
        # device servers that cut frames into packets) means the rest is lost
        self.session.char_gap = max(0.05, 20 * self.char_time)

    def abort(self, exc: GatewayError) -> None:
        self._aborted = exc
        _wake(self._waiter)

    def data_received(self, data: bytes) -> None:
        self.session.receive_data(data, asyncio.get_running_loop().time())
        _wake(self._waiter)

    # --- one transaction --------------------------------------------------------------------

    async def _transaction(self, command: Command) -> Answer:
        loop = asyncio.get_running_loop()
        session = self.session
        timeout = self.slow_timeout if command.timeout_class is TimeoutClass.SLOW else self.timeout
        # the characters of the command's frame (its ID's value does not change its length) and of the longest reply
        timeout += (len(frame_command(command, 0)) + _LONGEST_REPLY) * self.char_time
        self._aborted = None
        now = loop.time()
        until = now + self.write_budget if self.write_budget is not None and command.is_write else None
        session.start(command, now, timeout, until=until)
        while session.result is None:
            self._flush()
            if self._aborted is not None or not self.connected:
                session.connected()
                raise LinkDown(f"link {self.name} is down: {self.last_error or 'closed'}")
            deadline = session.next_deadline()
            if deadline is not None and loop.time() >= deadline:
                session.handle_timeout(loop.time())
                continue
            # Wait for bytes or the core's deadline (no wait_for: it can swallow a cancellation).
            self._waiter = waiter = loop.create_future()
            timer = loop.call_at(deadline, _wake, waiter) if deadline is not None else None
            try:
                await waiter
            except asyncio.CancelledError:
                session.connected()  # the line is in an unknown state: resync next time
                raise
            finally:
                self._waiter = None
                if timer is not None:
                    timer.cancel()
        self._flush()
        self._sync_counters()
        result = session.take_result()
        if result.verdict is SlcVerdict.DONE:
            assert result.answer is not None
            return result.answer
        if result.verdict is SlcVerdict.REFUSED:
            self.counters.refusals += 1
            raise ControllerRefused(
                f"controller refused {command.name} (;E: illegal in this mode or out of range)",
                command=command.name,
                reason=result.reason,
            )
        if result.verdict is SlcVerdict.UNKNOWN:
            raise WriteOutcomeUnknown(f"link {self.name}: {command.name}: outcome unknown (applied at most once): "
                                      f"{result.reason}")
        raise LinkTimeout(f"link {self.name}: {command.name}: {result.reason}")

    def _flush(self) -> None:
        data = self.session.data_to_send()
        if data:
            try:
                self.send(data.translate(_EVEN_PARITY) if self._software_parity else data)
            except BaseException:
                self.session.connected()  # not sent: the transaction ends here, and the next one resyncs
                raise

    def _sync_counters(self) -> None:
        core, mine = self.session.counters, self.counters
        mine.timeouts, mine.crc_errors = core.timeouts, core.crc_errors
        # ID resyncs that recovered the numbering, not the first one after connecting
        mine.retries_by_kind[RETRANSMIT] = core.retransmits
        mine.retries_by_kind[ID_RESYNC] = core.id_resyncs - core.handshakes
        mine.faults = core.faults

    def line_quality(self) -> LineQuality:
        """Checksum errors, timeouts, retransmissions (;Z) and ID resyncs; the protocol has no NAK."""
        counters = self.counters
        return LineQuality(check_errors=counters.crc_errors, timeouts=counters.timeouts,
                           retransmits=counters.retries_by_kind.get(RETRANSMIT, 0),
                           resyncs=counters.retries_by_kind.get(ID_RESYNC, 0))

    async def _run_command(self, command: Command) -> Answer:
        try:
            answer = await self._transaction(command)
        except ControllerRefused:
            self.note_result(True)
            raise
        except GatewayError as exc:
            self.note_result(False, str(exc))
            raise
        self.note_result(True)
        if self.session.fault_pending:
            await self._read_fault()
        return answer

    async def _read_fault(self) -> None:
        """After ;T: "read the bytes at addresses 84H and 85H to find out the reason"."""
        self.session.fault_pending = False
        try:
            answer = await self._transaction(cmds.read_bytes(mm.ERROR_BITS_REGION.start, 2))
        except GatewayError as exc:
            log.warning("link %s: controller reported a fault (;T); its error bits could not be read: %s",
                        self.name, exc)
            return
        assert isinstance(answer, DataReply)
        data = cmds.parse_read_reply(mm.ERROR_BITS_REGION.start, 2, answer.body_hex)
        fault = cmds.controller_fault(data[0], data[1])
        if self.last_fault is None or self.last_fault.errors != fault.errors:
            log.warning("link %s: %s", self.name, fault)
        self.last_fault = fault

    async def execute(
        self, command: Command, priority: Priority | None = None, line: LineLease | None = None
    ) -> Answer:
        """Send ``command`` and return its answer (``Ack`` or ``DataReply``).

        Raises ``ControllerRefused`` (;E), ``LinkTimeout``, ``LinkDown`` or ``ProtocolError``.
        Writes default to the write priority, everything else to the poll priority; with ``line``
        (a write session's lease) the command runs on the line the session holds.
        """
        if priority is None:
            priority = Priority.WRITE if command.is_write else Priority.POLL
        return await self.submit(lambda: self._run_command(command), priority, line)

    # --- typed operations -------------------------------------------------------------------

    async def read(self, address: int, count: int = 1, priority: Priority = Priority.POLL) -> bytes:
        """Read 1 or 2 bytes of the memory map."""
        answer = await self.execute(cmds.read_bytes(address, count), priority)
        return cmds.parse_read_reply(address, count, _data(answer).body_hex)

    async def write_word(self, address: int, value: int, line: LineLease | None = None) -> None:
        await self.execute(cmds.write_word(address, value), line=line)

    async def write_byte(self, address: int, value: int) -> None:
        await self.execute(cmds.write_byte(address, value))

    async def update_byte(self, address: int, bit: int, value: bool, line: LineLease | None = None) -> int:
        """Set one bit of a relay byte: read the byte fresh, write it back at once.

        Both transactions run back to back on the line, ahead of any poll; the ladder could still
        change another bit of the same byte between the read and the write (one scan at most).
        ``line``: as for :meth:`execute`.
        """

        async def op() -> int:
            answer = await self._run_command(cmds.read_bytes(address, 1))
            current = cmds.parse_read_reply(address, 1, _data(answer).body_hex)[0]
            new = (current | (1 << bit)) if value else (current & ~(1 << bit) & 0xFF)
            await self._run_command(cmds.write_byte(address, new))
            return new

        return await self.submit(op, Priority.WRITE, line)

    async def set_mode(self, mode: Mode) -> None:
        await self.execute(cmds.set_mode(mode))

    async def probe(self) -> FrnInfo:
        answer = await self.execute(cmds.read_frn())
        return cmds.parse_frn_reply(_data(answer).body_hex)

    async def upload_program(self, controller: ControllerType) -> bytes:
        """Every program block in order (the controller must be in program mode)."""
        upload = Upload(controller)
        await self._transfer(upload)
        return upload.program

    async def download_program(self, controller: ControllerType, program: bytes) -> None:
        """Download every block in order (program mode).  ``program`` is block_count * 15 bytes.

        Never silently partial: the restart rules (from block 0, at most ``MAX_TRANSFER_RESTARTS``
        times, then an error naming the block) are :mod:`gateway.protocols.slc_ascii.transfer`'s.
        """
        await self._transfer(Download(controller, program))

    async def _transfer(self, transfer: Upload | Download) -> None:
        """Run the commands of a program transfer back to back, holding the line."""

        async def op() -> None:
            while (command := transfer.next_command()) is not None:
                try:
                    answer = await self._run_command(command)
                except transfer.restart_on as exc:
                    restart: Restart | None = transfer.failed(exc)
                else:
                    restart = transfer.answered(answer)
                if restart is not None:
                    log.info("link %s: %s restarts from block 0 (block 0x%02X: %s)", self.name,
                             restart.transfer, restart.block, restart.reason)

        await self.submit(op, Priority.WRITE)


def _wake(waiter: asyncio.Future[None] | None) -> None:
    if waiter is not None and not waiter.done():
        waiter.set_result(None)


def _data(answer: Answer) -> DataReply:
    if not isinstance(answer, DataReply):
        raise ProtocolError("expected a data reply, got an acknowledge")
    return answer
