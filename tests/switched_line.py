"""A simulated SLC 5/04 behind a TCP port that a test switches off and on (a line cut, a controller gone)."""

from __future__ import annotations

import asyncio
import uuid
from dataclasses import dataclass
from typing import Any
from urllib.parse import urlencode

from gateway.kinds.df1.sim.slc500 import Slc500Simulator
from gateway.sim import get_simulator
from gateway.sim.serve import close_tcp, serve_tcp
from tests.net import HOST

__all__ = ["Line"]


@dataclass
class Line:
    """A simulated SLC 5/04 behind a TCP port that can be switched off and on."""

    sim: Slc500Simulator
    port: int = 0
    server: asyncio.Server | None = None

    @classmethod
    async def start(cls, **options: Any) -> Line:
        url = "sim://slc504?" + urlencode({"ladder": "0", **options, "instance": uuid.uuid4().hex})
        sim = get_simulator(url)
        assert isinstance(sim, Slc500Simulator)
        line = cls(sim)
        await line.on()
        return line

    async def on(self) -> None:
        self.server = await serve_tcp(self.sim, HOST, self.port)
        self.port = self.server.sockets[0].getsockname()[1]

    async def off(self) -> None:
        if self.server is not None:
            await close_tcp(self.server)
            self.server = None

    @property
    def url(self) -> str:
        return f"socket://{HOST}:{self.port}"
