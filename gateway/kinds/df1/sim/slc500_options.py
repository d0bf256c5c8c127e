"""Options and counters of the simulated SLC 5/04 (``gateway.kinds.df1.sim.slc500``): ``sim://slc504?...``."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Final

from gateway.frozen import frozen
from gateway.protocols.df1.framing import DEFAULT_CHECKSUM, Checksum
from gateway.sim.models import read_sim_option
from gateway.sim.scan import SCAN_OPTION, ScanTime, parse_scan

__all__ = ["Slc500Counters", "Slc500Options"]

# ------------------------------------------------------------------------------------ options

_ONE_IN_OPTIONS: Final = ("corrupt", "drop", "withhold_ack", "duplicate", "noise", "lose_in", "corrupt_in")
_SLC500_OPTION_NAMES: Final = (
    *_ONE_IN_OPTIONS, "checksum", "station", "delay", "seed", "link_ack_timeout", "garble", "faults_on", SCAN_OPTION
)


@frozen
class Slc500Options:
    """Link settings and fault injection; ``1 in N`` faults are off at 0."""

    checksum: Checksum = DEFAULT_CHECKSUM
    station: int = 1  #: our DF1 node address
    corrupt: int = 0  #: corrupt 1 in N outgoing frames
    drop: int = 0  #: execute but never answer 1 in N commands
    withhold_ack: int = 0  #: do not send the DLE ACK of 1 in N received good frames
    duplicate: int = 0  #: send 1 in N outgoing frames twice
    noise: int = 0  #: precede 1 in N outputs with garbage bytes
    delay: float = 0.0  #: turnaround before each reply, seconds
    seed: int = 1  #: seed of the fault generator
    link_ack_timeout: float = 0.5  #: our link's ACK timeout (then DLE ENQ), seconds
    lose_in: int = 0  #: lose 1 in N frames from the host whole
    corrupt_in: int = 0  #: damage 1 in N frames from the host
    faults_on: str = "all"  #: "writes": drop, lose_in and corrupt_in strike only write commands
    scan: ScanTime | None = None  #: the program scan: replies at the end of the scan in progress (None: at once)

    def __post_init__(self) -> None:
        if not 0 <= self.station <= 254:
            raise ValueError(f"simulator option station={self.station}: a DF1 node address is 0-254")
        for name in _ONE_IN_OPTIONS:
            if getattr(self, name) < 0:
                raise ValueError(f"simulator option {name}={getattr(self, name)}: 1 in N must not be negative")
        if not (math.isfinite(self.delay) and self.delay >= 0):
            raise ValueError(f"simulator option delay={self.delay}: seconds, 0 or more")
        if self.faults_on not in ("all", "writes"):
            raise ValueError(f"simulator option faults_on={self.faults_on!r}: choose all or writes")
        if not (math.isfinite(self.link_ack_timeout) and self.link_ack_timeout > 0):
            raise ValueError(f"simulator option link_ack_timeout={self.link_ack_timeout}: seconds, more than 0")

    @classmethod
    def from_options(cls, options: Mapping[str, str]) -> Slc500Options:
        """Parse ``sim://slc504?...`` options (strings); ValueError names the bad option."""
        unknown = sorted(set(options) - set(_SLC500_OPTION_NAMES))
        if unknown:
            known = ", ".join(sorted(_SLC500_OPTION_NAMES))
            raise ValueError(f"unknown slc504 simulator option(s) {', '.join(unknown)} (known: {known})")
        if "garble" in options and "corrupt" in options:
            raise ValueError("simulator options garble and corrupt are the same; give only one")
        one_in = {
            name: read_sim_option(options, "garble" if name == "corrupt" and "garble" in options else name, int, 0)
            for name in _ONE_IN_OPTIONS
        }
        return cls(
            checksum=_checksum_option(options.get("checksum", DEFAULT_CHECKSUM.value)),
            station=read_sim_option(options, "station", int, 1),
            corrupt=one_in["corrupt"],
            drop=one_in["drop"],
            withhold_ack=one_in["withhold_ack"],
            duplicate=one_in["duplicate"],
            noise=one_in["noise"],
            delay=read_sim_option(options, "delay", float, 0.0),
            seed=read_sim_option(options, "seed", int, 1),
            link_ack_timeout=read_sim_option(options, "link_ack_timeout", float, 0.5),
            lose_in=one_in["lose_in"],
            corrupt_in=one_in["corrupt_in"],
            faults_on=options.get("faults_on", "all").strip().lower(),
            scan=parse_scan(options.get(SCAN_OPTION)),
        )


def _checksum_option(text: str) -> Checksum:
    try:
        return Checksum(text.strip().lower())
    except ValueError:
        raise ValueError(f"simulator option checksum={text!r}: choose bcc or crc") from None


# ---------------------------------------------------------------------------------- counters


@dataclass
class Slc500Counters:
    """What the simulator saw and did (the link's own counters are in ``simulator.link.counters``)."""

    frames_received: int = 0  #: good frames, duplicates included
    duplicates_received: int = 0  #: frames dropped by the link's duplicate detection
    ignored: int = 0  #: packets not for our station, replies, packets without a PCCC header
    replies_sent: int = 0  #: reply packets queued on the link
    replies_acked: int = 0
    replies_failed: int = 0  #: the link gave up (NAK or ENQ limit)
    refusals: int = 0  #: replies with STS != 0
    dropped: int = 0
    corrupted: int = 0
    withheld_acks: int = 0
    duplicates: int = 0  #: frames sent twice
    noise: int = 0
    lost_in: int = 0  #: frames from the host lost whole (``lose_in``)
    corrupted_in: int = 0  #: frames from the host damaged (``corrupt_in``)
    replies_resent: int = 0  #: replies sent again for a duplicate (``duplicate_reply=resend``)
    commands: dict[str, int] = field(default_factory=dict)  #: by kind: "read", "write", ...
