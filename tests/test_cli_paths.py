"""Serial ports by any path, a missing port, a listen port in use, and ``simulate --port``: the CLI
as a real subprocess, on this machine's pseudo-terminals and 127.0.0.1.

What the user sees is written out here: a path outside ``/dev`` (a socat pty's link in ``/tmp``)
works for ``check-config``, ``run`` and ``probe`` alike; a path with nothing behind it is a
``check-config`` warning and a clear ``probe`` error; a port in use names the config key and the
option to use instead.
"""

from __future__ import annotations

import os
import select
import socket
import subprocess
from pathlib import Path

from cli_support import CLI, TIMEOUT, cli, fails, ok_json, start_simulator, stop
from test_cli import pty_slc150  # noqa: F401 (a fixture)
from test_cli_reload import ModbusSocket

from tests.net import free_port
from tests.waiting import until_sync

#: An SLC 150's reply to "read 8 bytes at 00A3" (its device type 15H and FRN 47), the simulator's
#: answer to the request below (the frame of test_cli.test_simulate_stops_on_sigterm_with_a_client_connected)
PROBE_REQUEST, PROBE_REPLY_START = b"#010800A3\r", b":021FFE1547"


def link_config(tmp_path: Path, port: str, head: str = "") -> Path:
    config = tmp_path / "gateway.toml"
    config.write_text(f'{head}[[link]]\nname = "press-1"\nprotocol = "slc-ascii"\nport = "{port}"\nunit = 1\n')
    return config


def test_a_port_outside_dev_is_a_serial_port_for_check_config_and_probe(
    pty_slc150: str, tmp_path: Path  # noqa: F811 (the fixture imported above)
) -> None:
    """As socat's ``link=/tmp/ttyV0`` makes it: a symlink to a pty, anywhere."""
    link = tmp_path / "ttyV0"
    link.symlink_to(pty_slc150)
    result = cli("check-config", str(link_config(tmp_path, str(link))))
    assert result.returncode == 0, result.stderr
    assert result.stderr == ""  # no warning: it exists
    assert f'port = "{link}"' in result.stdout
    assert ok_json("probe", str(link)) == {"controller": "SLC150", "device_type": 0x15, "frn": 47}


def test_a_missing_port_is_a_warning_for_check_config_and_an_error_for_probe(tmp_path: Path) -> None:
    missing = tmp_path / "ttyUSB9"
    result = cli("check-config", str(link_config(tmp_path, str(missing))))
    assert result.returncode == 0, result.stderr
    assert result.stderr == (
        f'slc-gateway check-config: warning: link "press-1": port {missing} does not exist (yet): run keeps trying '
        "to open it until it appears; check the name (ls /dev/serial/by-id/ lists USB adapters)\n"
    )
    assert fails("probe", str(missing)) == (
        f"slc-gateway probe: {missing}: no such serial port (nothing at this path): check the name "
        "(ls /dev/serial/by-id/ lists USB adapters)"
    )


def test_a_relative_port_says_it_must_be_absolute(tmp_path: Path) -> None:
    reason = fails("check-config", str(link_config(tmp_path, "ttyUSB0")))
    assert reason.endswith(
        'link "press-1" (link[0]).port: "ttyUSB0" (did you mean "/dev/ttyUSB0"?): expected a serial port by its '
        "absolute path (/dev/ttyUSB0, /tmp/ttyV0) or COM3, socket://host:port, rfc2217://host:port or "
        "sim://slc150 | sim://slc100"
    ), reason


def run_until_exit(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*CLI, "run", *args], capture_output=True, text=True, timeout=TIMEOUT, check=False)


def test_a_port_in_use_names_the_key_and_the_option(tmp_path: Path) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        config = link_config(tmp_path, "sim://slc150", f'[modbus]\nlisten = "127.0.0.1:{port}"\n')
        result = run_until_exit(str(config))
        assert result.returncode == 1, result.stderr
        assert result.stderr.splitlines()[-1] == (
            f'slc-gateway run: [modbus] listen = "127.0.0.1:{port}": cannot listen there: the port is in use (by '
            "another slc-gateway, or another server): set another [modbus] listen or run with --listen HOST:PORT"
        )
        config = link_config(tmp_path, "sim://slc150", f'[modbus]\nlisten = "127.0.0.1:{free_port()}"\n')
        result = run_until_exit(str(config), "--metrics-listen", f"127.0.0.1:{port}")
        assert result.returncode == 1, result.stderr
        assert result.stderr.splitlines()[-1] == (
            f'slc-gateway run: [metrics] listen = "127.0.0.1:{port}": cannot listen there: the port is in use (by '
            "another slc-gateway, or another server): set another [metrics] listen or run with --metrics-listen "
            "HOST:PORT"
        )
        assert "Traceback" not in result.stderr and "Errno" not in result.stderr


def test_simulate_serves_an_existing_tty(tmp_path: Path) -> None:
    """``simulate --port``: on one end of a pty pair this test made (by a symlink, as socat's
    ``link=`` makes them); the test talks to the other end as the gateway would."""
    master, slave = os.openpty()
    link = tmp_path / "ttyV1"
    link.symlink_to(os.ttyname(slave))
    process, line = start_simulator("slc150", "--port", str(link), "--no-ladder")
    try:
        assert line == f"simulated slc150 on {link}"
        os.write(master, PROBE_REQUEST)
        reply = b""
        while b"\r" not in reply:
            ready, _, _ = select.select([master], [], [], 5)
            assert ready, f"no reply from the simulator on {link} within 5 s (got {reply!r})"
            reply += os.read(master, 64)
        assert reply.startswith(PROBE_REPLY_START), reply
    finally:
        stop(process)
        os.close(master)
        os.close(slave)
    assert fails("simulate", "slc150", "--port", str(tmp_path / "nothing")) == (
        f"slc-gateway simulate: {tmp_path / 'nothing'}: cannot open: No such file or directory"
    )
    result = cli("simulate", "slc150", "--port", str(link), "--pty")
    assert result.returncode == 2 and "not allowed with argument" in result.stderr  # one place to serve at a time


def test_run_waits_for_a_missing_port_to_appear(pty_slc150: str, tmp_path: Path) -> None:  # noqa: F811
    """The warning's promise: ``run`` keeps trying a port that is not there, and serves once it is."""
    port = tmp_path / "ttyV0"
    modbus = free_port()
    config = link_config(tmp_path, str(port), f'[modbus]\nlisten = "127.0.0.1:{modbus}"\n')
    log = tmp_path / "gateway.log"
    with log.open("w") as err:
        process = subprocess.Popen([*CLI, "run", str(config)], stdout=subprocess.DEVNULL, stderr=err, text=True)
    try:
        until_sync(lambda: "no such serial port" in log.read_text(), 15.0, what="the link reported down")
        assert f'port {port} does not exist (yet): run keeps trying to open it until it appears' in log.read_text()
        port.symlink_to(pty_slc150)  # the adapter plugged in
        client = ModbusSocket(modbus)
        until_sync(lambda: isinstance(client.read_holding(1, 0, 4), list), 15.0,
                   what="unit 1 served once the port appeared")
    finally:
        process.terminate()
        assert process.wait(timeout=15) == 0, log.read_text()
