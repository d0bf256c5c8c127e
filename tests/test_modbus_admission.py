"""``gateway.modbus.admission.Admission``: who gets a connection slot, from peer addresses that are
not all loopback.

The rules (README: the ``[modbus]`` keys ``allow`` and ``loopback_reads``, "loopback outside
``allow`` may read, never write"): a peer inside ``allow`` is admitted with the rights its listener gives; a
peer outside ``allow`` is refused, except a *loopback* peer when ``loopback_reads`` is on, which is
admitted for reads only; without ``allow`` every peer is admitted with full rights.
"""

from __future__ import annotations

import ipaddress

import pytest

from gateway.modbus.admission import Admission, IPNetwork, format_address, host_allowed, peer_host


class FakeSlot:
    """A connection as admission sees it: never stalled, records an eviction."""

    def __init__(self) -> None:
        self.evicted: str | None = None

    def stalled_since(self) -> float | None:
        return None

    def evict(self, reason: str) -> None:
        self.evicted = reason


ALLOW: tuple[IPNetwork, ...] = (ipaddress.ip_network("10.20.0.0/24"), ipaddress.ip_network("fd00:20::/64"))

INSIDE = [("10.20.0.1", 40001), ("10.20.0.254", 40002), ("fd00:20::7", 40003, 0, 0), ("::ffff:10.20.0.9", 40004, 0, 0)]
OUTSIDE = [("10.20.1.1", 40005), ("192.0.2.7", 40006), ("fd00:21::7", 40007, 0, 0), ("::ffff:192.0.2.8", 40008, 0, 0)]
LOOPBACK = [("127.0.0.1", 40009), ("127.3.4.5", 40010), ("::1", 40011, 0, 0), ("::ffff:127.0.0.1", 40012, 0, 0)]


def admission(*, loopback_reads: bool, allow: tuple[IPNetwork, ...] | None = ALLOW) -> Admission:
    return Admission("test", max_connections=100, allow=allow, loopback_reads=loopback_reads)


@pytest.mark.parametrize("loopback_reads", [False, True])
@pytest.mark.parametrize("peer", INSIDE, ids=str)
def test_a_peer_inside_allow_is_admitted_with_full_rights(peer: tuple[object, ...], loopback_reads: bool) -> None:
    gate = admission(loopback_reads=loopback_reads)
    assert gate.admit(FakeSlot(), peer) is True
    assert gate.read_only(peer) is False
    assert (gate.established, gate.refused) == (1, 0)


@pytest.mark.parametrize("loopback_reads", [False, True])
@pytest.mark.parametrize("peer", OUTSIDE, ids=str)
def test_a_peer_outside_allow_is_refused_with_or_without_loopback_reads(
    peer: tuple[object, ...], loopback_reads: bool
) -> None:
    gate = admission(loopback_reads=loopback_reads)
    assert gate.read_only(peer) is False  # loopback_reads is about loopback peers only
    assert gate.admit(FakeSlot(), peer) is False
    assert (gate.established, gate.refused) == (0, 1)


@pytest.mark.parametrize("peer", LOOPBACK, ids=str)
def test_a_loopback_peer_outside_allow_reads_only_with_loopback_reads(peer: tuple[object, ...]) -> None:
    gate = admission(loopback_reads=True)
    assert gate.read_only(peer) is True
    assert gate.admit(FakeSlot(), peer) is True
    closed = admission(loopback_reads=False)
    assert closed.read_only(peer) is False
    assert closed.admit(FakeSlot(), peer) is False


def test_a_loopback_peer_inside_allow_has_full_rights() -> None:
    gate = admission(loopback_reads=True, allow=(*ALLOW, ipaddress.ip_network("127.0.0.0/8")))
    assert gate.read_only(("127.0.0.1", 40013)) is False
    assert gate.admit(FakeSlot(), ("127.0.0.1", 40013)) is True
    assert gate.read_only(("::1", 40014, 0, 0)) is True  # ::1 is not in 127.0.0.0/8


@pytest.mark.parametrize("loopback_reads", [False, True])
def test_without_allow_every_peer_is_admitted_with_full_rights(loopback_reads: bool) -> None:
    gate = admission(loopback_reads=loopback_reads, allow=None)
    for peer in (*INSIDE, *OUTSIDE, *LOOPBACK):
        assert gate.admit(FakeSlot(), peer) is True
        assert gate.read_only(peer) is False


def test_a_peer_without_an_ip_address_is_refused_when_allow_is_set() -> None:
    gate = admission(loopback_reads=True)
    for peer in (None, "/run/socket", ("not-an-address", 1)):
        assert gate.read_only(peer) is False
        assert gate.admit(FakeSlot(), peer) is False
    assert gate.refused == 3


def test_peer_host_and_host_allowed() -> None:
    assert peer_host(("::ffff:10.20.0.9", 1, 0, 0)) == "10.20.0.9"
    assert peer_host(("fe80::1%eth0", 1, 0, 2)) == "fe80::1"
    assert peer_host(("10.20.0.1", 1)) == "10.20.0.1"
    assert peer_host(None) is None and peer_host(("x", 1)) is None
    assert peer_host((7, 1)) is None and peer_host(()) is None
    assert host_allowed("10.20.0.1", ALLOW) and host_allowed("fd00:20::1", ALLOW)
    assert not host_allowed("10.20.1.1", ALLOW) and not host_allowed(None, ALLOW)
    assert not host_allowed("127.0.0.1", ALLOW)


def test_loopback_reads_is_off_unless_asked_for() -> None:
    gate = Admission("test", max_connections=10, allow=ALLOW)
    assert gate.read_only(("127.0.0.1", 1)) is False
    assert gate.admit(FakeSlot(), ("127.0.0.1", 1)) is False


def test_format_address_brackets_ipv6_only() -> None:
    assert format_address(("fd00:20::7", 502, 0, 0)) == "[fd00:20::7]:502"
    assert format_address(("10.20.0.1", 502)) == "10.20.0.1:502"
    assert format_address("/run/socket") == "/run/socket"


def test_a_refusal_is_logged_with_the_peer_and_its_cause(caplog: pytest.LogCaptureFixture) -> None:
    gate = Admission("plain", max_connections=1, max_per_address=1, allow=ALLOW)
    assert gate.admit(FakeSlot(), ("10.20.1.1", 40005)) is False
    assert gate.admit(FakeSlot(), ("10.20.0.1", 40006)) is True
    assert gate.admit(FakeSlot(), ("10.20.0.1", 40007)) is False  # per address
    assert gate.admit(FakeSlot(), ("10.20.0.2", 40008)) is False  # no slot free, none idle
    text = caplog.text
    assert "plain: refused connection from 10.20.1.1:40005: peer not in the allowed networks" in text
    assert "refused connection from 10.20.0.1:40007: over max_connections_per_address (1)" in text
    assert "refused connection from 10.20.0.2:40008: already 1 connections, none idle" in text
    assert gate.refused == 3


def test_connections_per_address_are_counted_out_on_release() -> None:
    gate = Admission("test", max_connections=10, max_per_address=2)
    peer = ("10.20.0.1", 1)
    first, second = FakeSlot(), FakeSlot()
    assert gate.admit(first, peer) and gate.admit(second, peer)
    assert gate.admit(FakeSlot(), peer) is False
    gate.release(first)
    gate.release(first)  # idempotent
    assert gate.admit(FakeSlot(), peer) is True
    assert gate.admit(FakeSlot(), peer) is False
    assert gate.admit(FakeSlot(), ("10.20.0.2", 1)) is True  # another host is not held by this one's count


def test_a_tls_connection_is_counted_from_its_handshake_to_its_release() -> None:
    gate = Admission("tls", max_connections=1, max_per_address=1, max_handshakes=4)
    peer = ("10.20.0.1", 1)
    slot = FakeSlot()
    assert gate.admit(slot, peer, handshake_started=0.0) is True
    assert (gate.handshaking, gate.established) == (1, 0)
    assert gate.admit(FakeSlot(), peer, handshake_started=0.1) is False  # its handshake counts
    assert gate.handshake_done(slot, peer) is True
    assert (gate.handshaking, gate.established) == (0, 1)
    gate.release(slot)
    assert gate.established == 0
    again = FakeSlot()
    assert gate.admit(again, peer, handshake_started=1.0) is True  # the address was counted out


def test_a_handshake_done_with_no_room_is_refused_and_counted_out() -> None:
    gate = Admission("tls", max_connections=1, max_per_address=1, max_handshakes=4)
    assert gate.admit(FakeSlot(), ("10.20.0.9", 1)) is True  # the one slot, in use (never stalled)
    peer = ("10.20.0.1", 2)
    slot = FakeSlot()
    assert gate.admit(slot, peer, handshake_started=0.0) is True
    assert gate.handshake_done(slot, peer) is False
    assert (gate.handshaking, gate.established) == (0, 1)
    assert gate.admit(FakeSlot(), peer, handshake_started=1.0) is True  # not still counted


def test_a_handshake_done_of_a_slot_not_handshaking_is_counted_by_its_peer() -> None:
    gate = Admission("tls", max_connections=2, max_per_address=1, max_handshakes=4)
    slot = FakeSlot()
    assert gate.handshake_done(slot, ("10.20.0.1", 1)) is True
    assert gate.established == 1
    gate.release(slot)
    assert gate.established == 0
