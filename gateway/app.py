"""Wire links, pollers and the Modbus server together under one ``asyncio.TaskGroup``."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import signal
from collections.abc import Sequence
from typing import Any

from gateway.config import GatewayConfig, LinkConfig, parse_listen
from gateway.drivers.slc_ascii import SlcAsciiDriver
from gateway.errors import ModbusExceptionReply
from gateway.metrics import MetricsServer
from gateway.modbus.admission import RolePolicy
from gateway.modbus.mapping import STATUS_BASE, STATUS_REGISTERS, Block, Table
from gateway.modbus.server import ModbusTcpServer, make_tls_context
from gateway.transport import SerialSettings, describe_url, set_trace_limits
from gateway.unit import SlcAsciiUnit, Unit, WritableRange

__all__ = ["Gateway", "GatewayBackend", "build_unit", "describe_map", "run_gateway"]

log = logging.getLogger("gateway")

_TABLES = {"holding": Table.HOLDING, "input": Table.INPUT, "coil": Table.COIL, "discrete": Table.DISCRETE}


def _settings(link: LinkConfig) -> SerialSettings:
    return SerialSettings(link.baudrate, link.bytesize, link.parity, link.stopbits)


def _writable(link: LinkConfig) -> list[WritableRange]:
    """The link's ``writable`` ranges, overlapping and adjacent ones merged.

    A write is checked against one range at a time, so FC16 across ``holding:40-41`` and
    ``holding:42-43`` is allowed only once they are one range ``holding:40-43``.
    """
    merged: list[list[int]] = []
    tables: list[str] = []
    for r in sorted(link.writable, key=lambda r: (r.table, r.first)):
        if merged and tables[-1] == r.table and r.first <= merged[-1][1] + 1:
            merged[-1][1] = max(merged[-1][1], r.last)
        else:
            merged.append([r.first, r.last])
            tables.append(r.table)
    return [(_TABLES[table], first, last) for table, (first, last) in zip(tables, merged, strict=True)]


def build_unit(link: LinkConfig) -> Unit:
    """The runtime of one ``[[link]]``: driver, plan, cache, poller."""
    common: dict[str, Any] = dict(
        unit_id=link.unit,
        name=link.name,
        stale_after=link.stale_after,
        read_only=link.read_only,
        writable=_writable(link),
        fast_interval=link.fast_interval,
        slow_interval=link.slow_interval,
        write_burst=link.write_burst,
        poll_burst=link.poll_burst,
        write_queue_per_client=link.write_queue_per_client,
        write_queue_per_link=link.write_queue_per_link,
    )
    if link.protocol == "df1":
        from gateway.unit_df1 import build_df1_unit

        return build_df1_unit(link, common)
    driver = SlcAsciiDriver(
        link.port,
        name=link.name,
        settings=_settings(link),
        timeout=link.timeout,
        retries=link.retries,
        trace=link.trace,
        down_after_failures=link.down_after_failures,
        down_after_seconds=link.down_after_seconds,
    )
    return SlcAsciiUnit(driver=driver, **common)


class GatewayBackend:
    """The Modbus server's backend: dispatch by unit id."""

    def __init__(self, units: Sequence[Unit]) -> None:
        self.units = {unit.unit_id: unit for unit in units}

    def has_unit(self, unit: int) -> bool:
        return unit in self.units

    def _unit(self, unit: int) -> Unit:
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
        self.units = [build_unit(link) for link in config.link]
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
            )
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
                for unit in self.units:
                    self._links.append(group.create_task(unit.driver.run(), name=f"{unit.name}-link"))
                    group.create_task(unit.poller.run(), name=f"{unit.name}-poller")
                for server in self.servers:
                    group.create_task(server.serve_forever(), name=f"{server.name}-server")
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
        for task in self._links:
            task.cancel()
        for unit in self.units:
            await unit.driver.close()
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
        unit = build_unit(link)
        plan = unit.plan
        fast = sum(1 for b in plan.blocks if b.scan.value == "fast")
        lines.append(f"unit {link.unit} ({link.name}, {link.protocol}, {describe_url(link.port)}):")
        for table in Table:
            runs = plan.ranges(table)
            if runs:
                text = ", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in runs)
                lines.append(f"  {table.value:9} {text}")
        status_last = STATUS_BASE + sum(width for _, width in STATUS_REGISTERS) - 1
        lines.append(f"  {'status':9} input {STATUS_BASE}-{status_last}")
        lines.append(f"  read plan: {len(plan.blocks)} blocks ({fast} fast, {len(plan.blocks) - fast} slow)")
        lines.extend(f"    {line}" for line in _plan_lines(plan.blocks))
    return "\n".join(lines)


def _plan_lines(blocks: Sequence[Block]) -> list[str]:
    """One line per block; SLC 100/150 byte reads are summarised as address ranges per class."""
    lines: list[str] = []
    byte_reads: dict[str, list[tuple[int, int]]] = {}
    for block in blocks:
        request = block.request
        if isinstance(request, tuple):
            byte_reads.setdefault(block.scan.value, []).append((request[0], request[1]))
        else:
            lines.append(f"{block.scan.value:4} {block.label}")
    for scan, reads in byte_reads.items():
        runs: list[list[int]] = []
        for start, count in sorted(reads):
            if runs and runs[-1][1] == start:
                runs[-1][1] = start + count
            else:
                runs.append([start, start + count])
        text = ", ".join(f"0x{a:04X}-0x{b - 1:04X}" for a, b in runs)
        lines.append(f"{scan:4} {len(reads)} reads of 1-2 bytes covering {text}")
    return lines
