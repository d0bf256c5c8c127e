"""/metrics and /healthz of a real gateway (simulated controllers) over real sockets on 127.0.0.1."""

from __future__ import annotations

import asyncio
import contextlib
import ipaddress
import json
import logging
import math
import urllib.error
import urllib.request
from collections.abc import AsyncIterator, Callable

import pytest
from prometheus_client.parser import text_string_to_metric_families
from prometheus_client.samples import Sample
from pymodbus.client import AsyncModbusTcpClient

from gateway.app import Gateway
from gateway.config import parse_config
from gateway.http import HttpServer
from gateway.modbus.mapping import STATUS_BASE
from tests.waiting import until

HOST = "127.0.0.1"

GOOD_LINK = """
[[link]]
name = "press-1"
protocol = "slc-ascii"
port = "sim://slc150?ladder=0"
unit = 1
"""

# Every reply dropped: the controller never answers.
SILENT_LINK = """
[[link]]
name = "press-2"
protocol = "slc-ascii"
port = "sim://slc150?drop=1&instance=silent"
unit = 2
timeout = 0.05
retries = 0
stale_after = 0.5
"""


def config_text(*links: str) -> str:
    return '[modbus]\nlisten = "127.0.0.1:0"\n\n[metrics]\nlisten = "127.0.0.1:0"\n' + "".join(links)


@pytest.fixture
async def gateway() -> AsyncIterator[Gateway]:
    async with Gateway(parse_config(config_text(GOOD_LINK))) as gw:
        yield gw


class Response:
    def __init__(self, raw: bytes) -> None:
        head, _, self.body = raw.partition(b"\r\n\r\n")
        status_line, *header_lines = head.decode("latin-1").split("\r\n")
        self.version, status, self.reason = status_line.split(" ", 2)
        self.status = int(status)
        self.headers = {name.lower(): value.strip() for name, value in (h.split(":", 1) for h in header_lines)}

    def json(self) -> dict[str, object]:
        document = json.loads(self.body)
        assert isinstance(document, dict)
        return document


async def http(port: int, request: bytes) -> Response:
    """Send raw request bytes, read until the server closes, parse the response."""
    reader, writer = await asyncio.open_connection(HOST, port)
    try:
        writer.write(request)
        await writer.drain()
        async with asyncio.timeout(5):
            raw = await reader.read()  # to EOF: the server closes after one response
    finally:
        writer.close()
    response = Response(raw)
    assert response.version == "HTTP/1.1"
    assert response.headers["connection"] == "close"
    assert int(response.headers["content-length"]) == len(response.body) or request.startswith(b"HEAD")
    return response


async def get(port: int, path: str) -> Response:
    return await http(port, f"GET {path} HTTP/1.1\r\nHost: {HOST}:{port}\r\nAccept: */*\r\n\r\n".encode())


async def until_health(port: int, check: Callable[[Response], bool], within: float = 5.0) -> Response:
    async with asyncio.timeout(within):
        while True:
            response = await get(port, "/healthz")
            if check(response):
                return response
            await asyncio.sleep(0.05)


def samples(text: str) -> dict[str, list[Sample]]:
    """Samples by sample name (``..._total`` for counters)."""
    out: dict[str, list[Sample]] = {}
    for family in text_string_to_metric_families(text):
        for sample in family.samples:
            out.setdefault(sample.name, []).append(sample)
    return out


def value(found: dict[str, list[Sample]], name: str, **labels: str) -> float:
    matching = [s.value for s in found[name] if all(s.labels.get(k) == v for k, v in labels.items())]
    assert len(matching) == 1, (name, labels, found.get(name))
    return matching[0]


async def test_metrics_report_the_link_and_the_modbus_server(gateway: Gateway) -> None:
    port = gateway.metrics.port
    await until_health(port, lambda r: r.status == 200)

    client = AsyncModbusTcpClient(HOST, port=gateway.port, timeout=2, retries=0)
    await client.connect()
    try:
        status = await client.read_input_registers(STATUS_BASE, count=3, device_id=1)
        assert not status.isError() and status.registers[0] == 1
        unknown_unit = await client.read_input_registers(STATUS_BASE, count=1, device_id=9)
        assert unknown_unit.isError() and unknown_unit.exception_code == 0x0A
        unmapped = await client.read_holding_registers(5000, count=1, device_id=1)
        assert unmapped.isError() and unmapped.exception_code == 0x02
        response = await get(port, "/metrics")
    finally:
        client.close()

    assert response.status == 200
    assert response.headers["content-type"].startswith("text/plain; version=")
    found = samples(response.body.decode())
    link = {"link": "press-1", "unit": "1"}
    assert value(found, "slc_gateway_link_up", **link) == 1
    assert value(found, "slc_gateway_link_connected", **link) == 1
    assert 0 <= value(found, "slc_gateway_data_age_seconds", **link) < 5
    assert value(found, "slc_gateway_stale_after_seconds", **link) == 5
    assert value(found, "slc_gateway_transactions_total", **link) > 0
    assert value(found, "slc_gateway_errors_total", **link) == 0
    assert value(found, "slc_gateway_bytes_total", direction="tx", **link) > 0
    assert value(found, "slc_gateway_bytes_total", direction="rx", **link) > 0
    for kind in ("retransmit", "id_resync"):  # an SLC 100/150 link's kinds of retry
        assert value(found, "slc_gateway_retries_total", kind=kind, **link) == 0
    assert not [s for s in found if s[0] == "slc_gateway_retries_total" and s[1].get("kind") in ("enq", "nak")]
    for name in ("timeouts", "crc_errors", "refusals", "faults", "reconnects", "write_requests", "write_failures",
                 "partial_writes", "write_busy"):
        assert value(found, f"slc_gateway_{name}_total", **link) == 0

    server = {"server": "modbus"}
    assert value(found, "slc_gateway_modbus_requests_total", function_code="4", **server) == 2
    assert value(found, "slc_gateway_modbus_requests_total", function_code="3", **server) == 1
    assert value(found, "slc_gateway_modbus_exceptions_total", exception_code="10", **server) == 1
    assert value(found, "slc_gateway_modbus_exceptions_total", exception_code="2", **server) == 1
    assert value(found, "slc_gateway_modbus_backend_errors_total", **server) == 0
    assert value(found, "slc_gateway_modbus_connections", **server) == 1  # the client above, still open
    assert value(found, "slc_gateway_modbus_connections_accepted_total", **server) == 1
    assert value(found, "slc_gateway_modbus_connections_refused_total", **server) == 0
    assert value(found, "slc_gateway_modbus_connections_evicted_total", **server) == 0
    assert value(found, "slc_gateway_modbus_tls_handshakes", **server) == 0
    assert value(found, "slc_gateway_modbus_connections_dropped_total", **server) == 0

    # Read at scrape time: the counters move between two scrapes, the client is gone.
    await until(lambda: gateway.servers[0].connection_count == 0)
    again = samples((await get(port, "/metrics")).body.decode())
    transactions = "slc_gateway_transactions_total"
    assert value(again, transactions, **link) > value(found, transactions, **link)
    assert value(again, "slc_gateway_modbus_connections", **server) == 0


async def test_metrics_with_a_standard_http_client(gateway: Gateway) -> None:
    url = f"http://{HOST}:{gateway.metrics.port}/metrics?name[]=ignored"

    def fetch() -> tuple[int, str, str]:
        with urllib.request.urlopen(url, timeout=5) as reply:
            return reply.status, reply.headers["Content-Type"], reply.read().decode()

    status, content_type, text = await asyncio.to_thread(fetch)
    assert status == 200
    assert content_type.startswith("text/plain")
    assert "# TYPE slc_gateway_transactions_total counter" in text
    assert "# TYPE slc_gateway_link_up gauge" in text


async def test_healthz_ok_when_every_link_is_up_and_fresh(gateway: Gateway) -> None:
    response = await until_health(gateway.metrics.port, lambda r: r.status == 200)
    assert response.headers["content-type"] == "application/json"
    document = response.json()
    assert document["status"] == "ok"
    links = document["links"]
    assert isinstance(links, dict) and list(links) == ["press-1"]
    press = links["press-1"]
    assert press["unit"] == 1 and press["up"] is True and press["fresh"] is True
    assert isinstance(press["age_seconds"], float) and 0 <= press["age_seconds"] < 5
    assert press["last_error"] == ""


async def test_healthz_503_names_the_link_that_never_answers() -> None:
    async with Gateway(parse_config(config_text(GOOD_LINK, SILENT_LINK))) as gw:
        port = gw.metrics.port

        def settled(r: Response) -> bool:
            links = r.json()["links"]
            assert isinstance(links, dict)
            return bool(links["press-1"]["fresh"]) and links["press-2"]["up"] is False

        response = await until_health(port, settled)
        assert response.status == 503
        document = response.json()
        assert document["status"] == "degraded"
        links = document["links"]
        assert isinstance(links, dict)
        assert links["press-1"]["up"] is True
        silent = links["press-2"]
        assert silent["unit"] == 2 and silent["fresh"] is False
        assert silent["age_seconds"] is None  # never read
        assert "press-2" in silent["last_error"]

        found = samples((await get(port, "/metrics")).body.decode())
        silent_labels = {"link": "press-2", "unit": "2"}
        assert value(found, "slc_gateway_link_up", **silent_labels) == 0
        assert math.isinf(value(found, "slc_gateway_data_age_seconds", **silent_labels))
        assert value(found, "slc_gateway_timeouts_total", **silent_labels) > 0
        assert value(found, "slc_gateway_transactions_total", **silent_labels) == 0
        assert value(found, "slc_gateway_link_up", link="press-1", unit="1") == 1


@pytest.mark.parametrize(
    ("request_bytes", "status"),
    [
        (b"GET /index.html HTTP/1.1\r\nHost: x\r\n\r\n", 404),
        (b"GET /api/units HTTP/1.1\r\n\r\n", 404),
        (b"POST /api/status HTTP/1.1\r\nContent-Length: 0\r\n\r\n", 405),
        (b"GET /metrics/extra HTTP/1.1\r\n\r\n", 404),
        (b"GET /../healthz HTTP/1.1\r\n\r\n", 404),
        (b"POST /metrics HTTP/1.1\r\nContent-Length: 0\r\n\r\n", 405),
        (b"DELETE /healthz HTTP/1.1\r\n\r\n", 405),
        (b"GET /metrics HTTP/2.0\r\n\r\n", 505),
        (b"GET /metrics HTTP/1.9\r\n\r\n", 505),  # issue 14: was accepted
        (b"GET /metrics HTTP/1.2\r\n\r\n", 505),
        (b"GET /metrics\r\n\r\n", 400),
        (b"\x16\x03\x01\x02\x00\x01\x00\x01\xfc\x03\x03\r\n\r\n", 400),
        (b"GET /metrics HTTP/1.1\r\nX-Long: " + b"a" * 10000 + b"\r\n\r\n", 431),
    ],
)
async def test_other_requests_are_refused(gateway: Gateway, request_bytes: bytes, status: int) -> None:
    response = await http(gateway.metrics.port, request_bytes)
    assert response.status == status
    if status == 405:
        assert response.headers["allow"] == "GET, HEAD"


async def test_http_1_0_is_answered(gateway: Gateway) -> None:
    assert (await http(gateway.metrics.port, b"GET /healthz HTTP/1.0\r\n\r\n")).status in (200, 503)


async def closed_without_reply(port: int) -> bool:
    reader, writer = await asyncio.open_connection(HOST, port)
    try:
        with contextlib.suppress(ConnectionError):
            writer.write(b"GET /healthz HTTP/1.1\r\n\r\n")
            await writer.drain()
        async with asyncio.timeout(2):
            try:
                return await reader.read() == b""
            except ConnectionError:
                return True
    finally:
        writer.close()


async def test_allow_list_refuses_other_networks_and_logs_once_per_interval(
    gateway: Gateway, caplog: pytest.LogCaptureFixture
) -> None:
    """Issue 14: the metrics listener had no allow list."""
    caplog.set_level(logging.WARNING, logger="gateway.http")
    server = HttpServer(gateway.http_routes(), "127.0.0.1:0", allow=[ipaddress.ip_network("10.0.0.0/8")],
                        log_interval=0.5)
    await server.start()
    try:
        for _ in range(4):
            assert await closed_without_reply(server.port)
        assert server.refused == 4
        await asyncio.sleep(0.7)
    finally:
        await server.close()
    lines = [r.getMessage() for r in caplog.records if "metrics" in r.getMessage()]
    assert len(lines) == 2, lines
    assert "refused connection from 127.0.0.1" in lines[0] and "not in the allowed networks" in lines[0]
    assert "3 more in the last 0.5 s, from 127.0.0.1 (3)" in lines[1]


async def test_connection_cap_is_logged(gateway: Gateway, caplog: pytest.LogCaptureFixture) -> None:
    """Issue 14: connections over the cap were closed silently."""
    caplog.set_level(logging.WARNING, logger="gateway.http")
    server = HttpServer(gateway.http_routes(), "127.0.0.1:0", max_connections=2)
    await server.start()
    held = []
    try:
        for _ in range(2):
            _, writer = await asyncio.open_connection(HOST, server.port)
            writer.write(b"GET /metr")  # incomplete: holds its handler
            held.append(writer)
        await until(lambda: len(server._handlers) == 2)
        assert await closed_without_reply(server.port)
        assert server.refused == 1
        assert any("already 2 connections (max_connections)" in r.getMessage() for r in caplog.records)
    finally:
        for writer in held:
            writer.close()
        await server.close()


async def test_head_gives_headers_only(gateway: Gateway) -> None:
    response = await http(gateway.metrics.port, b"HEAD /metrics HTTP/1.1\r\n\r\n")
    assert response.status == 200
    assert response.body == b""
    assert int(response.headers["content-length"]) > 0


async def test_a_silent_client_times_out_and_does_not_block_others(gateway: Gateway) -> None:
    server = HttpServer(gateway.http_routes(), "127.0.0.1:0", request_timeout=0.3)
    await server.start()
    try:
        reader, writer = await asyncio.open_connection(HOST, server.port)
        writer.write(b"GET /metr")  # and nothing more
        response = await get(server.port, "/healthz")  # served meanwhile
        assert response.status in (200, 503)
        async with asyncio.timeout(2):
            raw = await reader.read()
        writer.close()
        assert Response(raw).status == 408
    finally:
        await server.close()


async def test_close_ends_open_connections_and_stops_listening(gateway: Gateway) -> None:
    server = HttpServer(gateway.http_routes(), "127.0.0.1:0")
    await server.start()
    port = server.port
    reader, writer = await asyncio.open_connection(HOST, port)
    writer.write(b"GET /metrics HTTP/1.1\r\n")  # incomplete: the handler is waiting
    await writer.drain()
    await asyncio.sleep(0.05)
    async with asyncio.timeout(2):
        await server.close()
        assert await reader.read() == b""
    writer.close()
    with pytest.raises(OSError):
        await asyncio.open_connection(HOST, port)
    with pytest.raises(RuntimeError):
        _ = server.port


async def test_metrics_show_the_lines_budget(gateway: Gateway) -> None:
    """The schedule's figures (docs/guide/freshness.md): what a client reads is demanded, the line's
    use and refresh periods once measured, and the stale limit /healthz uses."""
    port = gateway.metrics.port
    await until_health(port, lambda r: r.status == 200)
    client = AsyncModbusTcpClient(HOST, port=gateway.port, timeout=2, retries=0)
    await client.connect()
    try:
        assert not (await client.read_holding_registers(0, count=4, device_id=1)).isError()
    finally:
        client.close()
    link = {"link": "press-1", "unit": "1"}

    def measured(found: dict[str, list[Sample]]) -> bool:
        return any(s.labels.get("set") == "demanded" for s in found.get("slc_gateway_refresh_period_seconds", []))

    found = samples((await get(port, "/metrics")).body.decode())
    async with asyncio.timeout(10):
        while not measured(found):  # the demanded blocks are read twice before a period is known
            await asyncio.sleep(0.05)
            found = samples((await get(port, "/metrics")).body.decode())
    assert value(found, "slc_gateway_plan_blocks", **link) == 120  # the SLC 150 plan
    assert value(found, "slc_gateway_demanded_blocks", **link) == 4  # holding 0-3: four two-byte reads
    assert value(found, "slc_gateway_stale_limit_seconds", **link) >= 5  # stale_after plus a period
    assert value(found, "slc_gateway_refresh_period_seconds", set="demanded", **link) > 0
    assert value(found, "slc_gateway_transaction_seconds", **link) > 0
    assert value(found, "slc_gateway_age_bound_seconds", set="slow", **link) >= 10  # slow_interval at least
    for name in ("late_reads", "read_waits"):
        assert value(found, f"slc_gateway_{name}_total", **link) >= 0
