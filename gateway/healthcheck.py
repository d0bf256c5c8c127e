"""Health check for containers: one Modbus TCP read of a unit's status block.

::

    python -m gateway.healthcheck [HOST:PORT] [UNIT] [--require-link]

Sends function 4 (read input registers), address 1000 (the status block's ``link_up``), count 1,
to unit ``UNIT`` (default 1) at ``HOST:PORT`` (default 127.0.0.1:5020) and exits 0 on a normal
reply: the gateway accepts connections and its Modbus server answers.  Two policies:

* ``serving`` (default, the image's HEALTHCHECK): the status block is served whether or not the
  controller answers, so a controller that is off or a serial link that is down does not make the
  container unhealthy (restarting the gateway would not bring the controller back).
* ``link`` (``--require-link``): also demands ``link_up = 1``, the same condition under which the
  gateway's ``/healthz`` answers 503 for a link that is down.

Every line printed names the policy applied.  Exits 1, with the reason on stderr, on a refused
connection, no reply within ``--timeout`` seconds (default 3), an exception reply, a malformed
reply, or (``--require-link``) a link that is down.

Standard library only, a plain socket: no Modbus library, nothing to start but the interpreter
(the MBAP header is the server's own, :data:`gateway.modbus.mbap.MBAP`, a ``struct``).
"""

from __future__ import annotations

import argparse
import socket
import struct
import sys
from collections.abc import Sequence

from gateway.modbus.mbap import MBAP

__all__ = ["POLICY_LINK", "POLICY_SERVING", "check", "run_healthcheck"]

STATUS_LINK_UP = 1000
#: What each policy demands, as printed on every line of output.
POLICY_SERVING = "policy serving: the Modbus server answers; the link's state does not count (--require-link: it does)"
POLICY_LINK = "policy link (--require-link): the Modbus server answers and the controller link is up"
_TID = 0x4843  # "HC"


def _listen_address(text: str) -> tuple[str, int]:
    host, colon, port = text.rpartition(":")
    if not colon or not port.isdigit() or not 0 < int(port) < 65536 or not host:
        raise argparse.ArgumentTypeError(f"{text!r}: expected HOST:PORT, e.g. 127.0.0.1:5020 or [::1]:5020")
    return host.removeprefix("[").removesuffix("]"), int(port)


def _unit(text: str) -> int:
    if not text.isdigit() or not 0 <= int(text) <= 255:
        raise argparse.ArgumentTypeError(f"{text!r}: a unit id is 0..255")
    return int(text)


def _receive(sock: socket.socket, size: int) -> bytes:
    data = b""
    while len(data) < size:
        chunk = sock.recv(size - len(data))
        if not chunk:
            raise ConnectionError("connection closed before a complete reply")
        data += chunk
    return data


def check(host: str, port: int, unit: int = 1, timeout: float = 3.0) -> int:
    """The value of status register 1000 (1 = link up).  Raises ``OSError`` or ``ValueError``."""
    request = MBAP.pack(_TID, 0, 6, unit) + struct.pack(">BHH", 4, STATUS_LINK_UP, 1)
    with socket.create_connection((host, port), timeout=timeout) as sock:
        sock.sendall(request)
        tid, protocol, length, reply_unit = MBAP.unpack(_receive(sock, MBAP.size))
        if (tid, protocol, reply_unit) != (_TID, 0, unit) or not 2 <= length <= 254:
            raise ValueError(f"malformed reply header (tid {tid}, protocol {protocol}, length {length})")
        pdu = _receive(sock, length - 1)
    if pdu[0] == 0x84 and len(pdu) == 2:
        raise ValueError(f"exception 0x{pdu[1]:02X} from unit {unit}")
    if pdu[:2] != b"\x04\x02" or len(pdu) != 4:
        raise ValueError(f"malformed reply {pdu.hex()}")
    value: int = struct.unpack(">H", pdu[2:])[0]
    return value


def run_healthcheck(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m gateway.healthcheck",
        description="Modbus TCP health check of slc-gateway: read a unit's status register 1000.",
    )
    parser.add_argument("address", nargs="?", type=_listen_address, default=("127.0.0.1", 5020), metavar="HOST:PORT")
    parser.add_argument("unit", nargs="?", type=_unit, default=1, metavar="UNIT")
    parser.add_argument(
        "--require-link", action="store_true",
        help="also fail when the controller link is down (as /healthz does); default: only the gateway must answer",
    )
    parser.add_argument("--timeout", type=float, default=3.0, help="seconds to wait (default 3)")
    args = parser.parse_args(argv)
    host, port = args.address
    policy = POLICY_LINK if args.require_link else POLICY_SERVING
    try:
        link_up = check(host, port, args.unit, args.timeout)
    except (OSError, ValueError) as exc:
        print(f"unhealthy: {host}:{port} unit {args.unit}: {exc}; {policy}", file=sys.stderr)
        return 1
    state = "up" if link_up == 1 else "down"
    if args.require_link and link_up != 1:
        print(f"unhealthy: {host}:{port} unit {args.unit}: link {state}; {policy}", file=sys.stderr)
        return 1
    print(f"healthy: {host}:{port} unit {args.unit}: link {state}; {policy}")
    return 0


if __name__ == "__main__":
    raise SystemExit(run_healthcheck())
