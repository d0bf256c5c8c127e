"""The sending side of the SLC 100/150 session (``slc_ascii/sender.py``): message IDs on the wire.

From the manual (shared/docs/slc100-150-ascii-protocol.md, "Format of Transmission", [ID]):

* "The programming device must increment this number by one for each transmission to the
  controller, with the exception of transmission of messages containing ';Z'."
* "An otherwise valid message with an [ID] of 00 ... is always accepted, and restarts the message
  identifier numbering sequence, with the next message to have an expected [ID] of 01."
* "The identifier will roll over from 127D to 01" - never to 00.
* "Upon power up, the controller expects an [ID] of 00."
* ";Z ... retransmits its most recent acknowledge or data message with the same ID as was sent
  previously ... the message ID will not match if it was garbled.  In this case the command may be
  safely repeated": a repeated command keeps its ID (the controller refuses a second copy of an
  accepted message, "sequential order").

The session is driven against the simulated SLC 150 over a line of this test's, which can lose a
frame either way; every frame the session sends is decoded as the controller sees it.
"""

from __future__ import annotations

from gateway.kinds.slc_ascii.sim import SlcAsciiSimulator
from gateway.protocols.need_data import NEED_DATA
from gateway.protocols.slc_ascii import commands as cmds
from gateway.protocols.slc_ascii.commands import Command
from gateway.protocols.slc_ascii.framing import CommandDecoder, CommandFrame, HostEvent, RetransmitRequest
from gateway.protocols.slc_ascii.sender import next_id
from gateway.protocols.slc_ascii.transaction import SlcSession, SlcVerdict
from gateway.protocols.slc_ascii.write_proof import Result

READ = cmds.read_bytes(0x40, 2)
FRN = cmds.read_frn()


class Line:
    """The session, the simulated controller, and a line that loses the frames it is told to."""

    def __init__(self) -> None:
        self.sim = SlcAsciiSimulator(ladder=False)
        self.session = SlcSession(timeout=0.3, retries=3)
        self.now = 0.0
        self.sent: list[HostEvent] = []
        self.lose_to_controller = 0
        self.lose_to_host = 0

    def _to_controller(self, data: bytes) -> None:
        for frame in data.split(b"\r"):
            if not frame:
                continue
            decoder = CommandDecoder()
            decoder.receive_data(frame + b"\r")
            event = decoder.next_event()
            assert event is not NEED_DATA
            self.sent.append(event)
            if self.lose_to_controller:
                self.lose_to_controller -= 1
                continue
            for out in self.sim.receive(frame + b"\r", self.now):
                if self.lose_to_host:
                    self.lose_to_host -= 1
                    continue
                self.now += 0.01 + out.delay
                self.session.receive_data(out.data, self.now)

    def run(self, command: Command) -> Result:
        session = self.session
        session.start(command, self.now)
        for _ in range(1000):
            if session.result is not None:
                return session.take_result()
            data = session.data_to_send()
            if data:
                self._to_controller(data)
                continue
            deadline = session.next_deadline()
            assert deadline is not None
            self.now = max(self.now, deadline)
            session.handle_timeout(self.now)
        raise AssertionError("the session does not finish")

    def ids_of(self, command: Command) -> list[int]:
        """The IDs the command went with, in order (ID 00 resync reads apart)."""
        return [e.msg_id for e in self.sent
                if isinstance(e, CommandFrame) and e.code == command.code and e.params == command.params]


def test_the_id_after_each_id() -> None:
    assert next_id(0x00) == 0x01  # after ID 00 the controller expects 01
    assert next_id(0x01) == 0x02
    assert next_id(0x7E) == 0x7F
    assert next_id(0x7F) == 0x01  # 127D rolls over to 01, never to 00


def test_after_connecting_the_first_message_has_id_00_and_the_command_01() -> None:
    line = Line()
    assert line.run(READ).verdict is SlcVerdict.DONE
    first = line.sent[0]
    assert isinstance(first, CommandFrame) and first.msg_id == 0x00
    assert line.ids_of(READ) == [0x01]


def test_each_transmission_takes_the_next_id_and_127_rolls_over_to_01() -> None:
    line = Line()
    for _ in range(130):
        assert line.run(READ).verdict is SlcVerdict.DONE
    ids = line.ids_of(READ)
    assert ids == [*range(0x01, 0x80), 0x01, 0x02, 0x03]
    assert [e.msg_id for e in line.sent if isinstance(e, CommandFrame)].count(0x00) == 1  # only the first resync


def test_a_z_takes_no_id() -> None:
    line = Line()
    line.run(READ)  # ID 00 resync, then ID 01
    line.lose_to_host = 1  # the reply to ID 02 is lost: the session asks for it with ;Z
    assert line.run(READ).verdict is SlcVerdict.DONE
    assert any(isinstance(e, RetransmitRequest) for e in line.sent)
    line.run(READ)
    assert line.ids_of(READ) == [0x01, 0x02, 0x03]


def test_a_command_the_controller_did_not_get_goes_again_with_its_id() -> None:
    """The write is lost on the way: ``;Z`` fetches the previous reply (the ID does not match), so
    the controller did not get it and the same copy goes again, under the same ID; it runs once."""
    line = Line()
    line.run(READ)  # IDs 00 and 01
    write = cmds.write_word(0x40, 0x1234)
    line.lose_to_controller = 1
    assert line.run(write).verdict is SlcVerdict.DONE
    assert line.ids_of(write) == [0x02, 0x02]
    line.run(READ)
    assert line.ids_of(READ) == [0x01, 0x03]


def test_a_new_stream_begins_again_with_id_00() -> None:
    """``connected()``: the controller at the other end may have been powered up, and then expects
    ID 00; the numbering restarts there."""
    line = Line()
    for _ in range(3):
        line.run(READ)
    line.session.connected()
    line.sent.clear()
    line.now += 5.0
    assert line.run(READ).verdict is SlcVerdict.DONE
    first = line.sent[0]
    assert isinstance(first, CommandFrame) and first.msg_id == 0x00
    assert line.ids_of(READ) == [0x01]
