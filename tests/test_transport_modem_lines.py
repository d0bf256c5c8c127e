"""RTS / DTR of half-duplex lines (``gateway.transport.modem_lines``) and what each port kind does.

A local port gives setters (a pseudo-terminal here: it has no modem lines, so a change is logged once
and never fails the link); ``socket://`` gives none; a port wrapped for tracing or software parity
is unwrapped.  The driver keys RTS through the port's setter in ``toggle`` mode, holds it in
``on`` / ``off`` mode and sets DTR at each connection.
"""

from __future__ import annotations

import asyncio
import io
import logging
import os
import tty
from typing import Any

import pytest

from gateway.kinds.df1.half.driver import Df1HalfDuplexLine
from gateway.protocols.df1.framing import Checksum
from gateway.protocols.df1.half_duplex.events import StationConfig
from gateway.streams import SerialSettings
from gateway.transport import (
    ProtocolStream,
    SoftwareParityStream,
    TracingStream,
    modem_lines,
    open_stream,
)


class FakePort:
    """The modem-line attributes of a pyserial port, recording each change."""

    port = "/dev/ttyFAKE"

    def __init__(self) -> None:
        self.changes: list[tuple[str, bool]] = []

    def __setattr__(self, name: str, value: Any) -> None:
        if name in ("rts", "dtr"):
            self.changes.append((name, value))
        object.__setattr__(self, name, value)


def test_socket_and_sim_streams_have_no_modem_lines() -> None:
    assert modem_lines(ProtocolStream("socket://h:1")) is None


def test_wrapped_local_port_gives_setters() -> None:
    inner = ProtocolStream("/dev/ttyFAKE")
    inner.serial_port = FakePort()
    wrapped = TracingStream(SoftwareParityStream(inner, "E"), io.StringIO(), "x")
    lines = modem_lines(wrapped)
    assert lines is not None and not lines.remote
    lines.set_rts(True)
    lines.set_dtr(False)
    assert inner.serial_port.changes == [("rts", True), ("dtr", False)]


@pytest.mark.skipif(not hasattr(os, "openpty"), reason="needs a pseudo-terminal (POSIX)")
async def test_pseudo_terminal_without_modem_lines_logs_once_and_goes_on(caplog: pytest.LogCaptureFixture) -> None:
    master, slave = os.openpty()
    tty.setraw(master)
    stream = await open_stream(os.ttyname(slave), SerialSettings(19200, 8, "N", 1))
    try:
        lines = modem_lines(stream)
        assert lines is not None
        with caplog.at_level(logging.WARNING):
            for _ in range(3):
                lines.set_rts(True)  # a pty refuses TIOCMBIS: logged, not raised
        warnings = [r for r in caplog.records if "RTS" in r.getMessage()]
        assert len(warnings) <= 1
    finally:
        await stream.close()
        os.close(master)
        os.close(slave)


async def run_line(mode: str) -> list[tuple[str, bool]]:
    port = FakePort()

    async def opener(url: str, settings: object, **_: object) -> ProtocolStream:
        stream = ProtocolStream(url)
        stream.serial_port = port

        class Sink(asyncio.Transport):
            def write(self, data: Any) -> None:
                pass

            def is_closing(self) -> bool:
                return False

            def close(self) -> None:
                pass

        stream.connection_made(Sink())
        return stream

    line = Df1HalfDuplexLine("/dev/ttyFAKE", [StationConfig(1, poll_timeout=0.02, poll_interval=0.01)], name="l",
                             checksum=Checksum.BCC, rts_mode=mode, dtr=False, opener=opener, link_reset=False)
    await line.start()
    await asyncio.sleep(0.1)
    await line.close()
    return port.changes


async def test_toggle_keys_rts_around_each_poll() -> None:
    changes = await run_line("toggle")
    assert changes[0] == ("dtr", False)
    rts = [value for name, value in changes if name == "rts"]
    assert rts[:4] == [True, False, True, False] and rts.count(True) >= 2


@pytest.mark.parametrize(("mode", "held"), [("on", True), ("off", False)])
async def test_on_off_hold_rts(mode: str, held: bool) -> None:
    changes = await run_line(mode)
    assert changes == [("dtr", False), ("rts", held)]


def test_unknown_rts_mode_is_refused() -> None:
    with pytest.raises(ValueError, match="toggle, rs485, on, off"):
        Df1HalfDuplexLine("/dev/x", [StationConfig(1)], rts_mode="auto")
