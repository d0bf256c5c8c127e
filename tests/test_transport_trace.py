"""Issue 14, smaller items of the transport: trace files (0600, size cap, rotation), no credentials in logs."""

from __future__ import annotations

import os
import socket
import stat
from pathlib import Path

import pytest

from gateway.errors import LinkDown
from gateway.transport import SerialSettings, TraceFile, TracingStream, describe_url, open_stream


def test_trace_file_is_created_owner_only(tmp_path: Path) -> None:
    """Issue 14: trace files were created 0644 (world-readable line traffic)."""
    path = tmp_path / "link.trace"
    old_umask = os.umask(0o022)
    try:
        trace = TraceFile(path, max_bytes=1000, backups=1)
    finally:
        os.umask(old_umask)
    trace.write("x\n")
    trace.close()
    assert stat.S_IMODE(path.stat().st_mode) == 0o600


def test_existing_trace_file_is_tightened_to_0600(tmp_path: Path) -> None:
    path = tmp_path / "link.trace"
    path.write_text("old\n")
    path.chmod(0o644)
    TraceFile(path).close()
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert path.read_text() == "old\n"  # appended to, not truncated


def test_trace_file_is_capped_and_rotated(tmp_path: Path) -> None:
    """Issue 14: no size cap (about 0.6 MB/s per busy link)."""
    path = tmp_path / "link.trace"
    trace = TraceFile(path, max_bytes=100, backups=2)
    for index in range(50):
        trace.write(f"line {index:04d} " + "." * 20 + "\n")  # 31 bytes
    trace.close()
    files = sorted(p.name for p in tmp_path.iterdir())
    assert files == ["link.trace", "link.trace.1", "link.trace.2"]
    for name in files:
        assert (tmp_path / name).stat().st_size <= 100
        assert stat.S_IMODE((tmp_path / name).stat().st_mode) == 0o600
    assert path.read_text().splitlines()[-1].startswith("line 0049")
    total = sum((tmp_path / name).stat().st_size for name in files)
    assert total <= 300


def test_trace_without_backups_truncates(tmp_path: Path) -> None:
    path = tmp_path / "link.trace"
    trace = TraceFile(path, max_bytes=64, backups=0)
    for index in range(20):
        trace.write(f"{index:02d} " + "-" * 20 + "\n")
    trace.close()
    assert [p.name for p in tmp_path.iterdir()] == ["link.trace"]
    assert path.stat().st_size <= 64


async def test_tracing_stream_writes_through_the_capped_file(tmp_path: Path) -> None:
    path = tmp_path / "sim.trace"
    stream = await open_stream("sim://slc150?instance=trace-test", SerialSettings(), trace=path, link_name="x")
    assert isinstance(stream, TracingStream)
    stream.write(b"\x10\x02")
    await stream.close()
    assert "x TX 10 02" in path.read_text()
    assert stat.S_IMODE(path.stat().st_mode) == 0o600


def test_describe_url_drops_credentials_and_options() -> None:
    assert describe_url("socket://plc:s3cret@10.0.0.5:4001") == "socket://***@10.0.0.5:4001"
    assert describe_url("rfc2217://u:p@host:2217?x=1") == "rfc2217://***@host:2217"


async def test_link_down_message_has_no_password() -> None:
    """Issue 14: credentials in port URLs appeared in full in the log."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]  # closed again: connecting is refused
    with pytest.raises(LinkDown) as caught:
        await open_stream(f"socket://plc:s3cret@127.0.0.1:{port}", SerialSettings(), connect_timeout=2)
    assert "s3cret" not in str(caught.value)
    assert "***@127.0.0.1" in str(caught.value)
