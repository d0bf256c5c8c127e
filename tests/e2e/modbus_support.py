"""Helpers shared by the end-to-end gateway tests: a pymodbus client, exception codes, mbpoll."""

from __future__ import annotations

import contextlib
import os
import shutil
from collections.abc import AsyncIterator
from typing import Any

import pytest
from pymodbus.client import AsyncModbusTcpClient

HOST = "127.0.0.1"


@contextlib.asynccontextmanager
async def connect(port: int, reply_timeout: float = 3) -> AsyncIterator[AsyncModbusTcpClient]:
    client = AsyncModbusTcpClient(HOST, port=port, timeout=reply_timeout, retries=0)
    assert await client.connect(), f"cannot connect to the gateway on port {port}"
    try:
        yield client
    finally:
        client.close()


def exception_code(reply: Any) -> int | None:
    return reply.exception_code if reply.isError() else None


def mbpoll_path() -> str:
    """Debian's mbpoll; skip without it, unless SLC_GATEWAY_REQUIRE_MBPOLL=1 (CI) makes that a failure."""
    path = shutil.which("mbpoll")
    if path is None:
        if os.environ.get("SLC_GATEWAY_REQUIRE_MBPOLL") == "1":
            pytest.fail("mbpoll is not installed and SLC_GATEWAY_REQUIRE_MBPOLL=1 (apt-get install mbpoll)")
        pytest.skip("mbpoll is not installed (Debian package mbpoll); set SLC_GATEWAY_REQUIRE_MBPOLL=1 to fail instead")
    return path
