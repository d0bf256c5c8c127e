"""Where publishing's CPU goes in the gateway: the edge node's parts, per message published.

Beside ``bench/sparkplug_publishing.py`` (which measures what publishing costs the Modbus answers),
this runs the gateway in this process, with the same 64 DF1 links on the simulator farm (ladders
running) and Debian's mosquitto, and no Modbus load.  Windows alternate, the order rotated per pair:
``on`` (the broker up, the node online) and ``off`` (the broker stopped: the links poll, the node
waits to reconnect).  Per pair, the process's CPU (``time.process_time``) on minus off, divided by the
messages published in the ``on`` window, is the gateway's whole CPU per message (aiomqtt and paho
included); the median over the pairs is reported.

In every window, what the loop makes a ready callback wait (a probe every 1-3 ms: ``call_soon`` to its
run), the wait a Modbus request arriving then has before its turn: ``on`` against ``off`` is what
publishing adds to it, in this process, whatever else the machine runs.

In the ``on`` windows, the CPU of each part (``time.thread_time`` around the call; the wrapper adds
about a microsecond a call): reading the image (``LinkDevice.read``: after stores, and every
``check_interval`` for what ages), the core's DDATA (``EdgeNode.flush``, with ``encode`` inside it),
paho's ``publish`` (building a packet, queueing it) and ``loop_write`` (the socket writes, the
on_publish callbacks), and aiomqtt's write registration.  ``--source DIR`` runs another tree (an older
commit exported with ``git archive``) for a before / after.

    python bench/sparkplug_cpu.py [--quick] [--rounds N] [--duration S] [--links N] [--source DIR]
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import functools
import random
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from _benchlib import REPO, SimFarm, print_machine, result, table
from modbus_serving import free_port
from sparkplug_publishing import LINKS, Broker, config, mosquitto


def account(cpu: collections.Counter[str], calls: collections.Counter[str], owner: Any, name: str,
            label: str) -> None:
    """Wrap ``owner.name`` (a plain function or method) to add its thread CPU to ``cpu[label]``."""
    function = getattr(owner, name)

    @functools.wraps(function)
    def timed(*args: Any, **kwargs: Any) -> Any:
        started = time.thread_time()
        try:
            return function(*args, **kwargs)
        finally:
            cpu[label] += time.thread_time() - started
            calls[label] += 1

    setattr(owner, name, timed)


async def settle(reached: Any, patience: float = 30.0) -> None:
    for _ in range(int(patience / 0.1)):
        if reached():
            return
        await asyncio.sleep(0.1)
    raise SystemExit("the edge node did not reach the expected state in time")


async def run(links: int, rounds: int, duration: float) -> None:
    # imported here: --source puts another tree first on sys.path
    import aiomqtt
    import paho.mqtt.client as paho

    import gateway.sparkplug.devices as devices
    import gateway.sparkplug.node as node_module
    from gateway.app import Gateway
    from gateway.config import parse_config

    cpu: collections.Counter[str] = collections.Counter()
    calls: collections.Counter[str] = collections.Counter()
    parts = ((devices.LinkDevice, "read", "LinkDevice.read"), (node_module.EdgeNode, "flush", "EdgeNode.flush"),
             (node_module, "encode", "  of it: encode"), (paho.Client, "publish", "paho publish"),
             (paho.Client, "loop_write", "paho loop_write"),
             (aiomqtt.Client, "_on_socket_register_write", "aiomqtt register_write"))
    for owner, name, label in parts:
        account(cpu, calls, owner, name, label)
    broker_path = mosquitto()
    if broker_path is None:
        return
    pairs: list[tuple[float, float, float]] = []  # (on CPU s/s, off CPU s/s, on messages/s)
    lag: dict[str, list[float]] = {"on": [], "off": []}
    on_cpu: collections.Counter[str] = collections.Counter()
    on_calls: collections.Counter[str] = collections.Counter()
    on_seconds = on_messages = 0.0
    with tempfile.TemporaryDirectory() as tmp, SimFarm("slc504", links, paced=True, ladder=True) as farm:
        directory = Path(tmp)
        broker = Broker(broker_path, directory)
        broker.start()
        text = config(farm, links, free_port(), free_port(), broker.port, directory / "bdseq.json")
        async with Gateway(parse_config(text)) as gw:
            node = gw.sparkplug
            assert node is not None
            for r in range(rounds):
                window: dict[str, tuple[float, float]] = {}
                for mode in (("off", "on") if r % 2 == 0 else ("on", "off")):
                    if mode == "on":
                        broker.start()
                        await settle(lambda: node.session_state == "online" and not node.core.unborn)
                    else:
                        broker.stop()
                        await settle(lambda: node.session_state == "disconnected")
                    await asyncio.sleep(1.0)  # the births, or the last messages, out of the window
                    cpu.clear()
                    calls.clear()
                    sent0, t0, c0 = sum(node.sent.values()), time.perf_counter(), time.process_time()
                    waits: list[float] = []
                    probe = asyncio.create_task(loop_wait(waits))
                    await asyncio.sleep(duration)
                    probe.cancel()
                    lag[mode].extend(waits)
                    elapsed = time.perf_counter() - t0
                    window[mode] = ((time.process_time() - c0) / elapsed, (sum(node.sent.values()) - sent0) / elapsed)
                    if mode == "on":
                        on_cpu.update(cpu)
                        on_calls.update(calls)
                        on_seconds += elapsed
                        on_messages += window[mode][1] * elapsed
                pairs.append((window["on"][0], window["off"][0], window["on"][1]))
        broker.stop()
    report(pairs, on_cpu, on_calls, on_seconds, on_messages, lag)


async def loop_wait(waits: list[float]) -> None:
    """What a callback made ready at a random moment waits for the loop (what a Modbus request that
    arrives then waits before its turn), every 1-3 ms: the time from ``call_soon`` to its run."""
    loop = asyncio.get_running_loop()
    while True:
        await asyncio.sleep(random.uniform(0.001, 0.003))
        ran: asyncio.Future[float] = loop.create_future()
        ready = time.perf_counter()
        loop.call_soon(stamp, ran)
        waits.append(await ran - ready)


def stamp(ran: asyncio.Future[float]) -> None:
    ran.set_result(time.perf_counter())


def report(pairs: list[tuple[float, float, float]], cpu: collections.Counter[str], calls: collections.Counter[str],
           seconds: float, messages: float, lag: dict[str, list[float]]) -> None:
    waits = {mode: sorted(values) for mode, values in lag.items()}

    def pct(mode: str, q: float) -> float:
        values = waits[mode]
        return values[min(len(values) - 1, int(q * len(values)))] * 1e6 if values else float("nan")

    print(table(("loop wait", "samples", "p50 us", "p90 us", "p99 us", "p99.9 us"),
                [(mode, len(waits[mode]), *(f"{pct(mode, q):.0f}" for q in (0.5, 0.9, 0.99, 0.999)))
                 for mode in ("off", "on")]))
    per_message = statistics.median((on - off) / rate * 1e6 for on, off, rate in pairs if rate)
    print(table(("pair", "CPU on s/s", "CPU off s/s", "published/s", "CPU per message us"),
                [(i + 1, f"{on:.3f}", f"{off:.3f}", f"{rate:.0f}", f"{(on - off) / rate * 1e6:.0f}")
                 for i, (on, off, rate) in enumerate(pairs)]))
    print(f"median: {per_message:.0f} us of the gateway's CPU per message published")
    print(table(("part (on windows)", "ms/s", "calls/s", "us/call", "us/message"),
                [(label, f"{spent / seconds * 1e3:.2f}", f"{calls[label] / seconds:.0f}",
                  f"{spent / calls[label] * 1e6:.1f}", f"{spent / messages * 1e6:.1f}")
                 for label, spent in cpu.most_common()]))
    result(cpu_us_per_message=per_message, messages_per_s=messages / seconds,
           **{f"loop_wait_{mode}_p{q}_us": pct(mode, q / 100) for mode in ("off", "on") for q in (50, 99)},
           **{label.strip().replace(" ", "_").replace(":", "").replace(".", "_") + "_us_per_message":
              spent / messages * 1e6 for label, spent in cpu.items()})


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="8 links, one pair of 1 s windows (smoke test)")
    parser.add_argument("--rounds", type=int, default=0, help="pairs of windows (default 6; quick 1)")
    parser.add_argument("--duration", type=float, default=0.0, help="window, s (default 5; quick 1)")
    parser.add_argument("--links", type=int, default=0, help=f"links (default {LINKS}; quick 8)")
    parser.add_argument("--source", type=Path, default=REPO, help="the gateway's source tree (default this one)")
    args = parser.parse_args()
    rounds = args.rounds or (1 if args.quick else 6)
    duration = args.duration or (1.0 if args.quick else 5.0)
    links = args.links or (8 if args.quick else LINKS)
    sys.path.insert(0, str(args.source))
    print_machine()
    print(f"{links} DF1 links (paced 19200 8N1, ladders running), no Modbus load, {duration:g} s windows, "
          f"{rounds} pairs, gateway from {args.source}")
    asyncio.run(run(links, rounds, duration))


if __name__ == "__main__":
    main()
