"""``gateway.modbus.admission.Admission``: who gets a connection slot, from peer addresses that are
not all loopback.

The rules (README: the ``[modbus]`` keys ``allow`` and ``loopback_reads``, "loopback outside
``allow`` may read, never write"): a peer inside ``allow`` is admitted with the rights its listener gives; a
peer outside ``allow`` is refused, except a *loopback* peer when ``loopback_reads`` is on, which is
admitted for reads only; without ``allow`` every peer is admitted with full rights.
"""

from __future__ import annotations

import ipaddress
import logging

import pytest

from gateway.logutil import RepeatLog
from gateway.modbus.admission import (
    Admission,
    IPNetwork,
    Rights,
    RolePolicy,
    format_address,
    format_subject,
    host_allowed,
    peer_host,
    role_from_certificate,
)


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
    gate = Admission("tls", max_connections=3, max_per_address=1, max_handshakes=4)
    slot = FakeSlot()
    assert gate.handshake_done(slot, ("10.20.0.1", 1)) is True
    assert gate.established == 1
    assert gate.admit(FakeSlot(), ("10.20.0.1", 2)) is False  # its address holds its one connection
    gate.release(slot)
    assert gate.established == 0
    other = FakeSlot()
    assert gate.admit(other, ("10.20.0.1", 3)) is True
    assert gate.handshake_done(FakeSlot(), ("10.20.0.2", 4)) is True
    gate.release(FakeSlot())  # never admitted: nothing to count out
    assert gate.admit(FakeSlot(), ("10.20.0.1", 5)) is False  # the address's count is still that of `other`


def test_the_address_counted_at_the_handshake_is_the_one_counted_out() -> None:
    gate = Admission("tls", max_connections=2, max_per_address=1, max_handshakes=4)
    slot = FakeSlot()
    assert gate.admit(slot, ("10.20.0.1", 1), handshake_started=0.0) is True
    assert gate.handshake_done(slot, None) is True  # the peer is only named in a refusal's log line
    assert gate.admit(FakeSlot(), ("10.20.0.1", 2)) is False  # its address holds its one connection
    gate.release(slot)
    assert gate.admit(FakeSlot(), ("10.20.0.1", 2)) is True


def test_without_a_handshake_budget_a_tls_connection_holds_its_slot_from_accept() -> None:
    gate = Admission("tls", max_connections=2, max_per_address=1)
    slot = FakeSlot()
    assert gate.admit(slot, ("10.20.0.1", 1), handshake_started=0.0) is True
    assert (gate.handshaking, gate.established) == (0, 1)
    assert gate.handshake_done(slot, ("10.20.0.1", 1)) is True
    assert (gate.handshaking, gate.established) == (0, 1)
    assert gate.admit(FakeSlot(), ("10.20.0.1", 2)) is False  # counted once, and still
    gate.release(slot)
    assert gate.admit(FakeSlot(), ("10.20.0.1", 3)) is True  # and counted out


def test_an_address_whose_connections_are_all_gone_is_forgotten() -> None:
    """The per-address table holds only addresses with connections: it does not grow with every
    address that ever connected."""
    gate = Admission("tls", max_connections=4, max_per_address=2, max_handshakes=4)
    plain, tls = FakeSlot(), FakeSlot()
    assert gate.admit(plain, ("10.20.0.1", 1)) and gate.admit(tls, ("10.20.0.2", 1), handshake_started=0.0)
    assert gate.handshake_done(tls, ("10.20.0.2", 1))
    gate.release(plain)
    gate.release(tls)
    assert gate._per_address == {}


class StalledSlot(FakeSlot):
    """A connection holding its slot without using it since ``since``."""

    def __init__(self, since: float) -> None:
        super().__init__()
        self.since = since

    def stalled_since(self) -> float | None:
        return self.since


def test_of_connections_stalled_since_the_same_instant_one_is_evicted_for_a_newcomer() -> None:
    gate = Admission("plain", max_connections=2)
    first, second = StalledSlot(5.0), StalledSlot(5.0)
    assert gate.admit(first, ("10.20.0.1", 1)) and gate.admit(second, ("10.20.0.1", 2))
    assert gate.admit(FakeSlot(), ("10.20.0.2", 1)) is True
    assert sorted([first.evicted or "", second.evicted or ""]) == [
        "",
        "stalled mid-frame or no request yet, closed to make room",
    ]
    assert (gate.evicted, gate.established) == (1, 2)


def _summary(caplog: pytest.LogCaptureFixture, cause: str) -> str:
    messages = [record.getMessage() for record in caplog.records]
    lines = [line for line in messages if line.startswith(f"{cause}: ") and " more in " in line]
    assert len(lines) == 1, caplog.text
    return lines[0]


def test_repeated_refusals_are_summarised_with_the_addresses_refused(caplog: pytest.LogCaptureFixture) -> None:
    """The module's rule: each cause logged at once, then once per interval how many more and
    from which addresses."""
    log = RepeatLog(logging.getLogger("gateway.modbus.server"), 60.0, clock=lambda: 0.0, schedule=lambda *_: None)
    gate = Admission("tls", max_connections=1, max_handshakes=4, allow=ALLOW, repeat_log=log)
    for port in (1, 2):
        assert gate.admit(FakeSlot(), ("10.20.1.1", port)) is False
    assert gate.admit(FakeSlot(), ("10.20.0.1", 1)) is True  # the one slot, in use
    for port in (1, 2):
        assert gate.admit(FakeSlot(), ("10.20.0.2", port)) is False
    for port in (1, 2):
        slot = FakeSlot()
        assert gate.admit(slot, ("10.20.0.3", port), handshake_started=0.0) is True
        assert gate.handshake_done(slot, ("10.20.0.3", port)) is False
    assert "refused connection from 10.20.0.3:1: TLS handshake done but already 1 connections" in caplog.text
    log.flush_all()
    assert "from 10.20.1.1 (1)" in _summary(caplog, "tls: connection refused, peer not in the allowed networks")
    assert "from 10.20.0.2 (1)" in _summary(caplog, "tls: connection refused, already 1 connections, none idle")
    assert "from 10.20.0.3 (1)" in _summary(
        caplog, "tls: connection refused, TLS handshake done but already 1 connections"
    )


# -- identity ---------------------------------------------------------------------------------


def test_a_client_without_a_certificate_has_no_subject_nor_role_and_the_default_rights() -> None:
    cases: tuple[tuple[Rights, bool], ...] = (("read", False), ("read-write", True))
    for default, can_write in cases:
        client = RolePolicy({"operator": "read-write"}, default).identify("10.20.0.1:5", None)
        assert (client.address, client.subject, client.role, client.can_write) == ("10.20.0.1:5", None, None, can_write)


def test_format_subject() -> None:
    """``getpeercert()['subject']``: a tuple of RDNs, each a tuple of (attribute, value) pairs; the
    attributes RFC 4514 (3) gives a short name are written with it, others by their name."""
    cn, o = (("commonName", "operator"),), (("organizationName", "plant"),)
    assert format_subject((o, cn)) == "O=plant,CN=operator"
    assert format_subject(((("emailAddress", "ops@example.com"),), cn)) == "emailAddress=ops@example.com,CN=operator"
    assert format_subject(("junk", o, cn)) == "O=plant,CN=operator"  # what is not an RDN is skipped
    assert format_subject(((("commonName", "operator", "x"), "ab"), o)) == "O=plant"  # nor a pair
    assert format_subject(()) is None and format_subject(None) is None


def test_peer_host_drops_the_scope_of_an_address_whatever_it_holds() -> None:
    assert peer_host(("fe80::1%a%b", 1, 0, 2)) == "fe80::1"  # Linux lets an interface name hold a %


# -- the role extension, on certificates built here by the DER rules (X.690) -------------------------

ROLE = "1.3.6.1.4.1.50316.802.1"  # MB-TCP-Security-v36 R-21


def der(tag: int, content: bytes, length_octets: int | None = None) -> bytes:
    """One element (X.690 8.1): tag, length, content. The length in the short form below 128, else
    in the long form (0x80 + n, then n octets, most significant first); ``length_octets`` forces
    the long form with that many octets."""
    if length_octets is None and len(content) < 0x80:
        return bytes([tag, len(content)]) + content
    octets = length_octets or (len(content).bit_length() + 7) // 8
    return bytes([tag, 0x80 | octets]) + len(content).to_bytes(octets, "big") + content


def oid(dotted: str) -> bytes:
    """An OBJECT IDENTIFIER (X.690 8.19): 40 x the first arc + the second, then each arc in base
    128, the high bit set on every octet but an arc's last."""
    arcs = [int(arc) for arc in dotted.split(".")]
    content = bytearray()
    for arc in (40 * arcs[0] + arcs[1], *arcs[2:]):
        octets = [arc & 0x7F]
        while arc := arc >> 7:
            octets.append(0x80 | arc & 0x7F)
        content += bytes(reversed(octets))
    return der(0x06, bytes(content))


def extension(value: bytes, *, critical: bool = False, extension_id: str = ROLE) -> bytes:
    """Extension ::= SEQUENCE { extnID OID, critical BOOLEAN DEFAULT FALSE, extnValue OCTET STRING }."""
    return der(0x30, oid(extension_id) + (der(0x01, b"\xff") if critical else b"") + der(0x04, value))


def certificate(*extensions: bytes, before: bytes = b"") -> bytes:
    """A certificate's skeleton (RFC 5280 4.1): SEQUENCE { tbsCertificate SEQUENCE { version [0],
    serialNumber, ``before``, extensions [3] SEQUENCE OF Extension }, signatureAlgorithm,
    signatureValue }."""
    tbs = der(0xA0, der(0x02, b"\x02")) + der(0x02, b"\x01") + before + der(0xA3, der(0x30, b"".join(extensions)))
    return der(0x30, der(0x30, tbs) + der(0x30, oid("1.2.840.10045.4.3.2")) + der(0x03, b"\x00"))


def test_the_role_is_read_with_its_length_in_any_definite_form() -> None:
    utf8 = 0x0C
    assert role_from_certificate(certificate(extension(der(utf8, b"operator")))) == "operator"
    assert role_from_certificate(certificate(extension(der(utf8, b"operator"), critical=True))) == "operator"
    assert role_from_certificate(certificate(extension(der(utf8, b"r" * 200)))) == "r" * 200  # 0x81 0xC8
    assert role_from_certificate(certificate(extension(der(utf8, b"r" * 300)))) == "r" * 300  # 0x82 0x01 0x2C
    assert role_from_certificate(certificate(extension(der(utf8, b"operator", length_octets=4)))) == "operator"
    assert role_from_certificate(certificate(extension(der(utf8, b"")))) == ""  # 2 octets, ending the value
    assert role_from_certificate(certificate(extension(der(utf8, b"", length_octets=1)))) == ""
    other = extension(der(0x04, b"\x00"), extension_id="2.5.29.15")  # keyUsage, then the role
    assert role_from_certificate(certificate(other, extension(der(utf8, b"viewer")))) == "viewer"
    assert role_from_certificate(certificate(other)) is None


@pytest.mark.parametrize(
    ("value", "error"),
    [
        (bytes([0x0C, 0x80]) + b"operator\x00\x00", "bad DER length"),  # indefinite: not DER (X.690 10.1)
        (bytes([0x0C, 0x85, 0, 0, 0, 0, 8]) + b"operator", "bad DER length"),  # 5 length octets
        (bytes([0x0C, 0x82, 0x01]), "bad DER length"),  # length octets cut off by the value's end
        (bytes([0x0C, 0x09]) + b"operator", "DER element runs past its container"),
        (bytes([0x0C]), "truncated DER element"),  # a tag and no length
    ],
)
def test_a_role_with_a_bad_length_is_refused(value: bytes, error: str) -> None:
    with pytest.raises(ValueError, match=f"^{error}$"):
        role_from_certificate(certificate(extension(value)))


def test_what_is_not_a_certificate_is_refused_and_named() -> None:
    cases = {
        der(0x04, b"x"): "not a certificate",  # not a SEQUENCE
        der(0x30, der(0x02, b"\x01")): "not a certificate",  # its tbsCertificate not a SEQUENCE
        der(0x30, der(0x30, der(0xA3, der(0x02, b"\x01")))): "bad extensions",  # [3] holds no SEQUENCE OF
        certificate(extension(der(0x0C, b"operator")), before=bytes([0x9F, 0x00])): (
            "multi-byte DER tags are not used in X.509"  # tag number 31 and up (X.690 8.1.2.4)
        ),
    }
    for data, error in cases.items():
        with pytest.raises(ValueError) as raised:
            role_from_certificate(data)
        assert str(raised.value) == error
