"""The diagnostic commands of the CLI (probe, read, write, mode, upload, download) on one link.

The link kind (``--protocol``, or the one a ``sim://`` URL's controller speaks) runs the command
(its ``tool``); this module picks the kind, keeps the first bytes that came back and, when no
valid answer came, says which other protocol they look like.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from typing import Any

from gateway.errors import ControllerRefused, InvalidRequest, LinkTimeout
from gateway.kinds import LinkKind, kind_names, link_kind, link_kinds
from gateway.sim import parse_sim_url
from gateway.tools_common import print_result, resolve_retries
from gateway.transport import ByteStream, SerialSettings, open_stream

__all__ = [
    "ReceivedBytes",
    "print_result",
    "resolve_protocol",
    "resolve_retries",
    "run_tool",
    "wrong_protocol_hint",
]


def _kind_of_model(model: str) -> LinkKind[Any]:
    for kind in link_kinds().values():
        if model in kind.config_model.sim_models:
            return kind
    raise InvalidRequest(f"sim://{model}: no link kind speaks to this simulator")


def resolve_protocol(url: str, protocol: str | None) -> str:
    """``--protocol``, or the one a ``sim://`` URL's controller speaks; the first kind by default."""
    if not url.lower().startswith("sim://"):
        return protocol or kind_names()[0]
    try:
        model, _ = parse_sim_url(url)
    except ValueError as exc:
        raise InvalidRequest(str(exc)) from exc
    spoken = _kind_of_model(model).name
    if protocol is not None and protocol != spoken:
        raise InvalidRequest(
            f"{url} simulates an {model}, which speaks {spoken}, not {protocol}: "
            f"leave out --protocol (a sim:// URL names its controller) or give --protocol {spoken}"
        )
    return spoken


class ReceivedBytes:
    """An opener for a driver that keeps the first bytes the controller sent (for hints)."""

    LIMIT = 4096

    def __init__(self) -> None:
        self.data = bytearray()

    async def opener(self, url: str, settings: SerialSettings, **kwargs: Any) -> ByteStream:
        return _Recording(await open_stream(url, settings, **kwargs), self)

    def keep(self, data: bytes) -> None:
        if len(self.data) < self.LIMIT:
            self.data += data[: self.LIMIT - len(self.data)]


class _Recording(ByteStream):
    def __init__(self, inner: ByteStream, received: ReceivedBytes) -> None:
        self._inner = inner
        self._received = received

    async def read(self) -> bytes:
        data = await self._inner.read()
        self._received.keep(data)
        return data

    def write(self, data: bytes) -> None:
        self._inner.write(data)

    async def close(self) -> None:
        await self._inner.close()

    def start_push(self, receive: Callable[[bytes], None], lost: Callable[[str], None]) -> bool:
        def kept(data: bytes) -> None:
            self._received.keep(data)
            receive(data)

        return self._inner.start_push(kept, lost)

    def char_time(self, settings: SerialSettings) -> float:
        return self._inner.char_time(settings)


def wrong_protocol_hint(protocol: str, received: bytes) -> str:
    """What to try after no valid answer came on a link run with ``protocol``; "" if nothing to say."""
    own = link_kind(protocol)
    others = [(kind.name, kind.hints) for kind in link_kinds().values() if kind is not own and kind.hints is not None]
    for name, hints in others:
        if hints.looks_like(received):
            return (f"the bytes that came back look like {hints.wire} try --protocol {name} "
                    "(see --trace FILE for the bytes)")
    if not received:
        check = own.hints.check if own.hints is not None else "the cable and the line settings"
        tries = " or ".join(f"--protocol {name} for {hints.controllers}" for name, hints in others)
        return f"nothing came back: check {check}" + (f", or try {tries}" if tries else "")
    return ""


def _sim_is_fresh(url: str) -> str:
    model = url.split("://", 1)[1].split("?", 1)[0].strip("/")
    return (
        "a sim:// URL is a fresh simulated controller, in run mode, for every command, so 'mode program' "
        f"does not carry over; for work in several steps run 'slc-gateway simulate {model} --listen "
        "127.0.0.1:7001' and use socket://127.0.0.1:7001"
    )


async def run_tool(command: str, args: argparse.Namespace) -> int:
    protocol = resolve_protocol(args.url, args.protocol)
    kind = link_kind(protocol)
    if kind.tool is None:
        raise InvalidRequest(f"{protocol} links have no diagnostic commands")
    received = ReceivedBytes()
    try:
        return await kind.tool(command, args, received.opener)
    except LinkTimeout as exc:
        hint = wrong_protocol_hint(protocol, bytes(received.data))
        if hint:
            raise LinkTimeout(f"{exc}; {hint}") from exc
        raise
    except ControllerRefused as exc:
        if command in ("upload", "download") and args.url.lower().startswith("sim://"):
            raise ControllerRefused(f"{exc}; {_sim_is_fresh(args.url)}", command=exc.command, reason=exc.reason,
                                    code=exc.code) from exc
        raise


