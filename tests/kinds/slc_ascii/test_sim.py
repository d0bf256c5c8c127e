"""The SLC 100/150 simulator's rules, driven sans-I/O through ``receive(data, now)``.

Every rule is the manual's (shared/docs/slc100-150-ascii-protocol.md): message IDs and ``;I``, ``;Z``,
mode rules, protect bits, value limits, program upload and download, power-up state.
"""

from __future__ import annotations

import pytest

from gateway.kinds.slc_ascii.sim import FaultPlan, SlcAsciiSimulator
from gateway.protocols.slc_ascii import commands as cmds
from gateway.protocols.slc_ascii.commands import Command, ControllerType, Mode, ReplyKind, TimeoutClass
from gateway.protocols.slc_ascii.framing import (
    NEED_DATA,
    Ack,
    DataReply,
    Fault,
    Garbled,
    IdMismatch,
    Refused,
    ReplyDecoder,
    ReplyEvent,
    encode_retransmit,
    frame_command,
)
from gateway.sim import create_simulator


def raw(code: int, params_hex: str = "") -> Command:
    """A command the builders would refuse to make (the simulator must refuse it too)."""
    return Command(code, bytes.fromhex(params_hex), "raw", ReplyKind.ACK, TimeoutClass.NORMAL)


class Host:
    """Talks to a simulator the way a host would, with its own clock."""

    def __init__(self, sim: SlcAsciiSimulator) -> None:
        self.sim = sim
        self.now = 0.0
        self.decoder = ReplyDecoder()
        self.next_id = 0

    def send(self, data: bytes) -> list[ReplyEvent]:
        self.now += 0.01
        out = self.sim.receive(data, self.now)
        self.decoder.receive_data(b"".join(o.data for o in out))
        events: list[ReplyEvent] = []
        while (event := self.decoder.next_event()) is not NEED_DATA:
            events.append(event)
        return events

    def raw_send(self, command: Command, msg_id: int) -> list[ReplyEvent]:
        return self.send(frame_command(command, msg_id))

    def do(self, command: Command) -> ReplyEvent:
        """Send with the next ID in sequence and return the single reply."""
        msg_id = self.next_id
        self.next_id = 1 if msg_id >= 0x7F else msg_id + 1
        events = self.raw_send(command, msg_id)
        assert len(events) == 1, events
        event = events[0]
        if isinstance(event, (Ack, DataReply, Refused)):
            assert event.msg_id == msg_id
        return event

    def read(self, address: int, count: int = 1) -> bytes:
        event = self.do(cmds.read_bytes(address, count))
        assert isinstance(event, DataReply), event
        return cmds.parse_read_reply(address, count, event.body_hex)

    def mode(self, mode: Mode) -> None:
        assert isinstance(self.do(cmds.set_mode(mode)), Ack)


@pytest.fixture
def sim() -> SlcAsciiSimulator:
    return SlcAsciiSimulator(ControllerType.SLC150, ladder=False)


@pytest.fixture
def host(sim: SlcAsciiSimulator) -> Host:
    return Host(sim)


# ---------------------------------------------------------------------------------------------
# FRN, reads


@pytest.mark.parametrize(
    ("model", "body"), [(ControllerType.SLC150, "021FFE1547"), (ControllerType.SLC100, "021FFE1005")]
)
def test_frn_reply(model: ControllerType, body: str) -> None:
    host = Host(SlcAsciiSimulator(model, ladder=False))
    event = host.do(cmds.read_frn())
    assert event == DataReply(body, 0)
    info = cmds.parse_frn_reply(body)
    assert info.controller is model


def test_read_words_and_bytes(host: Host, sim: SlcAsciiSimulator) -> None:
    assert host.read(0x40, 2) == (100).to_bytes(2, "big")  # 901.PRE
    assert host.read(0x7E, 2) == (0x8000 | 500).to_bytes(2, "big")  # 932.PRE, protected
    assert host.read(0x84, 2) == b"\x00\x00"
    sim.memory[0xA6] = 0x5A
    assert host.read(0xA6) == b"\x5a"


def test_a_command_fed_byte_by_byte_is_answered_once_at_its_cr(host: Host) -> None:
    frame = frame_command(cmds.read_frn(), 0)
    for i in range(len(frame) - 1):
        assert host.send(frame[i : i + 1]) == []
    assert host.send(frame[-1:]) == [DataReply("021FFE1547", 0)]


def test_commands_with_parity_bit_set_are_understood(host: Host) -> None:
    frame = bytes(b | 0x80 for b in frame_command(cmds.read_frn(), 0))
    assert host.send(frame) == [DataReply("021FFE1547", 0)]


@pytest.mark.parametrize(
    "command",
    [
        raw(0x02, "0003" "0040"),  # count 3
        raw(0x02, "0001" "0080"),  # checksum of the last ladder: not to be accessed
        raw(0x02, "0001" "00EC"),  # ** region
        raw(0x02, "0002" "0085"),  # second byte runs into the force select table? (86H is readable)
        raw(0x02, "0001" "0101"),  # the mode byte is not in the read list
        raw(0x02, "0001" "0200"),  # beyond the memory map
        raw(0x09),  # unknown command code
        raw(0x02, "0001"),  # too few parameters
    ],
)
def test_illegal_reads_are_refused(host: Host, sim: SlcAsciiSimulator, command: Command) -> None:
    if command.params == bytes.fromhex("00020085"):
        # 84H-85H and 86H are all readable: this one is legal, read it to prove it, byte for byte.
        sim.memory[0x85], sim.memory[0x86] = 0x12, 0x34
        msg_id = host.next_id
        assert host.do(command) == DataReply("020085" "1234", msg_id)
        return
    assert isinstance(host.do(command), Refused)


def test_garbled_input_gets_no_answer(host: Host, sim: SlcAsciiSimulator) -> None:
    assert host.send(b"#010800A4\r") == []  # bad CRC
    assert host.send(b"#0108\r") == []  # too short
    assert sim.counters.garbled_in == 2
    assert sim.counters.commands == 0
    assert host.do(cmds.read_frn()) == DataReply("021FFE1547", 0)


# ---------------------------------------------------------------------------------------------
# Message IDs


def test_after_power_up_the_controller_expects_id_00(host: Host, sim: SlcAsciiSimulator) -> None:
    assert host.raw_send(cmds.write_word(0x40, 1), 5) == [IdMismatch(0)]
    assert sim.applied_writes == []
    assert sim.word(0x40) == 100
    assert host.raw_send(cmds.write_word(0x40, 1), 0) == [Ack(0)]
    assert sim.applied_writes == [("word", 0x40, 1)]


def test_ids_must_be_sequential(host: Host, sim: SlcAsciiSimulator) -> None:
    assert host.raw_send(cmds.read_frn(), 0) == [DataReply("021FFE1547", 0)]
    assert host.raw_send(cmds.read_frn(), 1) == [DataReply("021FFE1547", 1)]
    # skipping an ID: ;I with the last valid ID, not executed
    assert host.raw_send(cmds.write_word(0x42, 7), 3) == [IdMismatch(1)]
    assert sim.word(0x42) == 110
    # the expected ID is still 02
    assert host.raw_send(cmds.write_word(0x42, 7), 2) == [Ack(2)]
    assert sim.word(0x42) == 7
    assert sim.counters.id_mismatches == 1


def test_a_repeated_id_is_not_executed_twice(host: Host, sim: SlcAsciiSimulator) -> None:
    host.raw_send(cmds.read_frn(), 0)
    assert host.raw_send(cmds.write_word(0x44, 11), 1) == [Ack(1)]
    # The same message again (e.g. the host did not see the ;R): ;I01 says ID 01 was accepted.
    assert host.raw_send(cmds.write_word(0x44, 11), 1) == [IdMismatch(1)]
    assert sim.applied_writes == [("word", 0x44, 11)]


def test_id_00_is_always_accepted_and_restarts_the_sequence(host: Host) -> None:
    for msg_id in range(0, 6):
        host.raw_send(cmds.read_frn(), msg_id)
    assert host.raw_send(cmds.read_frn(), 0) == [DataReply("021FFE1547", 0)]
    assert host.raw_send(cmds.read_frn(), 6) == [IdMismatch(0)]
    assert host.raw_send(cmds.read_frn(), 1) == [DataReply("021FFE1547", 1)]


def test_ids_roll_over_from_7f_to_01(host: Host) -> None:
    for _ in range(0x80):
        assert isinstance(host.do(cmds.read_frn()), DataReply)
    # host.next_id is now 01 after 7F
    assert host.next_id == 1
    assert host.raw_send(cmds.read_frn(), 1) == [DataReply("021FFE1547", 1)]
    assert host.raw_send(cmds.read_frn(), 2) == [DataReply("021FFE1547", 2)]


def test_after_7f_an_id_of_00_is_still_accepted(host: Host) -> None:
    for msg_id in range(0x80):
        host.raw_send(cmds.read_frn(), msg_id)
    assert host.raw_send(cmds.read_frn(), 0) == [DataReply("021FFE1547", 0)]


# ---------------------------------------------------------------------------------------------
# ;Z


def test_retransmit_repeats_the_last_reply_with_its_id(host: Host, sim: SlcAsciiSimulator) -> None:
    host.do(cmds.read_frn())
    assert host.do(cmds.write_word(0x46, 12)) == Ack(1)
    assert host.send(encode_retransmit(0x55)) == [Ack(1)]  # "The SLC ignores the ID in this message"
    assert host.send(encode_retransmit(1)) == [Ack(1)]
    assert sim.applied_writes == [("word", 0x46, 12)]  # not executed again
    assert sim.counters.retransmits == 2
    # ;Z does not use up an ID: 02 is still expected
    assert host.raw_send(cmds.read_frn(), 2) == [DataReply("021FFE1547", 2)]
    assert host.send(encode_retransmit(0)) == [DataReply("021FFE1547", 2)]


def test_retransmit_repeats_a_refusal_but_not_an_id_mismatch(host: Host) -> None:
    host.raw_send(cmds.read_frn(), 0)
    assert host.raw_send(cmds.write_word(0x7E, 1), 1) == [Refused(1)]
    assert host.send(encode_retransmit(1)) == [Refused(1)]
    assert host.raw_send(cmds.read_frn(), 9) == [IdMismatch(1)]
    # ";Z ... retransmits its most recent acknowledge or data message": the answer to ID 01
    assert host.send(encode_retransmit(9)) == [Refused(1)]


def test_retransmit_after_an_id_mismatch_fetches_the_answer_of_the_accepted_copy(host: Host) -> None:
    # The host sent ID 01 twice (it missed the first ;R): ;I01 says 01 was accepted, ;Z gives its ;R.
    host.raw_send(cmds.read_frn(), 0)
    assert host.raw_send(cmds.write_word(0x40, 3), 1) == [Ack(1)]
    assert host.raw_send(cmds.write_word(0x40, 3), 1) == [IdMismatch(1)]
    assert host.send(encode_retransmit(1)) == [Ack(1)]


def test_retransmit_with_nothing_to_repeat_is_silent(host: Host) -> None:
    assert host.send(encode_retransmit(0)) == []


def test_retransmit_after_a_garbled_command_repeats_the_previous_reply(host: Host) -> None:
    # The host can tell its command was lost: the repeated reply carries the older ID.
    host.raw_send(cmds.read_frn(), 0)
    assert host.send(b"#0503004004D202B7\r") == []  # ID 02... bad CRC: ignored
    assert host.send(encode_retransmit(1)) == [DataReply("021FFE1547", 0)]


# ---------------------------------------------------------------------------------------------
# Modes


def test_mode_selection_in_any_mode(host: Host, sim: SlcAsciiSimulator) -> None:
    for mode in (Mode.PROGRAM, Mode.CONTINUOUS_TEST, Mode.SAVE_TO_EEPROM, Mode.PROGRAM, Mode.RUN):
        host.mode(mode)
        assert sim.mode == mode
    assert isinstance(host.do(raw(0x03, "0101" "81")), Refused)  # not one of the four data bytes
    assert sim.mode == Mode.RUN


def test_reads_and_writes_are_refused_in_program_mode(host: Host, sim: SlcAsciiSimulator) -> None:
    host.mode(Mode.PROGRAM)
    for command in (
        cmds.read_bytes(0x40, 2),
        cmds.write_word(0x40, 5),
        cmds.write_byte(0xA6, 1),
        cmds.read_sequencer_preset(0x10, 0),
        cmds.write_sequencer_preset(0x10, 0, 5),
        cmds.read_reset_accumulator(0x20),
        cmds.write_reset_accumulator(0x20, 5),
    ):
        assert isinstance(host.do(command), Refused), command.name
    assert isinstance(host.do(cmds.read_frn()), DataReply)  # FRN: all modes
    assert [w for w in sim.applied_writes if w[0] != "mode"] == []
    host.mode(Mode.CONTINUOUS_TEST)  # test mode: reads and writes allowed
    assert host.read(0x40, 2) == (100).to_bytes(2, "big")
    assert isinstance(host.do(cmds.write_word(0x40, 5)), Ack)


def test_upload_and_download_only_in_program_mode(host: Host, sim: SlcAsciiSimulator) -> None:
    before = bytes(sim.program)
    assert isinstance(host.do(cmds.upload_block()), Refused)
    block = cmds.download_block(0, bytes(15), controller=ControllerType.SLC150)
    assert isinstance(host.do(block), Refused)
    assert bytes(sim.program) == before
    host.mode(Mode.CONTINUOUS_TEST)
    assert isinstance(host.do(cmds.upload_block()), Refused)


# ---------------------------------------------------------------------------------------------
# Protect bits and value limits


def test_write_to_a_protected_preset_is_refused(host: Host, sim: SlcAsciiSimulator) -> None:
    assert isinstance(host.do(cmds.write_word(0x7E, 5)), Refused)  # 932.PRE
    assert isinstance(host.do(cmds.write_word(0x3E, 5)), Refused)  # 932.ACC
    assert sim.word(0x7E) == 0x8000 | 500
    assert sim.word(0x3E) == 0x8000 | 7
    assert sim.applied_writes == []
    assert sim.counters.refusals == 2
    assert isinstance(host.do(cmds.write_word(0x7C, 5)), Ack)  # 931.PRE is not protected
    assert sim.word(0x7C) == 5


@pytest.mark.parametrize(
    ("command", "ok"),
    [
        (raw(0x03, "0040" "270F"), True),  # 9999
        (raw(0x03, "0040" "2710"), False),  # 10000: "limited to be less than 2710H"
        (raw(0x03, "0040" "FFFF"), False),
        (raw(0x03, "0041" "0001"), False),  # odd address
        (raw(0x03, "0080" "0001"), False),  # beyond the presets
        (raw(0x03, "0000" "0000"), True),
        (raw(0x03, "00A6" "FF"), True),  # relays 701-708
        (raw(0x03, "00B4" "01"), True),  # relays 813-820
        (raw(0x03, "00B5" "01"), False),  # relays 821-: not writable
        (raw(0x03, "00A5" "01"), False),  # inputs
        (raw(0x03, "0096" "01"), False),  # outputs
        (raw(0x06, "0010" "00" "0000"), False),  # sequencer preset must be non-zero
        (raw(0x06, "0010" "00" "2710"), False),  # and less than 2710H
        (raw(0x06, "0010" "04" "0001"), False),  # step 4 of a 4-step sequencer
        (raw(0x06, "0012" "00" "0001"), False),  # rung without a sequencer
        (raw(0x06, "0010" "03" "270F"), True),
        (raw(0x07, "0020" "2710"), False),  # reset accumulator limit
        (raw(0x07, "0030" "0001"), False),  # rung without a reset instruction
        (raw(0x07, "0020" "270F"), True),
    ],
)
def test_value_and_address_limits(host: Host, sim: SlcAsciiSimulator, command: Command, ok: bool) -> None:
    event = host.do(command)
    assert isinstance(event, Ack if ok else Refused)
    assert len(sim.applied_writes) == (1 if ok else 0)


def test_sequencer_and_reset_rung_commands(host: Host, sim: SlcAsciiSimulator) -> None:
    event = host.do(cmds.read_sequencer_preset(0x10, 2))
    assert isinstance(event, DataReply)
    assert cmds.parse_word_reply(event.body_hex) == cmds.WordReply(910, 300, False)
    assert isinstance(host.do(cmds.write_sequencer_preset(0x10, 2, 333)), Ack)
    event = host.do(cmds.read_sequencer_preset(0x10, 2))
    assert isinstance(event, DataReply)
    assert cmds.parse_word_reply(event.body_hex).value == 333
    assert isinstance(host.do(cmds.read_sequencer_preset(0x11, 3)), Refused)
    assert isinstance(host.do(cmds.write_reset_accumulator(0x20, 42)), Ack)
    assert sim.word(2 * (920 - 901)) == 42
    event = host.do(cmds.read_reset_accumulator(0x20))
    assert isinstance(event, DataReply)
    assert cmds.parse_word_reply(event.body_hex) == cmds.WordReply(920, 42, False)
    assert sim.applied_writes == [("sequencer", 0x10 * 256 + 2, 333), ("reset", 0x20, 42)]


# ---------------------------------------------------------------------------------------------
# Upload and download


@pytest.mark.parametrize("model", [ControllerType.SLC150, ControllerType.SLC100])
def test_upload_returns_every_block_in_order(model: ControllerType) -> None:
    sim = SlcAsciiSimulator(model, ladder=False)
    host = Host(sim)
    host.mode(Mode.PROGRAM)
    data = bytearray()
    for expected in range(model.block_count):
        event = host.do(cmds.upload_block())
        assert isinstance(event, DataReply)
        block = cmds.parse_upload_reply(event.body_hex, controller=model)
        assert block.block == expected
        data += block.data
    assert len(data) == model.block_count * 15
    assert data[:-8] == sim.program[:-8]
    assert data[-8:] == bytes(8)  # "8 bytes of fill"
    # the transfer is complete: a mode change is allowed again, and a new upload starts at 00
    event = host.do(cmds.upload_block())
    assert isinstance(event, DataReply)
    assert cmds.parse_upload_reply(event.body_hex).block == 0


def test_no_mode_change_during_a_transfer_except_program(host: Host, sim: SlcAsciiSimulator) -> None:
    host.mode(Mode.PROGRAM)
    host.do(cmds.upload_block())
    host.do(cmds.upload_block())
    assert isinstance(host.do(cmds.set_mode(Mode.RUN)), Refused)
    block = cmds.download_block(0, bytes(15), controller=ControllerType.SLC150)
    assert isinstance(host.do(block), Refused)  # no load direction change either
    host.mode(Mode.PROGRAM)  # re-entering program mode resets the procedure
    event = host.do(cmds.upload_block())
    assert isinstance(event, DataReply)
    assert cmds.parse_upload_reply(event.body_hex).block == 0
    assert sim.mode == Mode.PROGRAM


def test_download_clears_nvram_and_writes_every_block(host: Host, sim: SlcAsciiSimulator) -> None:
    model = ControllerType.SLC150
    program = bytes((i * 13 + 1) & 0xFF for i in range(model.block_count * 15 - 8)) + bytes(8)
    host.mode(Mode.PROGRAM)
    first = cmds.download_block(0, program[:15], controller=model)
    assert isinstance(host.do(first), Ack)
    assert sim.program[:15] == program[:15]
    assert sim.program[15:] == bytes(len(sim.program) - 15)  # NVRAM cleared when the download began
    # out of sequence: refused
    assert isinstance(host.do(cmds.download_block(2, program[30:45], controller=model)), Refused)
    for block in range(1, model.block_count):
        command = cmds.download_block(block, program[block * 15 : block * 15 + 15], controller=model)
        assert isinstance(host.do(command), Ack), block
    assert bytes(sim.program) == program
    assert sim.applied_writes[-1] == ("program", 0, len(program))
    host.mode(Mode.RUN)  # allowed again after the last block


def test_reentering_program_mode_during_a_download_leaves_nvram_cleared(host: Host, sim: SlcAsciiSimulator) -> None:
    host.mode(Mode.PROGRAM)
    host.do(cmds.download_block(0, bytes(range(15)), controller=ControllerType.SLC150))
    host.mode(Mode.PROGRAM)
    assert sim.program[15:] == bytes(len(sim.program) - 15)
    assert isinstance(host.do(cmds.download_block(1, bytes(15), controller=ControllerType.SLC150)), Refused)


# ---------------------------------------------------------------------------------------------
# Power cycles


def test_power_cycle_resets_ids_and_keeps_memory(host: Host, sim: SlcAsciiSimulator) -> None:
    for _ in range(3):
        host.do(cmds.read_frn())
    host.do(cmds.write_word(0x48, 77))
    sim.power_cycle()
    assert sim.counters.power_cycles == 1
    assert host.send(encode_retransmit(4)) == []  # the last reply is gone
    assert host.raw_send(cmds.read_frn(), 5) == [IdMismatch(0)]  # expects 00 again
    assert host.raw_send(cmds.read_bytes(0x48, 2), 0) == [DataReply("020048004D", 0)]
    assert sim.word(0x48) == 77


def test_power_cycle_every_n_frames(sim: SlcAsciiSimulator) -> None:
    sim = SlcAsciiSimulator(ControllerType.SLC150, faults=FaultPlan(power_cycle_every=4), ladder=False)
    host = Host(sim)
    replies = [host.raw_send(cmds.read_frn(), msg_id) for msg_id in range(6)]
    # frames 1-3 accepted; power cycle before the 4th: it is answered ;I00
    assert replies[3] == [IdMismatch(0)]
    assert replies[4] == [IdMismatch(0)]
    assert sim.counters.power_cycles == 1
    assert host.send(encode_retransmit(0)) == []  # nothing accepted since power-up; not a frame either
    assert host.raw_send(cmds.read_frn(), 0) == [DataReply("021FFE1547", 0)]  # 7th frame
    host.raw_send(cmds.read_frn(), 1)  # 8th frame: power cycle again
    assert sim.counters.power_cycles == 2


# ---------------------------------------------------------------------------------------------
# Fault injection


def test_dropped_replies_are_counted(sim: SlcAsciiSimulator) -> None:
    sim = SlcAsciiSimulator(ControllerType.SLC150, faults=FaultPlan(drop=3, seed=7), ladder=False)
    host = Host(sim)
    answered = sum(len(host.raw_send(cmds.read_frn(), 0)) for _ in range(300))
    assert sim.counters.dropped > 0
    assert answered + sim.counters.dropped == 300
    assert 50 < sim.counters.dropped < 150  # about 1 in 3
    assert sim.counters.commands == 300  # dropped replies were still executed


def test_garbled_replies_never_decode_as_valid(sim: SlcAsciiSimulator) -> None:
    sim = SlcAsciiSimulator(ControllerType.SLC150, faults=FaultPlan(garble=2, seed=3), ladder=False)
    host = Host(sim)
    good = garbled = 0
    for _ in range(400):
        for event in host.send(frame_command(cmds.read_bytes(0x40, 2), 0)):
            if isinstance(event, Garbled):
                garbled += 1
            else:
                assert event == DataReply("0200400064", 0)
                good += 1
    assert sim.counters.garbled_out > 100
    # A truncated reply shows up as garbled only when the next frame starts (the last one may still
    # be pending); a bit flipped into a leading character splits one reply into two garbled lines.
    assert garbled >= sim.counters.garbled_out - 1
    assert good + sim.counters.garbled_out == 400


def test_fault_injection_is_reproducible_with_a_seed() -> None:
    def run(seed: int) -> list[bytes]:
        sim = SlcAsciiSimulator(ControllerType.SLC150, faults=FaultPlan(garble=3, drop=4, seed=seed), ladder=False)
        return [b"".join(o.data for o in sim.receive(frame_command(cmds.read_frn(), 0), i)) for i in range(50)]

    assert run(5) == run(5)
    assert run(5) != run(6)


def test_fault_every_n_commands(sim: SlcAsciiSimulator) -> None:
    sim = SlcAsciiSimulator(ControllerType.SLC150, faults=FaultPlan(fault_every=3), ladder=False)
    host = Host(sim)
    # A frame with a wrong ID is not a command: no ;T for it.
    assert host.raw_send(cmds.read_frn(), 9) == [IdMismatch(0)]
    events: list[ReplyEvent] = []
    for msg_id in range(6):
        events += host.raw_send(cmds.read_frn(), msg_id)
        if msg_id == 2:
            # after the 3rd command: ;T, and an error bit for 84H-85H
            assert events[-1] == Fault(0)
            # another frame with a wrong ID right after the ;T: still no second ;T
            assert host.raw_send(cmds.read_frn(), 0x50) == [IdMismatch(2)]
    assert [type(e) for e in events].count(Fault) == 2
    assert sim.counters.faults == 2
    assert host.read(0x84, 2)[0] & 0x08  # error 8 (84H bit 3)
    assert cmds.decode_error_bits(*host.read(0x84, 2)) == (8,)


def test_reply_delay_is_reported_with_each_output() -> None:
    sim = SlcAsciiSimulator(ControllerType.SLC150, faults=FaultPlan(delay=0.25), ladder=False)
    outputs = sim.receive(frame_command(cmds.read_frn(), 0), 0.0)
    assert [o.delay for o in outputs] == [0.25]


def test_fault_options_from_a_url() -> None:
    device = create_simulator("slc100", {"garble": "5", "drop": "7", "power_cycle_every": "50", "seed": "1",
                                         "ladder": "0"})
    assert isinstance(device, SlcAsciiSimulator)
    assert device.model is ControllerType.SLC100
    assert (device.faults.garble, device.faults.drop, device.faults.power_cycle_every) == (5, 7, 50)
    with pytest.raises(ValueError, match="unknown"):
        FaultPlan.from_options({"bogus": "1"})
    with pytest.raises(ValueError, match="not a number"):
        FaultPlan.from_options({"drop": "x"})
    with pytest.raises(ValueError, match="negative"):
        FaultPlan.from_options({"drop": "-1"})


# ---------------------------------------------------------------------------------------------
# Ladder


def test_frozen_ladder_changes_nothing(host: Host, sim: SlcAsciiSimulator) -> None:
    before = bytes(sim.memory)
    for _ in range(20):
        host.now += 1.0
        host.do(cmds.read_frn())
    assert bytes(sim.memory) == before


def test_running_ladder_times_and_counts() -> None:
    sim = SlcAsciiSimulator(ControllerType.SLC150, ladder=True)
    host = Host(sim)
    first = host.read(0x00, 2)  # 901.ACC
    host.now += 0.55
    second = host.read(0x00, 2)
    assert int.from_bytes(second, "big") > int.from_bytes(first, "big")
    host.mode(Mode.PROGRAM)  # the ladder stops out of run mode
    before = bytes(sim.memory)
    host.now += 5.0
    host.do(cmds.read_frn())
    assert bytes(sim.memory) == before
