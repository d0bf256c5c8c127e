"""A real MQTT broker for the tests: Debian's mosquitto on a free loopback port, with a generated config.

Without mosquitto the tests that need it skip loudly, unless ``SLC_GATEWAY_REQUIRE_MOSQUITTO=1`` (CI,
``.ci/run``) makes that a failure.  ``apt-get install mosquitto`` provides ``/usr/sbin/mosquitto``.
"""

from __future__ import annotations

import contextlib
import importlib
import os
import shutil
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.net import free_port

HOST = "127.0.0.1"
#: started as root, mosquitto would drop to its own user, who cannot read the test's private directory
RUN_AS = "user root\n" if os.geteuid() == 0 else ""
HERE = Path(__file__).resolve().parent
#: the independent host application (tests/peers), imported as a module of that directory
PEERS = HERE.parent / "peers"


def mosquitto_path() -> str:
    path = shutil.which("mosquitto") or next(
        (p for p in ("/usr/sbin/mosquitto", "/usr/local/sbin/mosquitto") if os.access(p, os.X_OK)), None)
    if path is None:
        if os.environ.get("SLC_GATEWAY_REQUIRE_MOSQUITTO") == "1":
            pytest.fail("mosquitto is not installed and SLC_GATEWAY_REQUIRE_MOSQUITTO=1 (apt-get install mosquitto)")
        pytest.skip("MOSQUITTO NOT INSTALLED: the Sparkplug tests need a real broker (Debian package mosquitto); "
                    "set SLC_GATEWAY_REQUIRE_MOSQUITTO=1 to fail instead")
    return path


class Broker:
    """A running mosquitto: ``port``; ``stop()`` / ``start()`` to take it away and bring it back."""

    def __init__(self, directory: Path) -> None:
        self.path = mosquitto_path()
        self.directory = directory
        self.port = free_port()
        self.config = directory / "mosquitto.conf"
        self.log = directory / "mosquitto.log"
        self.config.write_text(
            f"{RUN_AS}listener {self.port} {HOST}\nallow_anonymous true\npersistence false\n"
            f"log_dest file {self.log}\nlog_type error\nlog_type warning\nlog_type notice\n",
            encoding="utf-8",
        )
        self.process: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        self.process = subprocess.Popen([self.path, "-c", str(self.config)], stdout=subprocess.DEVNULL,
                                        stderr=subprocess.PIPE)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                err = self.process.stderr.read().decode(errors="replace") if self.process.stderr else ""
                pytest.fail(f"mosquitto exited at start: {err} {self.log.read_text() if self.log.exists() else ''}")
            with contextlib.suppress(OSError), socket.create_connection((HOST, self.port), timeout=0.5):
                return
            time.sleep(0.05)
        pytest.fail(f"mosquitto did not listen on {HOST}:{self.port} within 10 s")

    def stop(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(5)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self.process = None


@pytest.fixture
def broker(tmp_path: Path) -> Iterator[Broker]:
    running = Broker(tmp_path)
    running.start()
    try:
        yield running
    finally:
        running.stop()


def import_host() -> type:
    """The independent host application's ``SparkplugHost`` (tests/peers/sparkplug_host.py)."""
    if str(PEERS) not in sys.path:
        sys.path.insert(0, str(PEERS))
    try:
        module = importlib.import_module("sparkplug_host")
    except ImportError as exc:
        pytest.fail(f"tests/peers/sparkplug_host.py (the independent host application) cannot be imported: {exc}")
    host: type = module.SparkplugHost
    return host
