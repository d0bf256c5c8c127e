"""Wire links, pollers and the Modbus server together under one ``asyncio.TaskGroup``."""

from __future__ import annotations

import asyncio
import contextlib
import errno
import logging
import signal
import ssl
import time
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Final

from gateway.config import GatewayConfig, TlsConfig, parse_listen
from gateway.config._common import show
from gateway.config.link import LinkBase
from gateway.errors import ConfigError, GatewayError
from gateway.health import Health
from gateway.http import HttpServer, Routes
from gateway.kinds import LinkKind, LinkRunner, link_kind, link_kinds
from gateway.metrics import Prometheus
from gateway.modbus.admission import RolePolicy
from gateway.modbus.backend import GatewayBackend
from gateway.modbus.mapping import STATUS_BASE, STATUS_REGISTERS, Table
from gateway.modbus.server import ModbusTcpServer, make_tls_context
from gateway.opcua.server import OpcUaServer
from gateway.reload import ConfigSource, ConfigStatus, LoadedConfig, line_changes, lines_of, restart_needed
from gateway.sparkplug.driver import SparkplugNode
from gateway.status import StatusPage
from gateway.transport import describe_url, set_trace_limits
from gateway.unit import Unit

__all__ = ["LISTEN_FLAGS", "Gateway", "LineRun", "build_units", "describe_map", "listen_error",
           "run_gateway"]

log = logging.getLogger("gateway")


def build_units(links: Sequence[LinkBase]) -> tuple[list[Unit[Any, Any]], list[LinkRunner]]:
    """The runtime of the ``[[link]]`` tables: their units (in file order) and the runners of their lines.

    Each kind builds all of its links among ``links`` at once (links that share a line share its runner);
    the Gateway passes the links of one line (``LineRun``).
    """
    by_name: dict[str, Unit[Any, Any]] = {}
    runners: list[LinkRunner] = []
    for protocol in dict.fromkeys(link.protocol for link in links):
        kind = _kind(protocol)
        built = kind.build_units(links)
        by_name.update((unit.name, unit) for unit in built.units)
        runners.extend(built.runners)
    missing = [link.name for link in links if link.name not in by_name]
    if missing:
        raise ConfigError(f"no unit was built for link(s) {', '.join(missing)}")
    return [by_name[link.name] for link in links], runners


def _kind(protocol: str) -> LinkKind[Any]:
    try:
        return link_kind(protocol)
    except KeyError:
        raise ConfigError(f"unknown protocol {protocol!r}: known are {', '.join(link_kinds())}") from None


#: The command-line options that override a config's listeners (``slc-gateway run``), by the listener's name.
LISTEN_FLAGS: Final = {"modbus": "--listen", "metrics": "--metrics-listen"}
#: The config key of each listener, by its name.
LISTEN_KEYS: Final = {"modbus": "[modbus] listen", "modbus-tls": "[modbus.tls] listen", "metrics": "[metrics] listen",
               "opcua": "[opcua] listen"}


def listen_error(name: str, listen: str, exc: OSError) -> ConfigError:
    """A listener that cannot bind, named by its config key and command-line option (a port in use ...)."""
    why = {
        errno.EADDRINUSE: "the port is in use (by another slc-gateway, or another server)",
        errno.EADDRNOTAVAIL: "not an address of this machine",
        errno.EACCES: "permission denied (ports below 1024 need CAP_NET_BIND_SERVICE)",
    }.get(exc.errno or 0, exc.strerror or str(exc))
    remedy = f"set another {LISTEN_KEYS[name]}"
    if name in LISTEN_FLAGS:
        remedy += f" or run with {LISTEN_FLAGS[name]} HOST:PORT"
    return ConfigError(f"{LISTEN_KEYS[name]} = {show(listen)}: cannot listen there: {why}: {remedy}")


@dataclass(eq=False, slots=True)
class LineRun:
    """The links of one port (one line) as the gateway runs them: their units, the runners of the
    line, and the tasks running both once started.  A reload keeps it whole or replaces it whole."""

    links: tuple[LinkBase, ...]
    units: list[Unit[Any, Any]]
    runners: list[LinkRunner]
    tasks: list[asyncio.Task[None]] = field(default_factory=list)

    @classmethod
    def build(cls, links: tuple[LinkBase, ...]) -> LineRun:
        units, runners = build_units(links)
        return cls(links, units, runners)

    def start(self, group: asyncio.TaskGroup) -> None:
        self.tasks = [group.create_task(runner.run(), name=f"{runner.name}-link") for runner in self.runners]
        self.tasks += [group.create_task(unit.run(), name=f"{unit.name}-poller") for unit in self.units]

    async def stop(self) -> None:
        """Stop cleanly: the writes already queued run to their answers first (each is answered within
        its link's write_timeout anyway), then the pollers and runners stop and the ports close."""
        drains = [asyncio.wait_for(unit.writes.drain(), unit.write_timeout) for unit in self.units]
        for result in await asyncio.gather(*drains, return_exceptions=True):
            if isinstance(result, Exception) and not isinstance(result, TimeoutError):
                log.warning("reload: draining the writes of a stopping link failed: %s", result)
        for task in self.tasks:
            task.cancel()
        if self.tasks:
            await asyncio.wait(self.tasks)
        for runner in self.runners:
            await runner.close()


def _server_options(config: GatewayConfig) -> dict[str, Any]:
    """The Modbus listeners' settings a reload applies (``ModbusTcpServer.reconfigure``)."""
    modbus = config.modbus
    return dict(
        max_connections=modbus.max_connections,
        max_connections_per_address=modbus.per_address_cap,
        idle_timeout=modbus.idle_timeout or None,
        frame_timeout=modbus.frame_timeout,
        allow=list(modbus.allow) or None,
        loopback_reads=modbus.loopback_reads,
        log_interval=config.logging.repeat_interval,
    )


def _tls_options(tls: TlsConfig) -> dict[str, Any]:
    """The TLS listener's own settings, its certificate files read now."""
    return dict(
        ssl_context=make_tls_context(str(tls.cert), str(tls.key), str(tls.client_ca) if tls.client_ca else None),
        handshake_timeout=tls.handshake_timeout,
        max_handshakes=tls.max_handshakes,
        roles=RolePolicy(dict(tls.roles), tls.default_rights) if tls.roles else None,
    )


class Gateway:
    """The whole service.  ``async with Gateway(config) as gw:`` runs it in the background (tests).

    ``source``: where ``config`` came from, for :meth:`reload`; ``sha256``: of its file (``/metrics``).
    """

    def __init__(self, config: GatewayConfig, source: ConfigSource | None = None, sha256: str | None = None) -> None:
        self.config = config
        self.source = source
        self.config_status = ConfigStatus(sha256, time.time())
        self.lines = {port: LineRun.build(links) for port, links in lines_of(config.link).items()}
        self.backend = GatewayBackend(())
        self._index_units()
        modbus = config.modbus
        set_trace_limits(config.logging.trace_max_bytes, config.logging.trace_backups)
        common = _server_options(config)
        self.servers: list[ModbusTcpServer] = []
        if modbus.plain_enabled:  # listen = "": TLS only
            host, port = parse_listen(modbus.listen)
            self.servers.append(ModbusTcpServer(self.backend, host, port, name="modbus", **common))
        if modbus.tls is not None:
            tls_host, tls_port = parse_listen(modbus.tls.listen)
            self.servers.append(ModbusTcpServer(self.backend, tls_host, tls_port, name="modbus-tls",
                                                **_tls_options(modbus.tls), **common))
        #: the Sparkplug B edge node ([sparkplug]), None when not configured
        self.sparkplug = SparkplugNode(config.sparkplug, config.link, self.units) if config.sparkplug else None
        #: the [metrics] listener's rooms, side by side: the status page, /metrics, /healthz (gateway.http)
        self.status_page = StatusPage(self, config.link, self.config_status)
        self.metrics: HttpServer | None = None
        if config.metrics is not None:
            self.metrics = HttpServer(
                self.http_routes(),
                config.metrics.listen,
                allow=list(config.metrics.allow) or None,
                max_connections=config.metrics.max_connections,
                log_interval=config.logging.repeat_interval,
            )
        self._group: asyncio.TaskGroup | None = None
        self._sparkplug_task: asyncio.Task[None] | None = None
        #: the OPC UA server ([opcua]), None when not configured
        self.opcua = OpcUaServer(config.opcua, config.link, self.units) if config.opcua else None
        self._started = asyncio.Event()
        self._reloader: asyncio.Task[None] | None = None
        self._stopping: list[LineRun] = []
        self._reload_lock = asyncio.Lock()
        self._reload_again = False

    def _index_units(self) -> None:
        """``units`` in file order, ``runners`` and the Modbus dispatch, from ``lines``."""
        by_name = {unit.name: unit for line in self.lines.values() for unit in line.units}
        self.units: list[Unit[Any, Any]] = [by_name[link.name] for link in self.config.link]
        self.runners: list[LinkRunner] = [runner for line in self.lines.values() for runner in line.runners]
        self.backend.units = {unit.unit_id: unit for unit in self.units}

    @property
    def port(self) -> int:
        return self.servers[0].port

    def _listeners(self) -> list[tuple[str, str, Callable[[], Awaitable[None]]]]:
        """(name, listen, start) of every listener, for :func:`listen_error`."""
        config = self.config
        listen = {"modbus": config.modbus.listen, "modbus-tls": config.modbus.tls.listen if config.modbus.tls else ""}
        found: list[tuple[str, str, Callable[[], Awaitable[None]]]] = [
            (server.name, listen[server.name], server.start) for server in self.servers]
        if self.metrics is not None and config.metrics is not None:
            found.append(("metrics", config.metrics.listen, self.metrics.start))
        if self.opcua is not None and config.opcua is not None:
            found.append(("opcua", config.opcua.listen, self.opcua.start))
        return found

    async def run(self, stop: asyncio.Event | None = None) -> None:
        """Run until ``stop`` is set (or cancelled); then stop cleanly."""
        stop = stop or asyncio.Event()
        for name, listen, start in self._listeners():
            try:
                await start()
            except OSError as exc:
                await asyncio.gather(*(server.close() for server in self.servers))
                if self.metrics is not None:
                    await self.metrics.close()
                if self.opcua is not None:
                    await self.opcua.close()
                raise listen_error(name, listen, exc) from None
        try:
            async with asyncio.TaskGroup() as group:
                self._group = group
                for line in self.lines.values():
                    line.start(group)
                for server in self.servers:
                    group.create_task(server.serve_forever(), name=f"{server.name}-server")
                self._start_sparkplug()
                if self.opcua is not None:
                    group.create_task(self.opcua.run(), name="opcua")
                self._started.set()
                await stop.wait()
                await self._shutdown()
                raise _Stopped
        except* _Stopped:
            pass
        finally:
            self._group = None

    async def _shutdown(self) -> None:
        # Stop accepting; requests in flight finish (a write waiting for its controller gets
        # its answer, or 0x0B when the link closes under it); then close the links.  A driver
        # runs until cancelled: cancel it first, so that closing its port cannot send it into a
        # reconnect backoff that SIGTERM would have to wait out.
        lines = [*self._stopping, *self.lines.values()]  # a reload's lines still stopping too
        if self._reloader is not None:
            self._reloader.cancel()
        await asyncio.gather(*(server.close() for server in self.servers))
        await self._stop_sparkplug()  # NDEATH before the links close (their DDEATHs would be noise)
        if self.opcua is not None:
            await self.opcua.close()  # its sessions closed, before the links close
        for line in lines:
            for task in line.tasks:
                task.cancel()
        for line in lines:
            for runner in line.runners:
                await runner.close()
        if self.metrics is not None:
            await self.metrics.close()

    # --- the Sparkplug edge node ---------------------------------------------------------------

    def _start_sparkplug(self) -> None:
        if self.sparkplug is not None and self._group is not None:
            self._sparkplug_task = self._group.create_task(self.sparkplug.run(), name="sparkplug")

    async def _stop_sparkplug(self) -> None:
        """A clean stop of the edge node's session: its DCMD writes in flight finish, then the NDEATH."""
        if self.sparkplug is None:
            return
        await self.sparkplug.close()
        self.sparkplug.detach()
        if self._sparkplug_task is not None:
            self._sparkplug_task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._sparkplug_task
            self._sparkplug_task = None

    async def _renew_sparkplug(self) -> None:
        """After a reload changed the links: the node's devices and metrics are the units', so its
        session ends (NDEATH) and a new one (the next bdSeq) births the devices as they are now
        (Sparkplug 3.0 §5.4, §5.7: a birth certificate is the whole set of metrics; a set that changes
        is a new session's birth).  ``[sparkplug]`` itself takes a restart (``gateway.reload``)."""
        if self.sparkplug is None:
            return
        await self._stop_sparkplug()
        self.sparkplug = SparkplugNode(self.sparkplug.config, self.config.link, self.units)
        self._start_sparkplug()

    # --- reload ---------------------------------------------------------------------------------

    def request_reload(self) -> None:
        """Reload the config file soon (SIGHUP); requests during a reload make one more after it."""
        if self._group is None:
            log.warning("reload: the gateway is not running yet: the file is read at start")
            return
        if self._reloader is not None and not self._reloader.done():
            self._reload_again = True
            return
        self._reloader = self._group.create_task(self._reload_while_asked(), name="config-reload")

    async def _reload_while_asked(self) -> None:
        self._reload_again = True
        while self._reload_again:
            self._reload_again = False
            try:
                await self.reload()
            except Exception as exc:  # a bug in a reload must not stop a gateway that serves
                log.exception("reload: failed")
                self._reload_failed(f"internal error: {exc!r}")

    async def reload(self) -> bool:
        """Read the config file again and apply it (``gateway.reload``); False when it did not load,
        and nothing changed."""
        if self.source is None:
            log.warning("reload: this gateway was not started from a config file: nothing to read")
            return False
        async with self._reload_lock:  # one reload at a time, each from the config the last one left
            try:
                loaded = self.source.load()
            except GatewayError as exc:
                self._reload_failed(str(exc))
                return False
            return await self.apply(loaded.config, loaded.sha256)

    def _reload_failed(self, reason: str) -> None:
        status = self.config_status
        status.reload_failures += 1
        status.last_failure = reason
        log.error("reload: %s", reason)
        log.error("reload: nothing changed: still serving the config loaded before (sha256 %s)",
                  status.short_sha256 or "none")

    async def apply(self, config: GatewayConfig, sha256: str | None = None) -> bool:
        """Run ``config`` from now on, keeping what did not change (``gateway.reload``)."""
        changes = line_changes(self.config.link, config.link)
        new_lines = lines_of(config.link)
        try:  # everything that can fail, before anything changes
            started = {key: LineRun.build(new_lines[key]) for key in changes.started}
            tls = _tls_options(config.modbus.tls) if config.modbus.tls is not None else None
        except (GatewayError, OSError, ssl.SSLError) as exc:
            self._reload_failed(str(exc))
            return False
        old, stopping = self.config, [self.lines[key] for key in changes.stopped]
        self.config = config
        self.lines = {key: self.lines[key] if key in changes.kept else started[key] for key in new_lines}
        self._index_units()  # requests for a unit that stops get 0x0A from now on; a new one's, 0x0B till it is up
        self._apply_settings(config, tls)
        self._stopping = stopping
        try:
            await asyncio.gather(*(line.stop() for line in stopping))
        finally:
            self._stopping = []
        self._rebuild([key for key in changes.started if key in changes.stopped])
        if self._group is not None:
            for key in changes.started:
                self.lines[key].start(self._group)
        if changes.started or changes.stopped:
            await self._renew_sparkplug()
            if self.opcua is not None:
                await self.opcua.relink(config.link, self.units)
        needed = restart_needed(old, config)
        status = self.config_status
        status.sha256, status.loaded_at, status.restart_needed = sha256, time.time(), tuple(needed)
        status.reloads += 1
        status.last_failure = None
        log.info("reload: loaded %s (sha256 %s); %s", self.source.path if self.source else "a new config",
                 status.short_sha256 or "none", changes.summary())
        for setting in needed:
            log.warning("reload: %s: a restart is needed to apply it", setting)
        return True

    def _rebuild(self, keys: Sequence[str]) -> None:
        """Build again the lines that replace a line just stopped on the same port: what the old one
        stored while it stopped (a target link's ``persist`` file) is what the new one loads."""
        for key in keys:
            try:
                self.lines[key] = LineRun.build(self.lines[key].links)
            except (GatewayError, OSError) as exc:  # built a moment ago: the file changed under us
                log.error("reload: line %s: built again after its old links stopped, it failed (%s): it runs as "
                          "built before they stopped", key, exc)
        self._index_units()

    def _apply_settings(self, config: GatewayConfig, tls: dict[str, Any] | None) -> None:
        """What the running listeners and the log take at once (``gateway.reload.LIVE_KEYS``)."""
        logging.getLogger().setLevel(config.logging.level)
        set_trace_limits(config.logging.trace_max_bytes, config.logging.trace_backups)
        common = _server_options(config)
        for server in self.servers:
            if server.ssl_context is None:
                server.reconfigure(**common)
            elif tls is not None:  # [modbus.tls] removed: the listener runs on as it is till a restart
                server.reconfigure(**tls, **common)
        self.status_page.set_links(config.link)
        if self.metrics is not None and config.metrics is not None:
            self.metrics.reconfigure(allow=list(config.metrics.allow) or None,
                                     max_connections=config.metrics.max_connections,
                                     log_interval=config.logging.repeat_interval)

    def http_routes(self) -> Routes:
        """The [metrics] listener's path -> handler table: its rooms side by side (``gateway.http``)."""
        routes = Routes()
        self.status_page.add_routes(routes)
        routes.add("/metrics", Prometheus(self, self.config_status).route)
        routes.add("/healthz", Health(self).route)
        return routes

    async def __aenter__(self) -> Gateway:
        self._stop = asyncio.Event()
        self._task = asyncio.create_task(self.run(self._stop), name="gateway")
        started = asyncio.create_task(self._started.wait())
        done, _ = await asyncio.wait({self._task, started}, return_when=asyncio.FIRST_COMPLETED)
        if self._task in done:
            started.cancel()
            self._task.result()  # raises the start-up error
        return self

    async def __aexit__(self, *exc: object) -> None:
        self._stop.set()
        with contextlib.suppress(asyncio.CancelledError):
            await self._task


class _Stopped(Exception):
    pass


async def run_gateway(loaded: LoadedConfig, source: ConfigSource | None = None) -> int:
    """``slc-gateway run``: serve until SIGINT or SIGTERM; SIGHUP reloads ``source``."""
    config = loaded.config
    logging.getLogger().setLevel(config.logging.level)
    gateway = Gateway(config, source, loaded.sha256)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    handlers: list[tuple[int, Callable[[], None]]] = [(signal.SIGINT, stop.set), (signal.SIGTERM, stop.set)]
    hangup = getattr(signal, "SIGHUP", None)  # not on Windows
    if hangup is not None:
        handlers.append((hangup, gateway.request_reload))
    for sig, handler in handlers:
        with contextlib.suppress(NotImplementedError):
            loop.add_signal_handler(sig, handler)
    for warning in config.warnings():
        log.warning("configuration: %s", warning)
    for unit in gateway.units:
        log.info("link %s: %s on %s as Modbus unit %d", unit.name, type(unit.driver).__name__,
                 describe_url(unit.driver.url), unit.unit_id)
    await gateway.run(stop)
    log.info("stopped")
    return 0


def describe_map(config: GatewayConfig) -> str:
    """The Modbus map and read plan of every link (``check-config``)."""
    lines: list[str] = []
    for link in config.link:
        kind = _kind(link.protocol)
        plan = kind.plan_of(link)
        fast = sum(1 for b in plan.blocks if b.scan.value == "fast")
        lines.append(f"unit {link.unit} ({link.name}, {link.protocol}, {describe_url(link.port)}):")
        for table in Table:
            runs = plan.ranges(table)
            if runs:
                text = ", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in runs)
                lines.append(f"  {table.value:9} {text}")
        status_last = STATUS_BASE + sum(width for _, width in STATUS_REGISTERS) - 1
        lines.append(f"  {'status':9} input {STATUS_BASE}-{status_last}")
        if kind.is_polled(link):
            lines.append(f"  read plan: {len(plan.blocks)} blocks ({fast} fast, {len(plan.blocks) - fast} slow)")
        else:
            lines.append("  not polled: the peer sends its data; served as it arrives")
        lines.extend(f"    {line}" for line in kind.plan_lines(plan))
    return "\n".join(lines)
