"""Wire links, pollers and the Modbus server together under one ``asyncio.TaskGroup``."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import signal
from collections.abc import Sequence
from typing import Any

from gateway.config import GatewayConfig, parse_listen
from gateway.config.link import LinkBase
from gateway.errors import ConfigError, ModbusExceptionReply
from gateway.kinds import LinkKind, LinkRunner, link_kind, link_kinds
from gateway.metrics import MetricsServer
from gateway.modbus.admission import RolePolicy
from gateway.modbus.mapping import STATUS_BASE, STATUS_REGISTERS, Table
from gateway.modbus.server import ModbusTcpServer, make_tls_context
from gateway.sparkplug.driver import SparkplugNode
from gateway.transport import describe_url, set_trace_limits
from gateway.unit import Unit

__all__ = ["Gateway", "GatewayBackend", "build_units", "describe_map", "run_gateway"]

log = logging.getLogger("gateway")


def build_units(links: Sequence[LinkBase]) -> tuple[list[Unit[Any, Any]], list[LinkRunner]]:
    """The runtime of the ``[[link]]`` tables: their units (in file order) and the runners of their lines.

    Each kind builds all of its links at once (links that share a line share its runner).
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


class GatewayBackend:
    """The Modbus server's backend: dispatch by unit id."""

    def __init__(self, units: Sequence[Unit[Any, Any]]) -> None:
        self.units = {unit.unit_id: unit for unit in units}

    def has_unit(self, unit: int) -> bool:
        return unit in self.units

    def _unit(self, unit: int) -> Unit[Any, Any]:
        try:
            return self.units[unit]
        except KeyError:
            raise ModbusExceptionReply(ModbusExceptionReply.GATEWAY_PATH_UNAVAILABLE) from None

    def read_now(self, unit: int, function_code: int, address: int, count: int) -> bytes:
        """FC1-FC4 from the unit's images: the reply's data bytes (the server's fast path)."""
        target = self.units.get(unit)
        if target is None:
            raise ModbusExceptionReply(ModbusExceptionReply.GATEWAY_PATH_UNAVAILABLE)
        if function_code == 3:
            return target.read_register_bytes(Table.HOLDING, address, count)
        if function_code == 4:
            return target.read_register_bytes(Table.INPUT, address, count)
        return target.read_bit_bytes(Table.COIL if function_code == 1 else Table.DISCRETE, address, count)

    async def read_coils(self, unit: int, address: int, count: int) -> Sequence[bool]:
        return self._unit(unit).read_bits(Table.COIL, address, count)

    async def read_discrete_inputs(self, unit: int, address: int, count: int) -> Sequence[bool]:
        return self._unit(unit).read_bits(Table.DISCRETE, address, count)

    async def read_holding_registers(self, unit: int, address: int, count: int) -> Sequence[int]:
        return self._unit(unit).read_registers(Table.HOLDING, address, count)

    async def read_input_registers(self, unit: int, address: int, count: int) -> Sequence[int]:
        return self._unit(unit).read_registers(Table.INPUT, address, count)

    async def write_coils(self, unit: int, address: int, values: Sequence[bool]) -> None:
        await self._unit(unit).write_bits(address, values)

    async def write_registers(self, unit: int, address: int, values: Sequence[int]) -> None:
        await self._unit(unit).write_registers(address, values)


class Gateway:
    """The whole service.  ``async with Gateway(config) as gw:`` runs it in the background (tests)."""

    def __init__(self, config: GatewayConfig) -> None:
        self.config = config
        self.units, self.runners = build_units(config.link)
        self.backend = GatewayBackend(self.units)
        modbus = config.modbus
        set_trace_limits(config.logging.trace_max_bytes, config.logging.trace_backups)
        common: dict[str, Any] = dict(
            max_connections=modbus.max_connections,
            max_connections_per_address=modbus.per_address_cap,
            idle_timeout=modbus.idle_timeout or None,
            frame_timeout=modbus.frame_timeout,
            allow=list(modbus.allow) or None,
            loopback_reads=modbus.loopback_reads,
            log_interval=config.logging.repeat_interval,
        )
        self.servers: list[ModbusTcpServer] = []
        if modbus.plain_enabled:  # listen = "": TLS only
            host, port = parse_listen(modbus.listen)
            self.servers.append(ModbusTcpServer(self.backend, host, port, name="modbus", **common))
        if modbus.tls is not None:
            tls = modbus.tls
            context = make_tls_context(str(tls.cert), str(tls.key), str(tls.client_ca) if tls.client_ca else None)
            tls_host, tls_port = parse_listen(tls.listen)
            roles = RolePolicy(dict(tls.roles), tls.default_rights) if tls.roles else None
            self.servers.append(
                ModbusTcpServer(
                    self.backend,
                    tls_host,
                    tls_port,
                    ssl_context=context,
                    name="modbus-tls",
                    handshake_timeout=tls.handshake_timeout,
                    max_handshakes=tls.max_handshakes,
                    roles=roles,
                    **common,
                )
            )
        self.metrics: MetricsServer | None = None
        if config.metrics is not None:
            self.metrics = MetricsServer(
                self,
                config.metrics.listen,
                allow=list(config.metrics.allow) or None,
                max_connections=config.metrics.max_connections,
                log_interval=config.logging.repeat_interval,
                links=config.link,
            )
        #: the Sparkplug B edge node ([sparkplug]), None when not configured
        self.sparkplug = SparkplugNode(config.sparkplug, config.link, self.units) if config.sparkplug else None
        self._task: asyncio.Task[None] | None = None
        self._links: list[asyncio.Task[None]] = []
        self._started = asyncio.Event()

    @property
    def port(self) -> int:
        return self.servers[0].port

    async def run(self, stop: asyncio.Event | None = None) -> None:
        """Run until ``stop`` is set (or cancelled); then stop cleanly."""
        stop = stop or asyncio.Event()
        for server in self.servers:
            await server.start()
        if self.metrics is not None:
            await self.metrics.start()
        try:
            async with asyncio.TaskGroup() as group:
                self._links = []
                for runner in self.runners:
                    self._links.append(group.create_task(runner.run(), name=f"{runner.name}-link"))
                for unit in self.units:
                    group.create_task(unit.run(), name=f"{unit.name}-poller")
                for server in self.servers:
                    group.create_task(server.serve_forever(), name=f"{server.name}-server")
                if self.sparkplug is not None:
                    self._links.append(group.create_task(self.sparkplug.run(), name="sparkplug"))
                self._started.set()
                await stop.wait()
                await self._shutdown()
                raise _Stopped
        except* _Stopped:
            pass

    async def _shutdown(self) -> None:
        # Stop accepting; requests in flight finish (a write waiting for its controller gets
        # its answer, or 0x0B when the link closes under it); then close the links.  A driver
        # runs until cancelled: cancel it first, so that closing its port cannot send it into a
        # reconnect backoff that SIGTERM would have to wait out.
        await asyncio.gather(*(server.close() for server in self.servers))
        if self.sparkplug is not None:
            await self.sparkplug.close()  # NDEATH before the links close (their DDEATHs would be noise)
        for task in self._links:
            task.cancel()
        for runner in self.runners:
            await runner.close()
        if self.metrics is not None:
            await self.metrics.close()

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
        if self._task is not None:
            with contextlib.suppress(asyncio.CancelledError):
                await self._task


class _Stopped(Exception):
    pass


async def run_gateway(config: GatewayConfig) -> int:
    """``slc-gateway run``: serve until SIGINT or SIGTERM."""
    logging.getLogger().setLevel(config.logging.level)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        with contextlib.suppress(NotImplementedError):
            loop.add_signal_handler(sig, stop.set)
    gateway = Gateway(config)
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
