"""The runner of a DF1 target link: owns the port, answers the MSG instructions a PLC sends.

A thin loop around two sans-I/O cores: :class:`~gateway.protocols.df1.full_duplex.responder.Df1Responder`
(the full-duplex link layer: ACK / NAK / ENQ, duplicates, reply retransmission) and
:class:`~gateway.protocols.df1.pccc.target.PcccTarget` (the commands against the data table).
For each new command, in this order, without an ``await`` in between:

1. the target executes it against the table (a write is checked whole, then applied whole);
2. what it wrote is committed to ``persist`` (when configured) and put in the unit's image;
3. the reply is queued on the link.

So no reply acknowledges a write that is not on disk, and no Modbus reader sees part of a write.
When the commit fails, the reply is STS 40 hex ("host could not complete function due to hardware
fault", 1770-6.5.16 p. 8-3) instead of success, what the command wrote is taken back out of the
table, and the error is logged: the PLC's MSG errors out and its ladder sends it again.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable, Sequence
from typing import Unpack

from gateway.errors import GatewayError
from gateway.line_driver import LineDriver, LineDriverOptions
from gateway.link_health import LineQuality
from gateway.protocols.df1.framing import DEFAULT_ACK_TIMEOUT, NEED_DATA, Checksum
from gateway.protocols.df1.full_duplex.responder import Df1Responder
from gateway.protocols.df1.full_duplex.responder_events import CommandReceived, DuplicateReceived, ReplyLost
from gateway.protocols.df1.pccc import PcccHeader, Sts, encode_reply
from gateway.protocols.df1.pccc.target import PcccTarget, TargetReply
from gateway.protocols.df1.pccc.target_table import ElementRef
from gateway.streams import SerialSettings

__all__ = ["TargetRunner"]

log = logging.getLogger("gateway.df1.target")
audit = logging.getLogger("gateway.audit")


class TargetRunner(LineDriver):
    """One target link's port: the responder and the PCCC target (module doc)."""

    def __init__(
        self,
        url: str,
        *,
        settings: SerialSettings,
        target: PcccTarget,
        station: int,
        checksum: Checksum,
        duplicate_detect: bool = True,
        check_dst: bool = False,
        ack_timeout: float = DEFAULT_ACK_TIMEOUT,
        **line: Unpack[LineDriverOptions],
    ) -> None:
        super().__init__(url, settings=settings, **line)
        self.target = target
        self.responder = Df1Responder(station=station, checksum=checksum, duplicate_detect=duplicate_detect,
                                      check_dst=check_dst, ack_timeout=ack_timeout)
        #: commits and image updates of what a command wrote (set by the unit; GatewayError: not committed)
        self.on_written: Callable[[Sequence[ElementRef]], None] = lambda refs: None
        #: the PLC spoke at ``now`` (set by the unit: its values are not silent)
        self.on_heard: Callable[[float], None] = lambda now: None
        #: the last STS other than 0 sent to the PLC (status register 1002)
        self.last_sts = 0
        #: commands refused (STS other than 0)
        self.refused = 0

    @property
    def duplicates(self) -> int:
        return self.responder.counters.duplicates

    def metrics(self) -> dict[str, float]:
        """Per-link numbers for ``/metrics`` (``slc_gateway_link_<key>``)."""
        c = self.responder.counters
        return {
            "target_commands": float(c.commands_delivered),
            "target_duplicates": float(c.duplicates),
            "target_refused": float(self.refused),
            "target_bad_frames": float(c.bad_frames),
            "target_naks_sent": float(c.naks_sent),
            "target_enqs_received": float(c.enqs_received),
            "target_reply_retransmissions": float(c.retransmissions),
            "target_replies_lost": float(c.replies_lost),
        }

    # --- LineDriver hooks ------------------------------------------------------------------------

    def on_connect(self) -> None:
        self.responder.reset()
        while self.responder.next_event() is not NEED_DATA:
            pass  # replies lost with the old connection: their commands were executed and committed

    def abort(self, exc: GatewayError) -> None:
        """Nothing waits on the line: a command's reply is queued at once."""

    def data_received(self, data: bytes) -> None:
        now = asyncio.get_running_loop().time()
        self.responder.feed(data, now)
        self._pump(now)

    # --- the loop ------------------------------------------------------------------------------

    def _pump(self, now: float) -> None:
        responder = self.responder
        while (event := responder.next_event()) is not NEED_DATA:
            if isinstance(event, CommandReceived):
                self._execute(event, now)
            elif isinstance(event, DuplicateReceived):
                self.on_heard(now)
                log.debug("link %s: duplicate of TNS %d from node %d: acknowledged, not run again", self.name,
                          event.tns, event.src)
            elif isinstance(event, ReplyLost):
                log.info("link %s: reply to TNS %d lost (%s); the PLC's MSG times out", self.name,
                         PcccHeader.decode(event.packet).tns, event.reason.value)
        self._counters_from_core()
        out = responder.data_to_send()
        if out and self.connected:
            self.send(out)
        self.follow_deadline(responder.next_deadline())

    def _execute(self, command: CommandReceived, now: float) -> None:
        self.on_heard(now)
        result = self.target.execute(command.packet, now)
        reply = result.reply
        if reply is None:  # not a command (a reply sent to us): no answer, decided by the target
            self.responder.no_reply(command.packet)
            return
        if result.written:
            reply = self._commit(command, result)
        sts = PcccHeader.decode(reply).sts
        if sts:
            self.last_sts = sts
            self.refused += 1
            self.counters.errors += 1  # a command the PLC's MSG gets an error for
        self.note_result(True)
        self.responder.send_reply(reply, now)

    def _commit(self, command: CommandReceived, result: TargetReply) -> bytes:
        assert result.reply is not None
        try:
            self.on_written(result.written)
        except GatewayError as exc:
            log.error("link %s: %s", self.name, exc)
            return encode_reply(PcccHeader.decode(command.packet), sts=Sts.HOST_HARDWARE_FAULT)
        # DEBUG: a PLC's MSG may write every scan; a Modbus client's write is logged at INFO
        audit.debug("link %s: node %d wrote %s (TNS %d)", self.name, command.src,
                   ", ".join(f"{self.target.table[r.file].name}:{r.element}" for r in result.written), command.tns)
        return result.reply

    def _counters_from_core(self) -> None:
        c = self.responder.counters
        self.counters.crc_errors = c.bad_frames
        self.counters.retries_by_kind["nak"] = c.naks_received
        self.counters.retries_by_kind["enq"] = c.enqs_sent
        self.counters.retries_by_kind["enq_received"] = c.enqs_received

    def on_deadline(self, now: float) -> None:
        self.responder.handle_timeout(now)
        self._pump(now)

    def line_quality(self) -> LineQuality:
        """Bad frames received (NAKed), DLE NAKs the PLC sent for our replies, and the replies sent again."""
        return LineQuality(check_errors=self.counters.crc_errors, timeouts=self.counters.timeouts,
                           naks=self.responder.counters.naks_received,
                           retransmits=self.responder.counters.retransmissions)
