"""Asyncio driver for the SLC 100/150 ASCII protocol: exactly-once writes over a lossy line.

One transaction (manual, *Format of Transmission*)::

    send  #... ID=n
      reply with ID n (;R, :data, ;E)          -> our answer
      ;I<last>  (not executed)                 -> last == n: an earlier copy of our command was
                                                  executed, ask ;Z for its answer; otherwise
                                                  resync and resend with ID 01
      nothing / garbled within the timeout     -> ;Z: the controller repeats its last reply;
          reply to ;Z with ID n                -> our answer
          reply to ;Z with an older ID         -> our command never arrived: resend it, same ID
      ;T at any time                           -> after this transaction read 84H-85H, record it

A write is sent again only when the controller proved it did not execute it (an older ID in
answer to ``;Z``, or ``;I``), so it is never applied twice; when no proof comes within the
retries the caller gets ``LinkTimeout`` (the outcome is then unknown, never silently dropped).

Resync: ID 00 "is always accepted", so a command sent with ID 00 is not protected by the ID
check.  Only a harmless read (``#0108``, read FRN) is ever sent with ID 00: it restarts the
controller's numbering, and the command follows with ID 01.  A reply that arrives after its
timeout and is taken for the answer to a later message can then cause a resend, but never a
second execution.
"""

from __future__ import annotations

import asyncio
import logging
from collections import deque
from pathlib import Path
from typing import Final

from gateway.drivers.base import LinkDriver, OpenStream, Priority, timeout_error
from gateway.errors import ControllerFault, ControllerRefused, GatewayError, LinkDown, ProtocolError
from gateway.protocols.slc_ascii import commands as cmds
from gateway.protocols.slc_ascii.commands import Command, ControllerType, FrnInfo, Mode, TimeoutClass
from gateway.protocols.slc_ascii.framing import (
    MAX_ID,
    NEED_DATA,
    Ack,
    DataReply,
    Fault,
    Garbled,
    IdMismatch,
    IdSequencer,
    Refused,
    ReplyDecoder,
    ReplyEvent,
    encode_command,
    encode_retransmit,
)
from gateway.transport import SerialSettings, open_stream

__all__ = ["SLC_ASCII_SETTINGS", "SlcAsciiDriver"]

log = logging.getLogger("gateway.link")

#: Manual: "even parity, and operates at 9600 baud ... 7 - data bits, 1 - parity bit, and 1 - stop bit".
SLC_ASCII_SETTINGS: Final = SerialSettings(baudrate=9600, bytesize=7, parity="E", stopbits=1)
#: The 0.3 s reply time of the manual, for commands other than mode changes and program edits.
DEFAULT_TIMEOUT: Final = 0.3
#: Mode changes and program transfer ("The exceptions are edit commands and mode changes").
DEFAULT_SLOW_TIMEOUT: Final = 3.0
#: How often one transaction resends after proof of non-execution (;I, older ID) before giving up.
MAX_RESENDS: Final = 8

Answer = Ack | DataReply

#: Characters of the longest reply: an upload block ``:<block><15 bytes><ID><CRC>CR``.
_LONGEST_REPLY: Final = 1 + 2 + 30 + 2 + 2 + 1

#: 7-bit character -> the same character with its even parity bit as bit 7.  On a port set to
#: 8 data bits and no parity this puts on the wire exactly what 7E1 would.
_EVEN_PARITY: Final = bytes((b & 0x7F) | ((bin(b & 0x7F).count("1") & 1) << 7) for b in range(256))


class SlcAsciiDriver(LinkDriver):
    """One SLC 100/150 on one byte stream."""

    def __init__(
        self,
        url: str,
        *,
        name: str = "",
        settings: SerialSettings = SLC_ASCII_SETTINGS,
        timeout: float = DEFAULT_TIMEOUT,
        slow_timeout: float = DEFAULT_SLOW_TIMEOUT,
        retries: int = 3,
        trace: Path | None = None,
        reconnect_min: float = 0.5,
        reconnect_max: float = 30.0,
        opener: OpenStream = open_stream,
    ) -> None:
        super().__init__(
            url,
            name=name,
            settings=settings,
            trace=trace,
            reconnect_min=reconnect_min,
            reconnect_max=reconnect_max,
            opener=opener,
        )
        self.timeout = timeout
        self.slow_timeout = max(slow_timeout, timeout)
        self.retries = retries
        self.last_fault: ControllerFault | None = None
        self._ids = IdSequencer()
        self._decoder = ReplyDecoder()
        self._events: deque[ReplyEvent] = deque()
        self._waiter: asyncio.Future[None] | None = None
        self._fault_pending = False
        # A port that cannot do 7E1 (some adapters, pseudo-terminals) can run at 8N1 with the
        # parity bit computed here; replies are read with bit 7 masked either way.
        self._software_parity = settings.bytesize == 8 and settings.parity == "N"

    def _send_frame(self, frame: bytes) -> None:
        self.send(frame.translate(_EVEN_PARITY) if self._software_parity else frame)

    # --- protocol hooks ---------------------------------------------------------------------

    def on_connect(self) -> None:
        # Upon power up the controller expects ID 00: the first transaction resynchronises.
        self._ids.reset()
        self._decoder = ReplyDecoder()
        self._events.clear()

    def abort(self, exc: GatewayError) -> None:
        waiter = self._waiter
        if waiter is not None and not waiter.done():
            waiter.set_exception(exc)

    def data_received(self, data: bytes) -> None:
        decoder = self._decoder
        decoder.receive_data(data)
        while True:
            event = decoder.next_event()
            if event is NEED_DATA:
                break
            if isinstance(event, Fault):
                self.counters.faults += 1
                self._fault_pending = True
                continue
            if isinstance(event, Garbled):
                self.counters.crc_errors += 1
            self._events.append(event)
        waiter = self._waiter
        if self._events and waiter is not None and not waiter.done():
            waiter.set_result(None)

    async def _next_event(self, deadline: float) -> ReplyEvent | None:
        """The next reply event, or None at ``deadline``."""
        if self._events:
            return self._events.popleft()
        if not self.connected:
            raise LinkDown(f"link {self.name} is down: {self.last_error or 'closed'}")
        loop = asyncio.get_running_loop()
        waiter = loop.create_future()
        self._waiter = waiter
        handle = loop.call_at(deadline, _wake, waiter)
        try:
            await waiter
        finally:
            handle.cancel()
            self._waiter = None
        return self._events.popleft() if self._events else None

    # --- one transaction --------------------------------------------------------------------

    async def _transaction(self, command: Command) -> Answer:
        loop = asyncio.get_running_loop()
        timeout = self.slow_timeout if command.timeout_class is TimeoutClass.SLOW else self.timeout
        # The manual's 0.3 s is the controller's answer time; the characters of the command and
        # of the longest reply (an upload block, 38 characters) take their own time on the line.
        timeout += (2 * command.byte_count + 9 + _LONGEST_REPLY) * self.char_time
        self._events.clear()  # late replies to an earlier transaction are of no use now
        if self._ids.peek == 0:
            await self._resync(timeout)
        msg_id = self._ids.take()
        self._send_frame(encode_command(command, msg_id))
        z_sent = 0  # ;Z sent since the last (re)send of the command
        resends = 0
        awaiting_z = False
        deadline = loop.time() + timeout
        while True:
            event = await self._next_event(deadline)
            if isinstance(event, (Ack, DataReply, Refused)):
                if event.msg_id == msg_id:
                    break
                if awaiting_z:
                    # The controller's last reply is older than our command: it never got it.
                    resends += 1
                    if resends > MAX_RESENDS:
                        raise ProtocolError(f"link {self.name}: {command.name}: controller keeps ignoring it")
                    self._send_frame(encode_command(command, msg_id))
                    awaiting_z, z_sent = False, 0
                    deadline = loop.time() + timeout
                continue  # a stale reply to an earlier transaction: ignore it
            if isinstance(event, IdMismatch):
                if event.last_valid_id != 0 and _next_id(event.last_valid_id) == msg_id:
                    # A controller whose last valid ID precedes ours accepts ours: this ;I
                    # answers an earlier message (a reply that came after its timeout).
                    continue
                self.counters.id_resyncs += 1
                resends += 1
                if resends > MAX_RESENDS:
                    raise ProtocolError(f"link {self.name}: {command.name}: message IDs do not resynchronise")
                if event.last_valid_id == msg_id:
                    # An earlier copy of this very message was accepted: fetch its answer.
                    self.counters.retransmits += 1
                    self._send_frame(encode_retransmit(msg_id))
                    awaiting_z = True
                else:
                    await self._resync(timeout)
                    msg_id = self._ids.take()
                    self._send_frame(encode_command(command, msg_id))
                    awaiting_z, z_sent = False, 0
                deadline = loop.time() + timeout
                continue
            if isinstance(event, Garbled):
                continue  # a garbled reply counts as missing: wait for the deadline, then ;Z
            # Deadline passed with no answer.
            self.counters.timeouts += 1
            if z_sent >= self.retries:
                self._ids.reset()  # we no longer know the controller's ID state
                raise timeout_error(self.name, command.name, timeout, z_sent + 1)
            z_sent += 1
            self.counters.retransmits += 1
            self._send_frame(encode_retransmit(msg_id))
            awaiting_z = True
            deadline = loop.time() + timeout
        if isinstance(event, Refused):
            self.counters.refusals += 1
            raise ControllerRefused(
                f"controller refused {command.name} (;E: illegal in this mode or out of range)",
                command=command.name,
                reason="illegal command or parameters for the current mode",
            )
        return event

    async def _resync(self, reply_time: float) -> None:
        """Restart the controller's message numbering with a harmless read: ``#0108`` with ID 00.

        ID 00 "is always accepted", so a command sent with it would be executed again by any
        copy of it (a resend after a reply that came too late to be recognised).  Only this
        read, which may run any number of times, ever uses ID 00; the command then goes with
        ID 01, and the controller's ID check answers a second copy of it with ``;I`` instead
        of executing it.  The line keeps the order, so the read is handled before the command.
        """
        loop = asyncio.get_running_loop()
        self._ids.reset()
        probe = encode_command(cmds.read_frn(), self._ids.take())
        for _ in range(self.retries + 1):
            self._send_frame(probe)
            deadline = loop.time() + reply_time
            while (event := await self._next_event(deadline)) is not None:
                if isinstance(event, DataReply) and event.msg_id == 0:
                    return
                # anything else answers an earlier message
            self.counters.timeouts += 1
        self._ids.reset()
        raise timeout_error(self.name, "read FRN with ID 00 (message ID resync)", reply_time, self.retries + 1)

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
        if self._fault_pending:
            await self._read_fault()
        return answer

    async def _read_fault(self) -> None:
        """After ;T: "read the bytes at addresses 84H and 85H to find out the reason"."""
        self._fault_pending = False
        try:
            answer = await self._transaction(cmds.read_bytes(0x84, 2))
        except GatewayError as exc:
            log.warning("link %s: controller reported a fault (;T); its error bits could not be read: %s",
                        self.name, exc)
            return
        assert isinstance(answer, DataReply)
        data = cmds.parse_read_reply(0x84, 2, answer.body_hex)
        fault = cmds.controller_fault(data[0], data[1])
        if self.last_fault is None or self.last_fault.errors != fault.errors:
            log.warning("link %s: %s", self.name, fault)
        self.last_fault = fault

    async def execute(self, command: Command, priority: Priority | None = None) -> Answer:
        """Send ``command`` and return its answer (``Ack`` or ``DataReply``).

        Raises ``ControllerRefused`` (;E), ``LinkTimeout``, ``LinkDown`` or ``ProtocolError``.
        Writes default to the write priority, everything else to the poll priority.
        """
        if priority is None:
            priority = Priority.WRITE if command.is_write else Priority.POLL
        return await self.submit(lambda: self._run_command(command), priority)

    # --- typed operations -------------------------------------------------------------------

    async def read(self, address: int, count: int = 1, priority: Priority = Priority.POLL) -> bytes:
        """Read 1 or 2 bytes of the memory map."""
        answer = await self.execute(cmds.read_bytes(address, count), priority)
        return cmds.parse_read_reply(address, count, _data(answer).body_hex)

    async def write_word(self, address: int, value: int) -> None:
        await self.execute(cmds.write_word(address, value))

    async def write_byte(self, address: int, value: int) -> None:
        await self.execute(cmds.write_byte(address, value))

    async def update_byte(self, address: int, bit: int, value: bool) -> int:
        """Set one bit of a relay byte: read the byte fresh, write it back at once.

        Both transactions run back to back on the line, ahead of any poll; the ladder could still
        change another bit of the same byte between the read and the write (one scan at most).
        """

        async def op() -> int:
            answer = await self._run_command(cmds.read_bytes(address, 1))
            current = cmds.parse_read_reply(address, 1, _data(answer).body_hex)[0]
            new = (current | (1 << bit)) if value else (current & ~(1 << bit) & 0xFF)
            await self._run_command(cmds.write_byte(address, new))
            return new

        return await self.submit(op, Priority.WRITE)

    async def set_mode(self, mode: Mode) -> None:
        await self.execute(cmds.set_mode(mode))

    async def probe(self) -> FrnInfo:
        answer = await self.execute(cmds.read_frn())
        return cmds.parse_frn_reply(_data(answer).body_hex)

    async def upload_program(self, controller: ControllerType) -> bytes:
        """Every program block in order (the controller must be in program mode)."""

        async def op() -> bytes:
            blocks = bytearray()
            for expected in range(controller.block_count):
                answer = await self._run_command(cmds.upload_block())
                block = cmds.parse_upload_reply(_data(answer).body_hex, controller=controller)
                if block.block != expected:
                    raise ProtocolError(f"upload: expected block 0x{expected:02X}, got 0x{block.block:02X}")
                blocks += block.data
            return bytes(blocks)

        return await self.submit(op, Priority.WRITE)

    async def download_program(self, controller: ControllerType, program: bytes) -> None:
        """Download every block in order (program mode).  ``program`` is block_count * 15 bytes."""
        size = controller.block_count * cmds.BLOCK_SIZE
        if len(program) != size:
            raise ProtocolError(f"download: a {controller.name} program is {size} bytes, got {len(program)}")
        commands = [
            cmds.download_block(block, program[block * 15 : block * 15 + 15], controller=controller)
            for block in range(controller.block_count)
        ]

        async def op() -> None:
            for command in commands:
                await self._run_command(command)

        await self.submit(op, Priority.WRITE)


def _next_id(msg_id: int) -> int:
    """The ID that follows ``msg_id`` (01..7F, then 01 again)."""
    return 1 if msg_id >= MAX_ID else msg_id + 1


def _wake(waiter: asyncio.Future[None]) -> None:
    if not waiter.done():
        waiter.set_result(None)


def _data(answer: Answer) -> DataReply:
    if not isinstance(answer, DataReply):
        raise ProtocolError("expected a data reply, got an acknowledge")
    return answer
