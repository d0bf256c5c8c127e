"""Each reading of the SLC 100/150 manual the simulator can take, byte for byte.

``docs/develop/controller-variants.md`` lists them with the manual's words; the driver's behaviour
under each is tested in tests/protocols/slc_ascii/test_transaction.py (core) and tests/soak (whole gateway).
"""

from __future__ import annotations

import pytest

from gateway.kinds.slc_ascii.sim import FaultPlan, SlcAsciiSimulator
from gateway.protocols.slc_ascii import commands as cmds
from gateway.protocols.slc_ascii.commands import Mode
from gateway.protocols.slc_ascii.framing import (
    encode_ack,
    encode_data_reply,
    encode_fault,
    encode_id_mismatch,
    encode_refused,
    encode_retransmit,
    frame_command,
)
from gateway.sim import create_simulator, parse_sim_url

READ = cmds.read_bytes(0x40, 2)
PRESET = encode_data_reply("020040" "0064", 1)


def sim_with(**variants: str) -> SlcAsciiSimulator:
    return SlcAsciiSimulator(ladder=False, variants=variants)


def wire(sim: SlcAsciiSimulator, data: bytes, now: float = 1.0) -> bytes:
    return b"".join(out.data for out in sim.receive(data, now))


def test_defaults_are_the_first_readings() -> None:
    assert sim_with().variants == {name: values[0] for name, values in SlcAsciiSimulator.VARIANTS.items()}


@pytest.mark.parametrize(("reading", "reported"), [("zero", 0), ("retained", 5)])
def test_power_up_id(reading: str, reported: int) -> None:
    sim = sim_with(power_up_id=reading)
    wire(sim, frame_command(READ, 0))
    for msg_id in range(1, 6):
        wire(sim, frame_command(READ, msg_id))
    sim.power_cycle()
    assert wire(sim, frame_command(READ, 6)) == encode_id_mismatch(reported)
    assert wire(sim, frame_command(READ, 0)) == encode_data_reply("020040" "0064", 0)  # 00 always accepted


@pytest.mark.parametrize(("reading", "answer"), [("silent", b""), ("error", encode_refused(7))])
def test_z_after_power_up(reading: str, answer: bytes) -> None:
    sim = sim_with(z_after_power_up=reading)
    wire(sim, frame_command(READ, 0))
    sim.power_cycle()
    assert wire(sim, encode_retransmit(7)) == answer


def test_late_replies_come_after_the_reply_time_and_hold_back_the_rest() -> None:
    sim = SlcAsciiSimulator(ladder=False, variants={"late_replies": "some"}, faults=FaultPlan(late_every=1))
    out = sim.receive(frame_command(READ, 0) + frame_command(READ, 1), 1.0)
    assert [o.delay for o in out] == [0.36, 0.36]  # in order: the second waits behind the first
    assert out[1].data == PRESET
    assert sim.counters.late == 2
    assert all(o.delay == 0 for o in sim_with(late_replies="none").receive(frame_command(READ, 0), 1.0))


@pytest.mark.parametrize(("reading", "clean"), [("no", True), ("once", False)])
def test_z_garbled_again(reading: str, clean: bool) -> None:
    sim = SlcAsciiSimulator(ladder=False, variants={"z_garbled_again": reading}, faults=FaultPlan(garble=1))
    first = wire(sim, frame_command(READ, 0))
    assert first != encode_data_reply("020040" "0064", 0)  # garbled (garble=1: every reply)
    sim.faults.garble = 0
    again = wire(sim, encode_retransmit(0))
    assert (again == encode_data_reply("020040" "0064", 0)) is clean
    assert wire(sim, encode_retransmit(0)) == encode_data_reply("020040" "0064", 0)  # only once


@pytest.mark.parametrize(("reading", "block"), [("restart", 0), ("keep", 3)])
def test_transfer_after_power_up(reading: str, block: int) -> None:
    sim = sim_with(transfer_after_power_up=reading)
    msg_id = 0
    for command in [cmds.set_mode(Mode.PROGRAM)] + [cmds.upload_block()] * 3:
        wire(sim, frame_command(command, msg_id))
        msg_id += 1
    sim.power_cycle()
    reply = wire(sim, frame_command(cmds.upload_block(), 0))
    assert reply.startswith(b":%02X" % block)


@pytest.mark.parametrize("reading", ["after_reply", "before_reply"])
def test_fault_report(reading: str) -> None:
    sim = SlcAsciiSimulator(ladder=False, variants={"fault_report": reading}, faults=FaultPlan(fault_every=1))
    reply = wire(sim, frame_command(READ, 0))
    answer = encode_data_reply("020040" "0064", 0)
    assert reply == (answer + encode_fault(0) if reading == "after_reply" else encode_fault(0) + answer)


def test_ack_is_unchanged_by_variants() -> None:
    sim = sim_with(power_up_id="retained", z_after_power_up="error")
    wire(sim, frame_command(READ, 0))
    assert wire(sim, frame_command(cmds.write_word(0x40, 5), 1)) == encode_ack(1)


def test_sim_urls_keep_every_variant_and_refuse_unknown_ones() -> None:
    url = "sim://slc150?variant=power_up_id=retained&variant=z_after_power_up=error,late_replies=some&drop=3"
    model, options = parse_sim_url(url)
    assert options["variant"] == "power_up_id=retained,z_after_power_up=error,late_replies=some"
    sim = create_simulator(model, options)
    assert isinstance(sim, SlcAsciiSimulator)
    assert (sim.variants["power_up_id"], sim.variants["z_after_power_up"], sim.variants["late_replies"]) == (
        "retained", "error", "some")
    assert sim.faults.drop == 3
    with pytest.raises(ValueError, match="unknown variant 'power_up'"):
        parse_sim_url("sim://slc150?variant=power_up=retained")
    with pytest.raises(ValueError, match="not one of zero, retained"):
        parse_sim_url("sim://slc100?variant=power_up_id=kept")
