"""The protocol cores under gateway/protocols/ are sans-I/O: no asyncio, socket, serial, time.

Checked on the source of every module of the tree (imports at any depth, ``from`` forms too),
so a new module cannot slip one in.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PROTOCOLS = Path(__file__).resolve().parent.parent / "gateway" / "protocols"
FORBIDDEN = {"asyncio", "socket", "serial", "serial_asyncio", "serial_asyncio_fast", "time", "selectors", "threading"}
MODULES = sorted(PROTOCOLS.rglob("*.py"))


def imported(tree: ast.AST) -> set[str]:
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names |= {alias.name.split(".")[0] for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module.split(".")[0])
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "__import__":
            names |= {arg.value.split(".")[0] for arg in node.args if isinstance(arg, ast.Constant)
                      and isinstance(arg.value, str)}
    return names


def test_the_tree_has_the_cores() -> None:
    names = {p.relative_to(PROTOCOLS).as_posix() for p in MODULES}
    assert {"slc_ascii/transaction.py", "slc_ascii/framing.py", "df1/full_duplex/datalink.py"} <= names


@pytest.mark.parametrize("module", MODULES, ids=lambda p: p.relative_to(PROTOCOLS).as_posix())
def test_no_io_imports(module: Path) -> None:
    bad = imported(ast.parse(module.read_text(encoding="utf-8"))) & FORBIDDEN
    assert not bad, f"{module.relative_to(PROTOCOLS.parent.parent)} imports {sorted(bad)}: protocol cores are sans-I/O"


def test_the_check_finds_an_import() -> None:
    assert imported(ast.parse("import time\nfrom asyncio import sleep\n__import__('socket')")) == {
        "time", "asyncio", "socket"}
