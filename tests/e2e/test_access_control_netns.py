"""End to end: the ``allow`` list seen from addresses that are not loopback.

The test makes two network namespaces of its own joined by a veth pair (``ip netns``, iproute2):

* the gateway's, ``10.77.33.1/24`` (and its loopback), where ``slc-gateway run`` serves a
  simulated SLC 150 over plain Modbus TCP (port 5020) and Modbus/TCP Security (TLS, port 8020);
* the clients', with two addresses: ``10.77.33.2`` inside ``allow = ["10.77.33.2/32"]`` and
  ``10.77.33.3`` outside it.

What README promises (``[modbus] allow``, ``loopback_reads``): a client inside ``allow`` reads and
writes, over plain TCP and TLS alike; a client outside it is closed at connect, without a reply
byte, and nothing it sends is applied; a loopback client (in the gateway's namespace) outside
``allow`` reads and gets exception 01 on a write (``loopback_reads = true``, the default).

Needs root (CAP_NET_ADMIN and CAP_SYS_ADMIN: ``ip netns add``), iproute2 and openssl. Where they
are missing the test is skipped with the reason, unless ``SLC_GATEWAY_REQUIRE_NETNS=1`` (CI, see
``.ci/run``) makes that a failure.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from test_access_control import make_ca, make_cert

ROOT = Path(__file__).resolve().parents[2]
SERVER, INSIDE, OUTSIDE = "10.77.33.1", "10.77.33.2", "10.77.33.3"
PLAIN, TLS = 5020, 8020
#: FC3 holding register 0 (901.ACC), one register; FC6 holding register 0 := value
READ = "0300000001"


def write(value: int) -> str:
    return f"060000{value:04x}"


#: One client process: connects from ``source`` to each target in turn (TLS when ``ca`` is set),
#: sends one request and prints what came back, hex ("" when closed without a byte).
CLIENT = r"""
import json, socket, ssl, struct, sys, time
def exchange(op):
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.settimeout(3)
    try:
        sock.bind((op["source"], 0))
        sock.connect((op["host"], op["port"]))
        if op.get("ca"):
            sock = ssl.create_default_context(cafile=op["ca"]).wrap_socket(sock, server_hostname=op["host"])
        pdu = bytes.fromhex(op["pdu"])
        sock.sendall(struct.pack(">HHHB", 7, 0, len(pdu) + 1, 1) + pdu)
        data = b""
        while len(data) < 6 or len(data) < 6 + int.from_bytes(data[4:6], "big"):
            chunk = sock.recv(256)
            if not chunk:
                break
            data += chunk
        return data.hex()
    except (OSError, ssl.SSLError) as exc:
        return "" if isinstance(exc, (ConnectionError, ssl.SSLError)) else f"error {exc!r}"
    finally:
        sock.close()
ops = json.loads(sys.argv[1])
if ops and ops[0].get("wait"):
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        reply = exchange(ops[0])
        if reply[14:16] == "03":
            break
        time.sleep(0.2)
print(json.dumps([exchange(op) for op in ops]))
"""


def _unavailable(reason: str) -> None:
    if os.environ.get("SLC_GATEWAY_REQUIRE_NETNS") == "1":
        pytest.fail(f"network namespace test required (SLC_GATEWAY_REQUIRE_NETNS=1) but {reason}")
    pytest.skip(f"NETWORK NAMESPACE TEST NOT RUN: {reason} (set SLC_GATEWAY_REQUIRE_NETNS=1 to fail instead)")


def _ip(*args: str) -> None:
    done = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=30)
    if done.returncode:
        raise RuntimeError(f"ip {' '.join(args)}: {done.stderr.strip()}")


@pytest.fixture(scope="module")
def namespaces() -> Iterator[tuple[str, str]]:
    """The gateway's and the clients' namespaces, joined by a veth pair (module doc)."""
    if shutil.which("ip") is None:
        _unavailable("the ip command is not installed (Debian package iproute2)")
    if shutil.which("openssl") is None:
        _unavailable("the openssl command is not installed (Debian package openssl)")
    if os.geteuid() != 0:
        _unavailable("it needs root to make network namespaces (ip netns add)")
    tag = f"sg{os.getpid() % 100000}"
    server_ns, client_ns = f"{tag}s", f"{tag}c"
    made: list[str] = []
    try:
        for ns in (server_ns, client_ns):
            _ip("netns", "add", ns)
            made.append(ns)
        _ip("link", "add", f"{tag}a", "type", "veth", "peer", "name", f"{tag}b")
        _ip("link", "set", f"{tag}a", "netns", server_ns)
        _ip("link", "set", f"{tag}b", "netns", client_ns)
        _ip("-n", server_ns, "addr", "add", f"{SERVER}/24", "dev", f"{tag}a")
        for address in (INSIDE, OUTSIDE):
            _ip("-n", client_ns, "addr", "add", f"{address}/24", "dev", f"{tag}b")
        for ns, dev in ((server_ns, f"{tag}a"), (client_ns, f"{tag}b")):
            _ip("-n", ns, "link", "set", dev, "up")
            _ip("-n", ns, "link", "set", "lo", "up")
    except RuntimeError as exc:
        for ns in made:
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=30)
        _unavailable(f"the network namespaces could not be made ({exc})")
    try:
        yield server_ns, client_ns
    finally:
        for ns in made:
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=30)  # the veth pair goes too


def clients(ns: str, ops: list[dict[str, object]]) -> list[str]:
    done = subprocess.run(["ip", "netns", "exec", ns, sys.executable, "-c", CLIENT, json.dumps(ops)],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    replies: list[str] = json.loads(done.stdout)
    return replies


def test_allow_from_inside_and_outside_over_tcp_and_tls(namespaces: tuple[str, str], tmp_path: Path) -> None:
    server_ns, client_ns = namespaces
    make_ca(tmp_path, "ca")
    make_cert(tmp_path, "server", "ca", f"subjectAltName=IP:{SERVER},IP:127.0.0.1\nextendedKeyUsage=serverAuth\n")
    config = tmp_path / "gateway.toml"
    config.write_text(f"""
[modbus]
listen = "0.0.0.0:{PLAIN}"
allow = ["{INSIDE}/32"]

[modbus.tls]
listen = "0.0.0.0:{TLS}"
cert = "{tmp_path / 'server.pem'}"
key = "{tmp_path / 'server.key'}"

[[link]]
name = "slc"
protocol = "slc-ascii"
port = "sim://slc150?ladder=0"
unit = 1
""")
    log = (tmp_path / "gateway.log").open("w")
    gateway = subprocess.Popen(["ip", "netns", "exec", server_ns, sys.executable, "-m", "gateway", "run", str(config)],
                               cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)
    ca = str(tmp_path / "ca.pem")
    try:
        plain = {"host": SERVER, "port": PLAIN}
        tls = {"host": SERVER, "port": TLS, "ca": ca}
        got = clients(client_ns, [
            {**plain, "source": INSIDE, "pdu": READ, "wait": True},
            {**plain, "source": INSIDE, "pdu": write(1111)},
            {**tls, "source": INSIDE, "pdu": READ},
            {**tls, "source": INSIDE, "pdu": write(2222)},
            {**plain, "source": OUTSIDE, "pdu": READ},
            {**plain, "source": OUTSIDE, "pdu": write(7777)},
            {**tls, "source": OUTSIDE, "pdu": READ},
            {**tls, "source": OUTSIDE, "pdu": write(8888)},
            {**plain, "source": INSIDE, "pdu": READ},
        ])
        mbap = "0007000000"
        assert got[0].startswith(mbap + "05010302"), got  # FC3, 2 bytes: read
        assert got[1] == mbap + "0601" + write(1111), got  # FC6 echoed: applied
        assert got[2] == mbap + "050103020457", got  # 1111 = 0457 hex, read over TLS
        assert got[3] == mbap + "0601" + write(2222), got
        assert got[4:8] == ["", "", "", ""], got  # outside allow: closed, not a byte
        assert got[8] == mbap + "05010302" + f"{2222:04x}", got  # nothing from outside was applied

        local = {"source": "127.0.0.1", "host": "127.0.0.1"}
        got = clients(server_ns, [
            {**local, "port": PLAIN, "pdu": READ},
            {**local, "port": PLAIN, "pdu": write(9999)},
            {**local, "port": TLS, "ca": ca, "pdu": READ},
            {**local, "port": TLS, "ca": ca, "pdu": write(9999)},
        ])
        read_2222 = mbap + "05010302" + f"{2222:04x}"
        refused_01 = mbap + "03018601"  # FC6 | 80, exception 01: no write rights
        assert got == [read_2222, refused_01, read_2222, refused_01], got
    finally:
        gateway.terminate()
        try:
            gateway.wait(timeout=15)
        except subprocess.TimeoutExpired:
            gateway.kill()
            gateway.wait(timeout=15)
        log.close()
    text = (tmp_path / "gateway.log").read_text()
    assert f"refused connection from {OUTSIDE}" in text, text[-3000:]
