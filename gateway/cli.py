"""Command-line interface of slc-gateway.

Commands: run, reload, check-config, export-tags, simulate, probe, read, write, mode, upload, download.

Exit status 0 on success; 1 with a one-line reason on stderr on any failure; 2 for usage errors.
No protocol logic lives here: the commands call the drivers, the simulators and the app.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import os
import signal
import sys
from collections.abc import Callable, Sequence
from dataclasses import replace
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

from gateway import __version__
from gateway.errors import GatewayError
from gateway.kinds import LinkKind, kind_names, link_kinds
from gateway.sim import model_names
from gateway.sim.models import sim_models

if TYPE_CHECKING:
    from gateway.config import GatewayConfig

__all__ = ["main"]

log = logging.getLogger("gateway")

DEMO_CONFIG = Path(__file__).with_name("demo.toml")


def _per_kind(value: Callable[[LinkKind[Any]], object]) -> str:
    """``9600 (slc-ascii), 19200 (df1)``: a value of every link kind, for help texts."""
    return ", ".join(f"{value(kind)} ({name})" for name, kind in link_kinds().items())


def _add_link_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("url", help="port URL: /dev/ttyUSB0, socket://host:port, rfc2217://host:port, sim://slc150")
    names = kind_names()
    protocols = " or ".join(f"{name} ({link_kinds()[name].controllers})" for name in names)
    parser.add_argument(
        "--protocol", choices=names,
        help=f"{protocols}; default {names[0]}; a sim:// URL's controller sets it",
    )
    parser.add_argument("--baudrate", type=int, help=f"default: {_per_kind(lambda k: k.serial_defaults.baudrate)}")
    parser.add_argument("--timeout", type=float,
                        help=f"seconds per reply; default: {_per_kind(lambda k: k.serial_defaults.timeout)}")
    parser.add_argument("--retries", type=int, help="retries per transaction (default 3; probe: 1, to fail fast)")
    for kind in link_kinds().values():  # each kind's own options (its name in their help)
        if kind.tool_options is not None:
            kind.tool_options(parser)
    parser.add_argument("--trace", type=Path, help="record every byte on the link to this file")
    parser.add_argument("--json", action="store_true", help="print JSON")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="slc-gateway",
        description="Modbus TCP gateway for Allen-Bradley SLC 100/150 and SLC 500 controllers.",
    )
    parser.add_argument("--version", action="version", version=f"slc-gateway {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv: debug)")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("run", help="run the gateway (default: the built-in demo with simulators)")
    p.add_argument("config", nargs="?", type=Path, help=f"config file (default: the demo, {DEMO_CONFIG.name})")
    p.add_argument(
        "--trace", type=Path, metavar="FILE",
        help="record every byte on every link, with timestamps and direction, to FILE (troubleshooting)",
    )
    p.add_argument(
        "--listen", metavar="HOST:PORT",
        help="serve Modbus TCP here instead of the config's [modbus] listen (e.g. when 5020 is taken)",
    )
    p.add_argument(
        "--metrics-listen", metavar="HOST:PORT",
        help="serve /metrics, /healthz and the status page here instead of the config's [metrics] listen",
    )
    p.add_argument("--pid-file", type=Path, metavar="FILE",
                   help="write the process id to FILE while running (for slc-gateway reload --pid-file FILE)")

    p = sub.add_parser("reload", help="make a running gateway re-read its config file (sends it SIGHUP)")
    which = p.add_mutually_exclusive_group(required=True)
    which.add_argument("--pid-file", type=Path, metavar="FILE", help="the file given to run --pid-file")
    which.add_argument("--pid", type=int, metavar="PID", help="the gateway's process id")

    p = sub.add_parser("check-config", help="validate a config file, print the resolved config and Modbus map")
    p.add_argument("config", type=Path)

    p = sub.add_parser("export-tags", help="write every mapped point of a config file as a tag list for SCADA")
    p.add_argument("config", type=Path)
    p.add_argument("--format", choices=("csv", "kepware", "json"), default="csv",
                   help="csv (name,unit,table,address,reference,type,access,description), kepware (its tag CSV "
                        "import), json; default csv")
    p.add_argument("-o", "--output", type=Path, metavar="FILE", help="write to FILE instead of standard output; "
                   "kepware with several units: a directory, one file unit-N.csv per unit (a Kepware device)")
    p.add_argument("--unit", type=int, metavar="N", help="only the links of Modbus unit N (a Kepware device)")

    sub.add_parser("hash-password", help="read a password on standard input, print its salted scrypt hash for an "
                   "[[opcua.user]] password_hash")

    p = sub.add_parser("simulate", help="serve a simulated controller over TCP, a pseudo-terminal or a serial port")
    p.add_argument("model", choices=model_names())
    where = p.add_mutually_exclusive_group()
    where.add_argument("--listen", default="127.0.0.1:7001", help="host:port (default 127.0.0.1:7001)")
    where.add_argument("--pty", action="store_true", help="serve on a new pseudo-terminal instead; prints its path")
    where.add_argument("--port", metavar="PATH",
                       help="serve on this existing tty instead: a serial port (/dev/ttyUSB1) or one end of a "
                            "pty pair (/dev/pts/N, a socat link such as /tmp/ttyV1)")
    p.add_argument("--garble", type=int, default=0, metavar="N", help="corrupt 1 in N replies")
    p.add_argument("--drop", type=int, default=0, metavar="N", help="drop 1 in N replies")
    p.add_argument("--delay", type=float, default=0.0, metavar="S", help="add S seconds to every reply")
    for kind in link_kinds().values():  # each kind's own simulator options (its name in their help)
        if kind.simulate_options is not None:
            kind.simulate_options(p)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--no-ladder", action="store_true", help="freeze the ladder: values change only when written")
    p.add_argument("--paced", action="store_true", help="pace characters at --baudrate (a real line's speed)")
    speeds = ", ".join(f"{model.settings.baudrate} ({name})" for name, model in sim_models().items())
    p.add_argument("--baudrate", type=int, help=f"line speed for --paced (default: {speeds})")
    p.add_argument("--turnaround", type=float, default=0.0, metavar="S", help="controller turnaround delay")
    p.add_argument("--variant", action="append", default=[], metavar="NAME=VALUE",
                   help="a reading of the manual where it leaves behaviour open (repeatable; "
                        "docs/develop/controller-variants.md lists them)")
    p.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                   help="any option of the model's sim:// URL (repeatable), e.g. stations=1,2,3,4 (the gateway.sim "
                        "module doc and each model's doc in docs/ list them)")

    p = sub.add_parser("probe", help="print the controller type and firmware revision")
    _add_link_options(p)

    p = sub.add_parser("read", help="read items: " + _per_kind(lambda kind: kind.item_examples[0]))
    _add_link_options(p)
    p.add_argument("items", nargs="+", metavar="ITEM")

    p = sub.add_parser("write", help="write items: " + _per_kind(lambda kind: kind.item_examples[1]))
    _add_link_options(p)
    p.add_argument("assignments", nargs="+", metavar="ITEM=VALUE")

    p = sub.add_parser("mode", help="change the controller mode")
    _add_link_options(p)
    p.add_argument("mode", choices=("run", "program", "test", "save"))

    p = sub.add_parser("upload", help="back up the controller's program to FILE (program mode)")
    _add_link_options(p)
    p.add_argument("file", type=Path)

    p = sub.add_parser("download", help="restore the program in FILE to the controller (program mode)")
    _add_link_options(p)
    p.add_argument("file", type=Path)
    return parser


def _setup_logging(verbose: int, quiet_level: int = logging.WARNING) -> None:
    level = quiet_level if verbose == 0 else logging.INFO if verbose == 1 else logging.DEBUG
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    command: str = args.command
    if command == "run":
        _setup_logging(max(args.verbose, 1))
    elif command in ("simulate", "check-config", "export-tags", "reload"):
        _setup_logging(args.verbose)
    else:
        # One-shot tools report a failure once, as the one-line reason below (the link's "down"
        # warning would say it twice); -v shows the link log.
        _setup_logging(args.verbose, logging.ERROR)
    try:
        if command == "run":
            return _run(args.config, args.trace, args.listen, args.metrics_listen, args.pid_file)
        if command == "reload":
            return _reload(args.pid_file, args.pid)
        if command == "check-config":
            return _check_config(args.config)
        if command == "export-tags":
            return _export_tags(args.config, args.format, args.output, args.unit)
        if command == "hash-password":
            return _hash_password()
        if command == "simulate":
            return asyncio.run(_simulate(args))
        from gateway import tools

        return asyncio.run(tools.run_tool(command, args))
    except GatewayError as exc:
        print(f"slc-gateway {command}: {exc}", file=sys.stderr)
        return 1
    except OSError as exc:  # TimeoutError is one, and may carry no message
        print(f"slc-gateway {command}: {exc or type(exc).__name__}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130


def _hash_password() -> int:
    """The password on standard input (its first line; prompted, not echoed, on a terminal) as a hash."""
    from gateway.opcua.passwords import hash_password

    if sys.stdin.isatty():
        import getpass

        password = getpass.getpass("password: ")
    else:
        password = sys.stdin.readline().rstrip("\r\n")
    if not password:
        print("slc-gateway hash-password: no password on standard input", file=sys.stderr)
        return 1
    print(hash_password(password))
    return 0


def _checked_listen(option: str, listen: str) -> str:
    from gateway.config import parse_listen

    try:
        parse_listen(listen)
    except ValueError as exc:
        raise GatewayError(f"{option}: {exc}") from exc
    return listen


def _run(config_path: Path | None, trace: Path | None = None, listen: str | None = None,
         metrics_listen: str | None = None, pid_file: Path | None = None) -> int:
    from gateway.app import LISTEN_FLAGS, run_gateway
    from gateway.reload import ConfigSource

    if listen is not None:
        listen = _checked_listen(LISTEN_FLAGS["modbus"], listen)
    if metrics_listen is not None:
        metrics_listen = _checked_listen(LISTEN_FLAGS["metrics"], metrics_listen)
    source = ConfigSource(config_path or DEMO_CONFIG, partial(_overrides, listen, metrics_listen, trace))
    loaded = source.load()
    if trace is not None:
        log.info("recording every byte on every link to %s", trace)
    if config_path is None:
        log.info("no config file given: running the demo (%s) against the built-in simulators", DEMO_CONFIG)
    if pid_file is None:
        return asyncio.run(run_gateway(loaded, source))
    try:
        pid_file.write_text(f"{os.getpid()}\n", encoding="ascii")
    except OSError as exc:
        raise GatewayError(f"--pid-file {pid_file}: cannot write it: {exc.strerror or exc}") from None
    try:
        return asyncio.run(run_gateway(loaded, source))
    finally:
        with contextlib.suppress(OSError):
            pid_file.unlink()


def _overrides(listen: str | None, metrics_listen: str | None, trace: Path | None,
               config: GatewayConfig) -> GatewayConfig:
    """What ``run``'s options change in the config file (at start, and at every reload)."""
    from gateway.config import MetricsConfig

    if listen is not None:
        config = config.model_copy(update={"modbus": config.modbus.model_copy(update={"listen": listen})})
    if metrics_listen is not None:
        metrics = config.metrics or MetricsConfig()
        config = config.model_copy(update={"metrics": metrics.model_copy(update={"listen": metrics_listen})})
    if trace is not None:
        links = tuple(link.model_copy(update={"trace": trace}) for link in config.link)
        config = config.model_copy(update={"link": links})
    return config


def _reload(pid_file: Path | None, pid: int | None) -> int:
    """``slc-gateway reload``: SIGHUP to the gateway of ``pid_file`` (or ``pid``), once it is one."""
    if pid_file is not None:
        try:
            text = pid_file.read_text(encoding="ascii").strip()
        except (OSError, UnicodeDecodeError) as exc:
            raise GatewayError(f"cannot read {pid_file}: {getattr(exc, 'strerror', None) or exc}: is the gateway "
                               "running with run --pid-file?") from None
        if not text.isdigit():
            raise GatewayError(f"{pid_file} holds {text[:20]!r}, not a process id")
        pid = int(text)
    assert pid is not None
    hangup = getattr(signal, "SIGHUP", None)
    if hangup is None:
        raise GatewayError("no SIGHUP on this system: restart the gateway to load its config")
    cmdline = Path(f"/proc/{pid}/cmdline")
    if cmdline.parent.parent.is_dir():  # Linux: never send SIGHUP (which ends most programs) to another one
        try:
            words = cmdline.read_bytes().split(b"\0")
        except OSError:
            raise GatewayError(f"no process {pid}: is the gateway running?") from None
        if not any(b"gateway" in word for word in words[:3]) or b"run" not in words:
            shown = " ".join(w.decode(errors="replace") for w in words if w)[:80]
            raise GatewayError(f"process {pid} is not slc-gateway run ({shown}): nothing sent")
    try:
        os.kill(pid, hangup)
    except ProcessLookupError:
        raise GatewayError(f"no process {pid}: is the gateway running?") from None
    print(f"slc-gateway reload: asked process {pid} to reload its config file: its log says what changed "
          "(or why the file did not load: then nothing changed)", file=sys.stderr)
    return 0


def _check_config(path: Path) -> int:
    from gateway.app import describe_map
    from gateway.config import load_config

    config = load_config(path)
    for warning in config.warnings():
        print(f"slc-gateway check-config: warning: {warning}", file=sys.stderr)
    print(config.describe())
    print()
    print(describe_map(config))
    return 0


def _export_tags(path: Path, format_name: str, output: Path | None, unit: int | None) -> int:
    from gateway.config import load_config
    from gateway.tags import config_tags, render

    config = load_config(path)
    if unit is not None and all(link.unit != unit for link in config.link):
        units = ", ".join(str(link.unit) for link in config.link)
        raise GatewayError(f"--unit {unit}: no link of {path} is unit {unit} (its units: {units})")
    tags = config_tags(config.link, unit)
    if format_name == "kepware":
        return _export_kepware(path, tags, output)
    _write_tags(render(tags, format_name), format_name, output)
    return 0


def _write_tags(text: str, format_name: str, output: Path | None) -> None:
    if output is None:
        sys.stdout.write(text)
    else:
        output.write_text(text, encoding="utf-8", newline="")
        print(f"slc-gateway export-tags: {text.count(chr(10)) - (format_name != 'json')} tags written to "
              f"{output}", file=sys.stderr)


def _export_kepware(path: Path, tags: Sequence[Any], output: Path | None) -> int:
    """One Kepware device per unit: a file (or standard output) for one unit; for several, ``-o DIR``
    gets ``unit-<N>.csv`` each.  Every device's word-order setting is said, and a unit whose 32-bit
    values mix word orders is warned about (``gateway.tags.KepwareDevice``)."""
    from gateway.tags import kepware_devices, render

    devices = kepware_devices(tags)
    if len(devices) > 1 and (output is None or output.is_file()):
        units = ", ".join(str(device.unit) for device in devices)
        where = "standard output" if output is None else f"the file {output}"
        raise GatewayError(f"--format kepware: {path} has units {units}, and a Kepware device is one unit: "
                           f"choose one with --unit N, or give -o DIR for one file per unit (not {where})")
    if len(devices) > 1:
        assert output is not None
        output.mkdir(parents=True, exist_ok=True)
    for device in devices:
        target = output / f"unit-{device.unit}.csv" if len(devices) > 1 and output is not None else output
        _write_tags(render(device.tags, "kepware"), "kepware", target)
        print(f"slc-gateway export-tags: unit {device.unit} ({', '.join(device.links)}): a Kepware Modbus device "
              f"with ID {device.unit} and {device.setting} (32-bit values {device.word_order})", file=sys.stderr)
        if device.misread:
            print(f"slc-gateway export-tags: warning: {device.warning()}", file=sys.stderr)
    return 0


async def _simulate(args: argparse.Namespace) -> int:
    from gateway.config import parse_listen
    from gateway.sim import create_simulator
    from gateway.sim.serve import close_tcp, serve_pty, serve_tcp, serve_tty

    model = sim_models()[args.model]
    options: dict[str, str] = {"seed": str(args.seed)}
    for key in ("garble", "drop"):
        value = getattr(args, key)
        if value:
            options[key] = str(value)
    if args.delay:
        options["delay"] = str(args.delay)
    for key in sorted(model.cli_options):  # the fault options this model takes (others are not its own)
        if getattr(args, key, 0):
            options[key] = str(getattr(args, key))
    for key in sorted(model.cli_settings):
        options[key] = str(getattr(args, key))
    if args.no_ladder:
        options["ladder"] = "0"
    if args.variant:
        options["variant"] = ",".join(args.variant)
    for text in args.option:
        key, sep, value = text.partition("=")
        if not sep or not key.strip():
            raise GatewayError(f"--option {text!r}: give KEY=VALUE, as in a sim:// URL (e.g. --option dead=3)")
        options[key.strip()] = value.strip()
    try:
        device = create_simulator(args.model, options)
    except ValueError as exc:
        raise GatewayError(str(exc)) from exc
    settings = replace(model.settings, baudrate=args.baudrate or model.settings.baudrate)
    paced = settings if args.paced else None
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        with contextlib.suppress(NotImplementedError):
            loop.add_signal_handler(sig, stop.set)
    if args.pty or args.port:
        if args.port:
            pty = serve_tty(device, args.port, settings, settings=paced, turnaround=args.turnaround)
        else:
            pty = serve_pty(device, settings=paced, turnaround=args.turnaround)
        print(f"simulated {args.model} on {pty.path}", flush=True)
        try:
            await stop.wait()
        finally:
            pty.close()
        return 0
    host, port = parse_listen(args.listen)
    server = await serve_tcp(device, host, port, settings=paced, turnaround=args.turnaround)
    bound = server.sockets[0].getsockname()
    print(f"simulated {args.model} listening on {bound[0]}:{bound[1]} (socket://{bound[0]}:{bound[1]})", flush=True)
    try:
        await stop.wait()
    finally:
        await close_tcp(server)  # drop connected clients too, so that we exit while one is connected
    return 0

