"""The status page's JSON API on the [metrics] listener, over real sockets on 127.0.0.1 (no browser)."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from typing import Any

import pytest

from gateway.app import Gateway
from gateway.config import parse_config
from gateway.sim import create_simulator
from gateway.sim.serve import close_tcp, serve_tcp
from tests.e2e.modbus_support import connect, exception_code
from tests.test_metrics import HOST, Response, get, http

LINKS = """
[modbus]
listen = "127.0.0.1:0"

[metrics]
listen = "127.0.0.1:0"

[[link]]
name = "press-1"
protocol = "slc-ascii"
port = "sim://slc150?ladder=0"
unit = 1

[[link]]
name = "remote"
protocol = "slc-ascii"
port = "rfc2217://plant:s3cret@127.0.0.1:1"
unit = 2
"""

SERVED = """
[[link]]
name = "served"
protocol = "slc-ascii"
port = "socket://127.0.0.1:{port}"
unit = 4
stale_after = 0.5
timeout = 0.1
retries = 0
"""


@pytest.fixture
async def plant() -> AsyncIterator[tuple[Gateway, asyncio.Server]]:
    """A gateway with a simulated SLC 150, a link with credentials that never connects, and an SLC 150
    served over TCP that the test can switch off."""
    server = await serve_tcp(create_simulator("slc150", {"ladder": "0"}), HOST, 0)
    port = server.sockets[0].getsockname()[1]
    try:
        async with Gateway(parse_config(LINKS + SERVED.format(port=port))) as gateway:
            yield gateway, server
    finally:
        await close_tcp(server)


async def api(gateway: Gateway, path: str) -> Any:
    assert gateway.metrics is not None
    response = await get(gateway.metrics.port, path)
    assert response.status == 200, (path, response.status, response.body)
    assert response.headers["content-type"] == "application/json"
    return response.json()


async def until_row(gateway: Gateway, name: str, state: str, within: float = 10.0) -> dict[str, Any]:
    async with asyncio.timeout(within):
        while True:
            rows = {row["name"]: row for row in (await api(gateway, "/api/status"))["links"]}
            if rows[name]["state"] == state:
                return rows[name]
            await asyncio.sleep(0.05)


async def test_status_rows(plant: tuple[Gateway, asyncio.Server]) -> None:
    gateway, _ = plant
    row = await until_row(gateway, "press-1", "up")
    assert (row["kind"], row["controllers"], row["port"], row["unit"]) == ("slc-ascii", "SLC 100/150",
                                                                            "sim://slc150", 1)
    assert row["since"] is not None and row["data_age"] is not None and row["data_age"] < row["stale_after"]
    assert row["transactions"] > 0 and row["errors"] == 0
    remote = await until_row(gateway, "remote", "down")
    assert remote["port"] == "rfc2217://***@127.0.0.1:1"
    assert remote["data_age"] is None
    assert "s3cret" not in str(remote) and "plant:" not in str(remote)
    plan = row["schedule"]  # the line's budget (docs/guide/freshness.md)
    assert set(plan) == {"blocks", "demanded", "transaction_time", "line_use", "refresh", "age_bound", "stale_limit",
                         "late_reads", "read_waits", "behind"}
    assert plan["blocks"] == 120 and plan["stale_limit"] >= row["stale_after"]
    assert set(plan["refresh"]) == set(plan["age_bound"]) == {"fast", "slow", "demanded"}
    assert plan["behind"] is None
    document = await api(gateway, "/api/status")
    assert [row["name"] for row in document["links"]] == ["press-1", "remote", "served"]
    assert document["servers"][0]["name"] == "modbus"


async def test_register_view_is_what_modbus_reads(plant: tuple[Gateway, asyncio.Server]) -> None:
    gateway, _ = plant
    await until_row(gateway, "press-1", "up")
    async with connect(gateway.port) as client:
        for table, read, start, count in (
            ("holding", client.read_holding_registers, 30, 8),  # accumulators and presets (frozen ladder)
            ("input", client.read_input_registers, 1000, 3),  # the status block
            ("coil", client.read_coils, 700, 12),  # 700 is not mapped
        ):
            view = await api(gateway, f"/api/units/1/{table}?start={start}&count={count}")
            assert (view["unit"], view["link"], view["table"], view["start"], view["count"]) == (
                1, "press-1", table, start, count)
            values = view["values"]
            assert [entry["address"] for entry in values] == list(range(start, start + count))
            mapped = [entry for entry in values if entry["state"] != "unmapped"]
            first = mapped[0]["address"]
            reply = await read(first, count=len(mapped), device_id=1)
            assert exception_code(reply) is None
            modbus = reply.registers if table != "coil" else [int(bit) for bit in reply.bits[: len(mapped)]]
            assert [entry["value"] for entry in mapped] == modbus
            assert all(entry["state"] == "fresh" for entry in mapped)
            assert all(entry["age"] is not None and entry["age"] >= 0 for entry in mapped if table != "input")
    holding = (await api(gateway, "/api/units/1/holding?start=32&count=1"))["values"][0]
    assert (holding["tag"], holding["type"]) == ("901.PRE", "uint16")


async def test_a_silent_controller_turns_down_and_its_values_stale(plant: tuple[Gateway, asyncio.Server]) -> None:
    gateway, server = plant
    await until_row(gateway, "served", "up")
    before = await api(gateway, "/api/units/4/holding?start=32&count=4")
    assert all(entry["state"] == "fresh" for entry in before["values"])
    await close_tcp(server)  # the controller is switched off
    row = await until_row(gateway, "served", "down")
    assert row["last_error"] and row["last_error_at"] is not None
    async with asyncio.timeout(5):  # stale_after (0.5 s) after the last answer
        while True:
            after = await api(gateway, "/api/units/4/holding?start=32&count=4")
            if any(entry["state"] != "fresh" for entry in after["values"]):
                break
            await asyncio.sleep(0.05)
    async with connect(gateway.port) as client:
        for old, entry in zip(before["values"], after["values"], strict=True):
            assert entry["state"] == "stale"
            assert entry["value"] == old["value"]  # the last value read, marked stale
            reply = await client.read_holding_registers(entry["address"], count=1, device_id=4)
            assert exception_code(reply) == 0x0B  # the rule the view follows


@pytest.mark.parametrize(
    ("path", "status", "words"),
    [
        ("/api/units/9/holding", 404, "no unit 9: the units are 1, 2, 4"),
        ("/api/units/one/holding", 404, "no unit one"),
        ("/api/units/1/registers", 404, "no table 'registers'"),
        ("/api/units/1/holding?start=-1", 400, "start must be a whole number 0-65535"),
        ("/api/units/1/holding?start=abc", 400, "start must be"),
        ("/api/units/1/holding?count=0", 400, "count must be a whole number 1-125"),
        ("/api/units/1/holding?count=126", 400, "count must be"),
        ("/api/units/1/holding?start=65530&count=10", 400, "runs past address 65535"),
        ("/api/units/1/holding?start=1&&=", 400, "malformed query"),
    ],
)
async def test_bad_requests_get_a_json_reason(plant: tuple[Gateway, asyncio.Server], path: str, status: int,
                                              words: str) -> None:
    gateway, _ = plant
    assert gateway.metrics is not None
    response = await get(gateway.metrics.port, path)
    assert response.status == status
    assert words in response.json()["error"]


async def test_page_files_and_read_only(plant: tuple[Gateway, asyncio.Server]) -> None:
    gateway, _ = plant
    assert gateway.metrics is not None
    port = gateway.metrics.port
    page = await get(port, "/")
    assert page.status == 200 and page.headers["content-type"].startswith("text/html")
    assert "default-src 'none'" in page.headers["content-security-policy"]
    assert b"http" not in page.body.replace(b"http-equiv", b"")  # nothing fetched from elsewhere
    for path, kind in (("/status.js", "text/javascript"), ("/status.css", "text/css")):
        response = await get(port, path)
        assert response.status == 200 and response.headers["content-type"].startswith(kind)
        assert b"http://" not in response.body and b"https://" not in response.body
    for method in (b"POST", b"PUT", b"DELETE"):
        response: Response = await http(port, method + b" /api/units/1/holding HTTP/1.1\r\nContent-Length: 0\r\n\r\n")
        assert response.status == 405
    head = await http(port, b"HEAD /api/status HTTP/1.1\r\n\r\n")
    assert head.status == 200 and head.body == b""


async def test_the_allow_list_closes_the_page_too() -> None:
    config = parse_config(LINKS.replace('listen = "127.0.0.1:0"\n\n[[link]]',
                                        'listen = "127.0.0.1:0"\nallow = ["10.9.9.0/24"]\n\n[[link]]', 1))
    async with Gateway(config) as gateway:
        assert gateway.metrics is not None
        reader, writer = await asyncio.open_connection(HOST, gateway.metrics.port)
        async with asyncio.timeout(5):
            try:  # aborted at accept, before a byte is read: nothing is answered
                writer.write(b"GET /api/status HTTP/1.1\r\n\r\n")
                answer = await reader.read()
            except ConnectionResetError:
                answer = b""
        assert answer == b""
        writer.close()
