"""Process kill: the gateway killed with SIGKILL gets its NDEATH from the broker within the keepalive.

``slc-gateway run`` runs as its own process against Debian's mosquitto; the independent host
application (tests/peers/sparkplug_host.py) watches.  SIGKILL leaves no chance of a clean stop: the
NDEATH that arrives is the will registered at CONNECT (Sparkplug 3.0 §5.4), which the broker sends
once the client has been silent for one and a half keepalive periods (MQTT 3.1.1 §3.1.2.10).
Its bdSeq must be the NBIRTH's; a restart then starts the next session with the next bdSeq, read
back from the state file (§5.4, tck-id-topics-nbirth-bdseq-increment).
"""

from __future__ import annotations

import asyncio
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from cli_support import stop
from mosquitto_support import HOST, Broker, broker, import_host  # noqa: F401 (the fixture)

GROUP, NODE = "plant1", "killed"
KEEPALIVE = 5
SparkplugHost = import_host()


def config(broker_port: int, directory: Path) -> Path:
    path = directory / "gateway.toml"
    path.write_text(
        f'[modbus]\nlisten = "127.0.0.1:0"\n\n[sparkplug]\nbroker = "mqtt://{HOST}:{broker_port}"\n'
        f'group_id = "{GROUP}"\nedge_node_id = "{NODE}"\nkeepalive = {KEEPALIVE}\nstatus_interval = 1.0\n'
        f'state_file = "bdseq.json"\n\n'
        '[[link]]\nname = "press"\nprotocol = "df1"\nport = "sim://slc504?ladder=0"\nunit = 1\n'
        '[[link.map]]\ntable = "holding"\nstart = 0\naddress = "N7:0"\ncount = 4\n',
        encoding="utf-8",
    )
    return path


#: seconds a started process may take to publish its NBIRTH: Python's start and one CONNECT, 2-3 s
#: here with a core kept busy.  On this 2-core VM otherwise idle it took 5-14 s: the two steps that
#: run in a thread before the CONNECT (the bdSeq save and aiomqtt's connect) each waited seconds for
#: an idle CPU to wake (measured with timestamps inside the thread; a busy loop in another process
#: made every run fast).  A lost first CONNECT is not left to this bound: it costs a second attempt,
#: which takes the next bdSeq (§5.4), and the bdSeq checks below fail on it whatever the timing.
STARTUP = 40


def start(path: Path) -> subprocess.Popen[bytes]:
    """``slc-gateway run`` on ``path``; its log goes to a file beside it (a pipe nobody reads could fill
    and stop the process)."""
    log = open(path.with_suffix(".log"), "ab")
    process = subprocess.Popen([sys.executable, "-m", "gateway", "run", str(path)], stdout=subprocess.DEVNULL,
                               stderr=log, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    log.close()  # the child has its own copy
    return process


async def born(host: Any, process: subprocess.Popen[bytes], path: Path, since: int = 0) -> Any:
    """The NBIRTH of the started process; if none comes, why (the process's exit and its log)."""
    try:
        return await host.wait_for(is_type("NBIRTH"), STARTUP, since=since)
    except TimeoutError:
        log = path.with_suffix(".log").read_text(encoding="utf-8", errors="replace")[-3000:]
        raise AssertionError(f"no NBIRTH within {STARTUP} s; process exit code {process.poll()}; log:\n{log}") from None


def is_type(verb: str, device: str | None = None) -> Callable[[Any], bool]:
    return lambda m: m.message_type == verb and m.edge_node_id == NODE and (device is None or m.device_id == device)


async def test_sigkill_gives_the_will_ndeath_within_the_keepalive(broker: Broker, tmp_path: Path) -> None:  # noqa: F811
    path = config(broker.port, tmp_path)
    async with SparkplugHost(HOST, broker.port) as host:
        process = start(path)
        try:
            nbirth = await born(host, process, path)
            assert nbirth.metric("bdSeq").value == 0  # no state file yet: the first CONNECT's bdSeq
            await host.wait_for(is_type("DBIRTH", "press"), 10)
            await host.wait_for(is_type("DDATA", "press"), 10, since=nbirth.index)
            process.send_signal(signal.SIGKILL)
            killed = time.monotonic()
            process.wait(5)
            ndeath = await host.wait_for(is_type("NDEATH"), 1.5 * KEEPALIVE + 3, since=nbirth.index)
            waited = time.monotonic() - killed
        finally:
            if process.poll() is None:
                process.kill()
                process.wait()
        assert waited <= 1.5 * KEEPALIVE + 1, waited
        assert ndeath.metric("bdSeq").value == nbirth.metric("bdSeq").value
        assert not host.node_online(GROUP, NODE)

        # a restart is a new session: the next bdSeq, from the state file
        process = start(path)
        try:
            again = await born(host, process, path, since=ndeath.index)
        finally:
            stop(process, wait=10)
        # the next bdSeq (§5.4), counted on from the state file the killed process left (a fresh start
        # would begin at 0 again): the restarted process's first CONNECT is its session
        assert again.metric("bdSeq").value == (nbirth.metric("bdSeq").value + 1) % 256
        assert json.loads((tmp_path / "bdseq.json").read_text())["bdSeq"] == again.metric("bdSeq").value
        # SIGTERM is a clean stop: NDEATH first (§5.5), with this session's bdSeq
        clean = await host.wait_for(is_type("NDEATH"), 5, since=again.index)
        assert clean.metric("bdSeq").value == again.metric("bdSeq").value
        await asyncio.sleep(0)
        assert host.violations == [], "\n".join(host.violations)
