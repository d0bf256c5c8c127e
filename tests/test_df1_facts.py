"""DF1 facts stated once, with the values the manuals give; every layer takes them from there.

Manuals: 1747-RM001G (SLC 500 instruction set, ch. 13, channel 0 configuration), 1766-RM001A
(MicroLogix 1400 instruction set, DF1 half-duplex master parameters), 1770-6.5.16 (DF1 protocol
and command set).
"""

from __future__ import annotations

import inspect
from collections.abc import Callable

from gateway.kinds.df1.config import Df1LinkConfig
from gateway.kinds.df1.driver import Df1Driver
from gateway.kinds.df1.half_duplex_driver import Df1HalfDuplexLine
from gateway.kinds.df1.sim.df1_multidrop import LineOptions
from gateway.kinds.df1.sim.slc500_options import Slc500Options
from gateway.kinds.df1.target_driver import TargetRunner
from gateway.protocols.df1.datalink import Df1DataLink
from gateway.protocols.df1.framing import DEFAULT_ACK_TIMEOUT, DEFAULT_CHECKSUM, Checksum
from gateway.protocols.df1.half_duplex_events import LineConfig
from gateway.protocols.df1.pccc.status import Sts, describe_status
from gateway.protocols.df1.responder import Df1Responder


def _default(callable_: Callable[..., object], name: str) -> object:
    return inspect.signature(callable_).parameters[name].default


def test_one_ack_timeout_default_the_manuals() -> None:
    # "ACK Timeout" 50 x 20 ms: SLC 500 channel 0 (1747-RM001G p. 13-52, Table 13.15) and a DF1
    # half-duplex master (1766-RM001A p. 600)
    assert DEFAULT_ACK_TIMEOUT == 50 * 0.020
    assert Df1LinkConfig.model_fields["ack_timeout"].default is DEFAULT_ACK_TIMEOUT
    assert LineConfig.__dataclass_fields__["ack_timeout"].default is DEFAULT_ACK_TIMEOUT
    for owner in (Df1DataLink, Df1Responder, Df1HalfDuplexLine, TargetRunner):
        assert _default(owner, "ack_timeout") is DEFAULT_ACK_TIMEOUT, owner


def test_one_checksum_default_the_slc_channels() -> None:
    # "Error Detection" CRC: the SLC 500 channel 0 default in DF1 (1747-RM001G p. 13-52, Table 13.15)
    assert DEFAULT_CHECKSUM is Checksum.CRC
    assert Df1LinkConfig.model_fields["checksum"].default == "crc"
    for owner in (Df1DataLink, Df1Responder, Df1HalfDuplexLine, Df1Driver):
        assert _default(owner, "checksum") is Checksum.CRC, owner
    assert Slc500Options().checksum is Checksum.CRC
    assert LineOptions.__dataclass_fields__["checksum"].default is Checksum.CRC


def test_the_two_hardware_faults_have_two_names() -> None:
    # 1770-6.5.16 p. 8-2, local STS nibble: 08 "Hardware fault" (the local node could not send);
    # p. 8-3, remote nibble: 40 "Host could not complete function due to hardware fault"
    assert Sts.LOCAL_HARDWARE_FAULT == 0x08 and Sts.HOST_HARDWARE_FAULT == 0x40
    assert describe_status(0x08).startswith("Hardware fault")
    assert describe_status(0x40).startswith("Host could not complete function due to hardware fault")
    assert not hasattr(Sts, "HARDWARE_FAULT")
