"""Simulated SLC 5/04 lines and a gateway config with [opcua], for the OPC UA tests (asyncua's and node-opcua's)."""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

from gateway.opcua.passwords import hash_password
from tests.switched_line import Line

HOST = "127.0.0.1"
#: the users of every test config: (name, password, role)
USERS = (("operator", "op-secret", "write"), ("viewer", "view-secret", "read"))
#: the maps of every link: (table, start, address, count, type)
MAPS = (
    ("holding", 0, "N7:0", 8, "int16"),
    ("holding", 100, "F8:0", 2, "float32"),
    ("coil", 0, "B3:0/0", 4, "bool"),
    ("input", 0, "N7:50", 2, "int16"),
)


def link_text(name: str, unit: int, line: Line, **keys: Any) -> str:
    settings = {"timeout": 0.05, "stale_after": 1.0, "down_after_failures": 3, "down_after_seconds": 1.0,
                "write_timeout": 3.0, **keys}
    text = f'[[link]]\nname = "{name}"\nprotocol = "df1"\nport = "{line.url}"\nunit = {unit}\n'
    text += "".join(f"{k} = {_toml(v)}\n" for k, v in settings.items())
    for table, start, address, count, kind in MAPS:
        text += (f'[[link.map]]\ntable = "{table}"\nstart = {start}\naddress = "{address}"\ncount = {count}\n'
                 f'type = "{kind}"\n')
    return text


def _toml(value: Any) -> str:
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    return str(value)


def opcua_text(port: int, directory: Path, **keys: Any) -> str:
    """``[modbus]`` on a free port and ``[opcua]`` on ``port`` with the test users, files under ``directory``."""
    options = {"listen": f"opc.tcp://{HOST}:{port}", "security": ["None", "Basic256Sha256-SignAndEncrypt"],
               "certificate": str(directory / "server" / "cert.der"),
               "private_key": str(directory / "server" / "key.pem"),
               "trusted_clients": str(directory / "trusted"), "publish_interval": 0.05, **keys}
    text = '[modbus]\nlisten = "127.0.0.1:0"\n\n[opcua]\n' + "".join(f"{k} = {_toml(v)}\n" for k, v in options.items())
    for name, password, role in USERS:
        text += f'[[opcua.user]]\nname = "{name}"\nrole = "{role}"\npassword_hash = "{hash_password(password)}"\n'
    return text + "\n"


async def eventually(check: Callable[[], Awaitable[bool]], seconds: float = 10.0, step: float = 0.05) -> None:
    """Wait until ``check()`` is true (AssertionError after ``seconds``)."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + seconds
    while not await check():
        if loop.time() > deadline:
            raise AssertionError(f"not true within {seconds} s")
        await asyncio.sleep(step)
