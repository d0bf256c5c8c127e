"""Helpers of the CLI tests: run ``python -m gateway ...`` and its simulators as subprocesses."""

from __future__ import annotations

import json
import selectors
import subprocess
import sys
from typing import Any

CLI = [sys.executable, "-m", "gateway"]
TIMEOUT = 30  # seconds for any one command; each normally takes well under one


def start_simulator(*args: str) -> tuple[subprocess.Popen[str], str]:
    """Run ``slc-gateway simulate ARGS`` and return it with the first line it prints."""
    process = subprocess.Popen(
        [*CLI, "simulate", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert process.stdout is not None
    with selectors.DefaultSelector() as selector:
        selector.register(process.stdout, selectors.EVENT_READ)
        if not selector.select(timeout=TIMEOUT):
            stop(process)
            raise AssertionError(f"simulate {' '.join(args)} printed nothing within {TIMEOUT} s")
    line = process.stdout.readline().strip()
    if not line:
        stop(process)
        _, err = process.communicate(timeout=5)
        raise AssertionError(f"simulate {' '.join(args)} exited: {err}")
    return process, line


def stop(process: subprocess.Popen[Any], wait: float = 5.0) -> None:
    """SIGTERM, ``wait`` seconds for a clean exit, then SIGKILL; the process's pipes closed."""
    if process.poll() is None:
        process.terminate()
        try:
            process.wait(timeout=wait)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(timeout=5)
    for stream in (process.stdout, process.stderr):
        if stream is not None:
            stream.close()


def cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*CLI, *args], capture_output=True, text=True, timeout=TIMEOUT, check=False)


def ok(*args: str) -> str:
    result = cli(*args)
    assert result.returncode == 0, f"{args}: exit {result.returncode}: {result.stderr}"
    assert result.stderr == ""
    return result.stdout


def ok_json(*args: str) -> Any:
    lines = ok(*args, "--json").splitlines()
    assert len(lines) == 1, lines  # one object
    return json.loads(lines[0])


def fails(*args: str, status: int = 1) -> str:
    """Run a command that must fail; return its one-line reason."""
    result = cli(*args)
    assert result.returncode == status, f"{args}: exit {result.returncode}: {result.stdout} {result.stderr}"
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, f"{args}: not a one-line reason: {result.stderr!r}"
    assert "Traceback" not in result.stderr
    return lines[0]
