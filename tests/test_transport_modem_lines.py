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


class Sink(asyncio.Transport):
    def write(self, data: Any) -> None:
        pass

    def is_closing(self) -> bool:
        return False

    def close(self) -> None:
        pass


async def run_port(port: Any, url: str = "/dev/ttyFAKE", *, connections: int = 1, **kwargs: Any) -> list[Any]:
    """Open the line ``connections`` times (the port is lost in between) on ``port``; the port's changes."""
    streams: list[ProtocolStream] = []

    async def opener(url: str, settings: object, **_: object) -> ProtocolStream:
        stream = ProtocolStream(url)
        stream.serial_port = port
        stream.connection_made(Sink())
        streams.append(stream)
        return stream

    line = Df1HalfDuplexLine(url, [StationConfig(1, poll_timeout=0.02, poll_interval=0.01)], name="l",
                             checksum=Checksum.BCC, opener=opener, link_reset=False, reconnect_min=0.01,
                             reconnect_max=0.01, **kwargs)
    await line.start()
    try:
        await asyncio.sleep(0.1)
        for _ in range(200):  # a loaded machine: let toggling show its first four changes
            toggled = line.rts_mode == "toggle" or (line.rts_mode == "rs485" and getattr(port, "refuse", False))
            if port is None or not toggled or sum(name == "rts" for name, _ in port.changes) >= 4:
                break
            await asyncio.sleep(0.01)
        for _ in range(connections - 1):
            streams[-1].connection_lost(None)
            for _ in range(200):
                await asyncio.sleep(0.01)
                if len(streams) > 1 and line.connected:
                    break
            await asyncio.sleep(0.05)
    finally:
        await line.close()
    assert len(streams) == connections
    return port.changes if port is not None else []


async def run_line(mode: str) -> list[tuple[str, bool]]:
    changes: list[tuple[str, bool]] = await run_port(FakePort(), rts_mode=mode, dtr=False)
    return changes


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


async def test_dtr_is_on_by_default_and_set_at_every_connection() -> None:
    """docs/guide/df1-half-duplex.md: ``dtr`` (line) defaults to true, "DTR while the port is open"."""
    changes = await run_port(FakePort(), rts_mode="off", connections=2)
    assert changes == [("dtr", True), ("rts", False), ("dtr", True), ("rts", False)]


class Rs485Port(FakePort):
    """A port whose driver takes the kernel's RS-485 mode (``refuse``: one that cannot)."""

    def __init__(self, refuse: bool = False) -> None:
        super().__init__()
        object.__setattr__(self, "refuse", refuse)

    def __setattr__(self, name: str, value: Any) -> None:
        if name == "rs485_mode":
            if self.refuse:
                raise ValueError("not supported")
            self.changes.append(("rs485", (value.rts_level_for_tx, value.delay_before_tx, value.delay_before_rx)))
            return
        super().__setattr__(name, value)


async def test_rs485_hands_rts_and_its_delays_to_the_kernel() -> None:
    """``rts = "rs485"``: the kernel keys RTS (on while sending) with ``rts_send_delay`` before the first
    byte and ``rts_off_delay`` after the last (docs/guide/df1-half-duplex.md "Radio and RS-485 settings");
    the gateway then never touches RTS itself."""
    changes = await run_port(Rs485Port(), rts_mode="rs485", dtr=False, rts_send_delay=0.02, rts_off_delay=0.01)
    assert changes == [("dtr", False), ("rs485", (True, 0.02, 0.01))]


async def test_rs485_refused_by_the_port_falls_back_to_toggling_rts() -> None:
    changes = await run_port(Rs485Port(refuse=True), rts_mode="rs485", dtr=False)
    rts = [value for name, value in changes if name == "rts"]
    assert changes[0] == ("dtr", False) and rts[:4] == [True, False, True, False]


@pytest.mark.parametrize("mode", ["toggle", "on", "off"])
async def test_toggle_on_off_never_ask_for_the_kernel_rs485_mode(mode: str) -> None:
    changes = await run_port(Rs485Port(), rts_mode=mode, dtr=False)
    assert [name for name, _ in changes if name == "rs485"] == []
    assert [value for name, value in changes if name == "rts"][:1] == [mode != "off"]


@pytest.mark.parametrize(("mode", "warned"), [("toggle", True), ("rs485", True), ("on", True), ("off", False)])
async def test_a_device_server_without_modem_lines_is_logged_once(
    mode: str, warned: bool, caplog: pytest.LogCaptureFixture
) -> None:
    """``socket://`` has no modem lines: the device server must key the transmitter, said once (not at
    each reconnection), and only when RTS should be keyed (docs/guide/df1-half-duplex.md)."""
    with caplog.at_level(logging.WARNING, logger="gateway.link"):
        await run_port(None, "socket://127.0.0.1:1", rts_mode=mode, connections=2)
    said = [r for r in caplog.records if "has no modem lines" in r.getMessage()]
    assert len(said) == (1 if warned else 0), [r.getMessage() for r in said]


class RemotePort(FakePort):
    """An ``rfc2217://`` port: its modem lines are switched over TCP."""


RemotePort.__module__ = "serial.rfc2217"


@pytest.mark.parametrize(("mode", "warned"), [("toggle", True), ("on", False), ("off", False)])
async def test_rts_toggle_over_rfc2217_is_logged_once(
    mode: str, warned: bool, caplog: pytest.LogCaptureFixture
) -> None:
    """Over ``rfc2217://`` RTS follows the data a network round trip late: not precise enough to key a
    radio (docs/guide/df1-half-duplex.md), said once; holding RTS on or off over it is fine."""
    with caplog.at_level(logging.WARNING, logger="gateway.link"):
        changes = await run_port(RemotePort(), "rfc2217://127.0.0.1:1", rts_mode=mode, connections=2)
    said = [r for r in caplog.records if "RFC 2217" in r.getMessage()]
    assert len(said) == (1 if warned else 0), [r.getMessage() for r in said]
    assert changes[0] == ("dtr", True)
