"""The container image, built from the Dockerfile and run: the entry command and the HEALTHCHECK.

No Docker engine runs here and no container registry can be reached, so the image is built with
buildah (``buildah bud --isolation chroot --format docker``: the Docker format keeps HEALTHCHECK,
which the OCI format drops) on a local base image, Debian bookworm with Debian's Python 3.11,
that ``.ci/base-image`` builds with mmdebstrap (``--build-arg BASE=...``; the Dockerfile's default
base stays ``python:3.11-slim``).

The image's own configuration (``buildah inspect``: ENTRYPOINT + CMD, USER, HEALTHCHECK) is then
run inside a container of the image (``buildah run --isolation chroot``; ``podman run`` cannot set
rlimits in some sandboxes), in a network namespace of its own so that the image's fixed ports
(5020, 9108) collide with nothing on the machine.  The shipped config is mounted over the image's
with its serial port replaced by a simulator.  Checked: the gateway runs as the image's non-root
user and owns the listening Modbus socket, answers Modbus reads, the HEALTHCHECK command passes
(both its policies), and SIGTERM (``docker stop``) ends it with exit status 0.

Needs root, buildah, podman, mmdebstrap (Debian packages), unshare and nsenter (util-linux) and the
package index (pip in the image's build stage).  Without them the test is skipped with the reason;
with ``SLC_GATEWAY_REQUIRE_IMAGE=1`` (CI, see .ci/run) it fails instead.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
REQUIRED = os.environ.get("SLC_GATEWAY_REQUIRE_IMAGE") == "1"
TOOLS = ("buildah", "podman", "mmdebstrap", "unshare", "nsenter")
#: The image's user (Dockerfile: useradd --uid 10001, USER slc-gateway:dialout).
IMAGE_UID = 10001
MODBUS_PORT = 5020  # the shipped config's and the HEALTHCHECK's


#: Output of a failed step that means the network (Debian mirror, package index) could not be reached.
_NETWORK_ERRORS = re.compile(
    r"Temporary failure in name resolution|Name or service not known|Network is unreachable|"
    r"NewConnectionError|ConnectTimeoutError|No route to host|Could not resolve|Failed to fetch|"
    r"\(from versions: none\)",
    re.IGNORECASE,
)


def _unavailable(reason: str) -> None:
    if REQUIRED:
        pytest.fail(f"container image test required (SLC_GATEWAY_REQUIRE_IMAGE=1) but {reason}")
    pytest.skip(f"CONTAINER IMAGE NOT BUILT: {reason} (set SLC_GATEWAY_REQUIRE_IMAGE=1 to fail instead)")


def _run(
    command: Sequence[str], timeout: float, what: str, cwd: Path | None = None
) -> subprocess.CompletedProcess[str]:
    try:
        result = subprocess.run(list(command), cwd=cwd, capture_output=True, text=True, timeout=timeout, check=False)
    except subprocess.TimeoutExpired as exc:
        pytest.fail(f"{what}: no result within {timeout:g} s:\n{exc.stdout!r}\n{exc.stderr!r}")
    if result.returncode != 0:
        output = result.stdout + result.stderr
        if _NETWORK_ERRORS.search(output):
            _unavailable(f"{what} could not reach the network:\n{output[-2000:]}")
        pytest.fail(f"{what} failed (exit {result.returncode}):\n{output[-6000:]}")
    return result


@dataclass
class Image:
    name: str
    config: dict[str, object]  # the Docker image config (Entrypoint, Cmd, User, Healthcheck, ...)

    def list_of(self, key: str) -> list[str]:
        value = self.config.get(key) or []
        assert isinstance(value, list), (key, value)
        return [str(v) for v in value]


@pytest.fixture(scope="module")
def image() -> Iterator[Image]:
    missing = [tool for tool in TOOLS if shutil.which(tool) is None]
    if missing:
        _unavailable(f"{', '.join(missing)} not installed (apt-get install buildah podman mmdebstrap)")
    if os.geteuid() != 0:
        _unavailable("not running as root (the image build and the container need it)")
    base = _run([str(ROOT / ".ci" / "base-image")], 900, ".ci/base-image").stdout.strip().splitlines()[-1]
    name = f"localhost/slc-gateway:test-{os.getpid()}"
    _run(
        ["buildah", "bud", "--isolation", "chroot", "--format", "docker", "--build-arg", f"BASE={base}",
         "--tag", name, "--file", str(ROOT / "Dockerfile"), str(ROOT)],
        900, "buildah bud",
    )
    try:
        inspected = json.loads(_run(["buildah", "inspect", "--type", "image", name], 60, "buildah inspect").stdout)
        yield Image(name, inspected["Docker"]["config"])
    finally:
        subprocess.run(["buildah", "rmi", "--force", name], capture_output=True, timeout=120, check=False)


def test_image_keeps_the_dockerfiles_settings(image: Image) -> None:
    assert image.list_of("Entrypoint") + image.list_of("Cmd") == ["slc-gateway", "run", "/etc/slc-gateway/gateway.toml"]
    assert image.config.get("User") == "slc-gateway:dialout"
    healthcheck = image.config.get("Healthcheck")
    assert isinstance(healthcheck, dict), "no HEALTHCHECK in the image (built in OCI format?)"
    assert healthcheck["Test"] == ["CMD", "python", "-m", "gateway.healthcheck", "127.0.0.1:5020", "1"]
    assert image.config.get("StopSignal") == "SIGTERM"
    assert set(image.config.get("ExposedPorts") or {}) == {"5020/tcp", "802/tcp", "9108/tcp"}


# --------------------------------------------------------------------------------------------
# A container of the image


@dataclass
class Container:
    name: str
    netns: str = ""  # /proc/<pid>/ns/net of the running entry command

    def run(self, command: Sequence[str], timeout: float = 60) -> subprocess.CompletedProcess[str]:
        """``command`` inside the container, as the image's user, in the entry command's network."""
        prefix = ["nsenter", f"--net={self.netns}"] if self.netns else []
        return subprocess.run(
            [*prefix, "buildah", "run", "--isolation", "chroot", self.name, "--", *command],
            capture_output=True, text=True, timeout=timeout, check=False,
        )


@pytest.fixture
def container(image: Image) -> Iterator[Container]:
    name = f"slc-gateway-test-{os.getpid()}"
    subprocess.run(["buildah", "rm", name], capture_output=True, timeout=60, check=False)
    _run(["buildah", "from", "--pull-never", "--name", name, image.name], 120, "buildah from")
    try:
        yield Container(name)
    finally:
        subprocess.run(["buildah", "rm", name], capture_output=True, timeout=60, check=False)


#: Run in a new network namespace: bring its loopback up, then become the given command.
_IN_NEW_NETNS = """
import fcntl, os, socket, struct, sys
with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
    fcntl.ioctl(s, 0x8914, struct.pack("16sH14x", b"lo", 0x1 | 0x8 | 0x40))  # SIOCSIFFLAGS: UP LOOPBACK RUNNING
os.execvp(sys.argv[1], sys.argv[1:])
"""


def _descendants(pid: int) -> list[int]:
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            ppid = int(stat[stat.rindex(")") + 2 :].split()[1])
            children.setdefault(ppid, []).append(int(entry.name))
    found, todo = [], [pid]
    while todo:
        for child in children.get(todo.pop(), []):
            found.append(child)
            todo.append(child)
    return found


def _gateway_process(outer: subprocess.Popen[str], entry: Sequence[str], deadline: float = 30) -> int:
    """The pid of the entry command (the container's PID 1 under Docker) below ``outer``."""
    end = time.monotonic() + deadline
    while time.monotonic() < end:
        assert outer.poll() is None, "buildah run exited early"
        for pid in _descendants(outer.pid):
            try:
                argv = (Path("/proc") / str(pid) / "cmdline").read_bytes().decode().split("\0")
            except OSError:
                continue
            # /opt/slc-gateway/bin/python /opt/slc-gateway/bin/slc-gateway run /etc/...
            if len(argv) > len(entry) and argv[0].endswith("/python") and Path(argv[1]).name == entry[0]:
                if argv[2 : 2 + len(entry) - 1] == list(entry[1:]):
                    return pid
        time.sleep(0.1)
    pytest.fail(f"no process running {entry} below buildah run after {deadline:g} s")


def _status_ids(pid: int, field: str) -> list[int]:
    for line in (Path("/proc") / str(pid) / "status").read_text().splitlines():
        if line.startswith(f"{field}:"):
            return [int(v) for v in line.split()[1:]]
    raise AssertionError(f"no {field} in /proc/{pid}/status")


def _listening_inode(pid: int, port: int) -> str:
    """The socket inode listening on 0.0.0.0:``port`` in the network namespace of ``pid``."""
    for line in (Path("/proc") / str(pid) / "net" / "tcp").read_text().splitlines()[1:]:
        fields = line.split()
        if fields[1] == f"00000000:{port:04X}" and fields[3] == "0A":  # 0A: LISTEN
            return fields[9]
    return ""


def _socket_inodes(pid: int) -> set[str]:
    inodes = set()
    for fd in (Path("/proc") / str(pid) / "fd").iterdir():
        target = os.readlink(fd)
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    return inodes


def test_entry_command_serves_modbus_as_the_image_user_passes_the_healthcheck_and_stops_on_sigterm(
    image: Image, container: Container, tmp_path: Path
) -> None:
    config = (ROOT / "config" / "gateway.toml").read_text(encoding="utf-8")
    config, n = re.subn(r'^port = "/dev/ttyUSB0"$', 'port = "sim://slc150?ladder=0"', config, flags=re.MULTILINE)
    assert n == 1
    config_path = tmp_path / "gateway.toml"
    config_path.write_text(config, encoding="utf-8")
    config_path.chmod(0o644)
    entry = image.list_of("Entrypoint") + image.list_of("Cmd")
    log_path = tmp_path / "container.log"
    with log_path.open("w", encoding="utf-8") as log:
        outer = subprocess.Popen(
            ["unshare", "--net", "--", sys.executable, "-c", _IN_NEW_NETNS,
             "buildah", "run", "--isolation", "chroot",
             "--volume", f"{config_path}:/etc/slc-gateway/gateway.toml:ro",
             container.name, "--", *entry],
            stdout=log, stderr=subprocess.STDOUT, text=True,
        )

    def output() -> str:
        return log_path.read_text(encoding="utf-8", errors="replace")

    pid = 0
    try:
        pid = _gateway_process(outer, entry)
        container.netns = f"/proc/{pid}/ns/net"

        # The HEALTHCHECK as Docker runs it: its command in the container, retried in the start period.
        healthcheck = image.config["Healthcheck"]
        assert isinstance(healthcheck, dict)
        test = healthcheck["Test"]
        assert test[0] == "CMD"
        end = time.monotonic() + 30
        while (result := container.run(test[1:])).returncode != 0:
            assert outer.poll() is None, f"the gateway exited:\n{output()}"
            if time.monotonic() > end:
                pytest.fail(f"HEALTHCHECK still failing after 30 s: {result.stdout}{result.stderr}\n{output()}")
            time.sleep(0.5)
        assert result.stdout.startswith("healthy: 127.0.0.1:5020 unit 1"), result.stdout
        assert "policy" in result.stdout, result.stdout
        # The stricter policy (--require-link) holds too once the simulated controller answers.
        end = time.monotonic() + 30
        while (strict := container.run([*test[1:], "--require-link"])).returncode != 0:
            if time.monotonic() > end:
                pytest.fail(f"--require-link health check still failing: {strict.stderr}\n{output()}")
            time.sleep(0.5)

        # The non-root user of the image runs the gateway and owns the Modbus listener.
        assert set(_status_ids(pid, "Uid")) == {IMAGE_UID}, _status_ids(pid, "Uid")
        assert 0 not in _status_ids(pid, "Gid")
        inode = _listening_inode(pid, MODBUS_PORT)
        assert inode, f"nothing listens on port {MODBUS_PORT} in the container's network"
        assert inode in _socket_inodes(pid)

        # An independent Modbus client (pymodbus, this interpreter) in the container's network.
        read = (
            "from pymodbus.client import ModbusTcpClient\n"
            f"c = ModbusTcpClient('127.0.0.1', port={MODBUS_PORT}, timeout=3)\n"
            "assert c.connect()\n"
            "r = c.read_holding_registers(32, count=4, device_id=1)\n"
            "print(r.registers)\n"
        )
        reply = _run(["nsenter", f"--net={container.netns}", sys.executable, "-c", read], 60, "Modbus read",
                     cwd=ROOT)
        assert reply.stdout.strip() == "[100, 110, 120, 130]"  # the simulator's presets of 901-904

        # docker stop: SIGTERM to the container's entry process, then its exit status.
        os.kill(pid, signal.SIGTERM)
        try:
            assert outer.wait(20) == 0, output()
        except subprocess.TimeoutExpired:
            pytest.fail(f"the gateway did not exit within 20 s of SIGTERM:\n{output()}")
        assert "Traceback" not in output()
        assert "stopped" in output()
    finally:
        if outer.poll() is None:
            if pid:
                os.kill(pid, signal.SIGKILL)  # buildah run, killed, would leave its child running
            outer.kill()
            outer.wait(30)
