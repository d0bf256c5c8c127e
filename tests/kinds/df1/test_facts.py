"""DF1 facts stated once, with the values the manuals give; every layer takes them from there.

Manuals: 1747-RM001G (SLC 500 instruction set, ch. 13, channel 0 configuration), 1766-RM001A
(MicroLogix 1400 instruction set, DF1 half-duplex master parameters), 1770-6.5.16 (DF1 protocol
and command set).
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from dataclasses import astuple
from typing import get_args

from gateway.app import describe_map
from gateway.config import parse_config
from gateway.kinds import df1
from gateway.kinds.df1 import tool
from gateway.kinds.df1.build import build_line, size_limits
from gateway.kinds.df1.config import Df1LinkConfig, group_lines
from gateway.kinds.df1.full.driver import Df1Driver
from gateway.kinds.df1.half.driver import Df1HalfDuplexLine, Df1Station
from gateway.kinds.df1.plc5_unit import Plc5Unit
from gateway.kinds.df1.sim import plc5 as sim_plc5
from gateway.kinds.df1.sim import slc500_data, slc500_processor
from gateway.kinds.df1.sim.df1_multidrop import LineOptions
from gateway.kinds.df1.sim.slc500_options import Slc500Options
from gateway.kinds.df1.target.build import build_target
from gateway.kinds.df1.target.driver import TargetRunner
from gateway.kinds.df1.target.unit import TargetUnit
from gateway.kinds.df1.unit import Df1Unit
from gateway.protocols.df1.address import SIGNED_FILE_TYPES, FileType, element_words, parse_address
from gateway.protocols.df1.framing import DEFAULT_ACK_TIMEOUT, DEFAULT_CHECKSUM, Checksum
from gateway.protocols.df1.full_duplex.datalink import Df1DataLink
from gateway.protocols.df1.full_duplex.responder import Df1Responder
from gateway.protocols.df1.full_duplex.station import FullDuplexStation
from gateway.protocols.df1.half_duplex.events import HALF_DUPLEX_ACK_TIMEOUT, LineConfig
from gateway.protocols.df1.pccc.commands import Request, is_write
from gateway.protocols.df1.pccc.limits import MAX_DATA_BYTES, PLC5_TYPED
from gateway.protocols.df1.pccc.status import Sts, describe_status
from gateway.protocols.df1.plc5_address import PLC5_SIGNED, PLC5_STRUCTURES, parse_plc5_address, plc5_element_words


def _default(callable_: Callable[..., object], name: str) -> object:
    return inspect.signature(callable_).parameters[name].default


def test_one_ack_timeout_default_per_mode() -> None:
    # full duplex and a target: the SLC 500 channel's "ACK Timeout" 50 x 20 ms (1747-RM001G p. 13-52,
    # Table 13.15); a half-duplex master: 0.5 s, its line's (p. 13-61 sizes it to the line)
    assert DEFAULT_ACK_TIMEOUT == 50 * 0.020
    for owner in (FullDuplexStation, TargetRunner):  # the data link and the responder take the station's
        assert _default(owner, "ack_timeout") is DEFAULT_ACK_TIMEOUT, owner
    assert Df1DataLink().ack_timeout is Df1Responder().ack_timeout is DEFAULT_ACK_TIMEOUT
    assert HALF_DUPLEX_ACK_TIMEOUT == 0.5
    assert LineConfig.__dataclass_fields__["ack_timeout"].default is HALF_DUPLEX_ACK_TIMEOUT
    assert _default(Df1HalfDuplexLine, "ack_timeout") is HALF_DUPLEX_ACK_TIMEOUT
    # the config states no number of its own: the key's default is the line's, a target's is filled in
    assert Df1LinkConfig.model_fields["ack_timeout"].default is HALF_DUPLEX_ACK_TIMEOUT
    (target,) = parse_config(_TARGET).links
    assert isinstance(target, Df1LinkConfig) and target.ack_timeout == 1.0
    assert build_target(target).driver.responder.ack_timeout == 1.0
    half = _link("slc5/04", 'duplex = "half"', port="socket://127.0.0.1:9")
    assert half.ack_timeout == 0.5
    assert build_line(group_lines([half])[0]).tunables.ack_timeout == 0.5


_TARGET = """
[[link]]
name = "msg"
protocol = "df1"
role = "target"
port = "sim://plc-msg"
unit = 5
[[link.file]]
file = 7
type = "N"
elements = 4
table = "holding"
start = 0
"""


def test_one_checksum_default_the_slc_channels() -> None:
    # "Error Detection" CRC: the SLC 500 channel 0 default in DF1 (1747-RM001G p. 13-52, Table 13.15)
    assert DEFAULT_CHECKSUM is Checksum.CRC
    assert Df1LinkConfig.model_fields["checksum"].default == "crc"
    for owner in (FullDuplexStation, Df1HalfDuplexLine, Df1Driver):
        assert _default(owner, "checksum") is Checksum.CRC, owner
    assert Df1DataLink().checksum is Df1Responder().checksum is Checksum.CRC
    assert Slc500Options().checksum is Checksum.CRC
    assert LineOptions.__dataclass_fields__["checksum"].default is Checksum.CRC


def test_the_two_hardware_faults_have_two_names() -> None:
    # 1770-6.5.16 p. 8-2, local STS nibble: 08 "Hardware fault" (the local node could not send);
    # p. 8-3, remote nibble: 40 "Host could not complete function due to hardware fault"
    assert Sts.LOCAL_HARDWARE_FAULT == 0x08 and Sts.HOST_HARDWARE_FAULT == 0x40
    assert describe_status(0x08).startswith("Hardware fault")
    assert describe_status(0x40).startswith("Host could not complete function due to hardware fault")
    assert not hasattr(Sts, "HARDWARE_FAULT")


def _link(processor: str, extra: str = "", port: str = "sim://slc504") -> Df1LinkConfig:
    text = f"""
[[link]]
name = "press"
protocol = "df1"
port = "{port}"
unit = 1
processor = "{processor}"
{extra}
[[link.map]]
table = "holding"
start = 0
address = "N7:0"
count = 1
"""
    (link,) = parse_config(text).links
    assert isinstance(link, Df1LinkConfig)
    return link


def test_the_size_limits_are_the_families_and_an_override_only_lowers_them() -> None:
    # notes §4.36: SLC 500 fixed, 5/01, 5/02: 82 bytes; 5/03-5/05: 236 read, 228 written.
    # PLC-5 word range: 244 bytes of reply data (1770-6.5.16), 239 of address and data (KF2 p. 5-57).
    expected = {"slc5/01": (82, 82), "slc5/04": (236, 228), "plc5": (244, 239)}
    for processor, limits in expected.items():
        assert astuple(size_limits(_link(processor))) == limits, processor
        lowered = size_limits(_link(processor, "max_read_bytes = 40\nmax_write_bytes = 30"))
        assert astuple(lowered) == (40, 30), processor
        # above the family's limit: the family's, for SLC 500 and PLC-5 alike
        raised = size_limits(_link(processor, "max_read_bytes = 244\nmax_write_bytes = 244"))
        assert astuple(raised) == limits, processor
    assert MAX_DATA_BYTES == 244
    assert Df1LinkConfig.model_fields["max_read_bytes"].metadata[-1].le == 244


def test_the_simulators_and_the_target_take_the_limits_table() -> None:
    assert (slc500_processor.MAX_READ_BYTES, slc500_processor.MAX_WRITE_BYTES) == (236, 228)
    assert (sim_plc5.MAX_WORD_RANGE_READ, sim_plc5.MAX_WORD_RANGE_WRITE) == (244, 239)
    # a PLC-5 typed write carries at most 240 bytes of address, type/data parameter and data
    # (1770-6.5.16 p. 7-30), a typed read's reply 244
    assert (PLC5_TYPED.max_read_bytes, PLC5_TYPED.max_write_bytes) == (244, 240)


def test_element_words_structures_and_signedness_one_table_per_family() -> None:
    # SLC 500 (shared/docs/slc500-addressing-reference.md: "Each timer structure consists of three words",
    # "Each floating-point element consists of two words"): a timer / counter / control element is 3 words
    # (control, PRE or LEN, ACC or POS), a float 2, every other element 1; integers and the
    # structures' words are signed.  PLC-5 (1770-6.5.16 p. 13-13): the same sizes by file letter.
    slc = {FileType.TIMER: 3, FileType.COUNTER: 3, FileType.CONTROL: 3, FileType.FLOAT: 2,
           FileType.INTEGER: 1, FileType.BIT: 1, FileType.STATUS: 1}
    assert {file_type: element_words(file_type) for file_type in slc} == slc
    assert SIGNED_FILE_TYPES == {FileType.INTEGER, FileType.TIMER, FileType.COUNTER, FileType.CONTROL}
    plc5 = {"T": 3, "C": 3, "R": 3, "F": 2, "N": 1, "B": 1, "S": 1, "I": 1, "O": 1, "A": 1, "D": 1}
    assert {letter: plc5_element_words(letter) for letter in plc5} == plc5
    assert PLC5_STRUCTURES == {"T", "C", "R"} and PLC5_SIGNED == {"N", "T", "C", "R"}
    # the simulator's files, the tool's decoding and the planners take these tables
    files = slc500_data.data_files()
    assert (files[4].element_words, files[8].element_words, files[7].element_words) == (3, 2, 1)
    assert tool.decode_value(parse_address("N7:0"), b"\xff\xff") == -1
    assert tool.decode_value(parse_address("B3:0"), b"\xff\xff") == 0xFFFF
    assert tool.decode_plc5_value(parse_plc5_address("T4:0.ACC"), b"\xff\xff") == -1
    assert tool.decode_plc5_value(parse_plc5_address("B3:0"), b"\xff\xff") == 0xFFFF


def test_is_write_has_one_authority() -> None:
    """A command that changes the controller (CMD 0F): typed logical write AA, masked write AB, two
    field write A9, set processor mode 80 (SLC 500 PCCC command notes); word range write 00,
    typed write 67, read-modify-write 26 (1770-6.5.16 ch. 7).  Reads, file info, diagnostic
    status and echo do not.  The drivers take no ``write=`` of their own: they ask ``is_write`` (``line``
    is a write session's lease, which says nothing of what the request is)."""
    writes = {(cls.CMD, cls.FNC) for cls in get_args(Request) if is_write(object.__new__(cls))}
    assert writes == {(0x0F, 0xAA), (0x0F, 0xAB), (0x0F, 0xA9), (0x0F, 0x80), (0x0F, 0x00), (0x0F, 0x67), (0x0F, 0x26)}
    for driver in (Df1Driver, Df1Station):
        assert list(inspect.signature(driver.execute).parameters) == ["self", "request", "name", "line"], driver


def test_polled_or_not_is_the_unit_classes() -> None:
    """A target's unit is filled by its runner as the PLC's MSGs arrive; a master's is polled.
    ``check-config`` takes that from the unit class, not from a second test of the role."""
    assert TargetUnit.POLLED is False and Df1Unit.POLLED is True and Plc5Unit.POLLED is True
    (target,) = parse_config(_TARGET).links
    master = _link("slc5/04")
    assert isinstance(target, Df1LinkConfig)
    assert (df1.KIND.is_polled(target), df1.KIND.is_polled(master)) == (False, True)
    assert build_target(target).schedule is None  # no poller's schedule: nothing reads it
    described = describe_map(parse_config(_TARGET))
    assert "not polled: the peer sends its data" in described and "read plan:" not in described
