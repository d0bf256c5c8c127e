"""The DF1 protocol cores are sans-I/O: no module under gateway/protocols/df1/ imports I/O or clocks.

ARCHITECTURE.md rule 1: the caller passes ``now``; timers are ``next_deadline()`` /
``handle_timeout(now)``.  Checked on the source (``ast``), so an import inside a function or
under ``if TYPE_CHECKING`` counts too.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import gateway.protocols.df1 as df1_package

FORBIDDEN = {"asyncio", "socket", "serial", "serial_asyncio", "serial_asyncio_fast", "time", "selectors"}
PACKAGE = Path(df1_package.__file__).parent
MODULES = sorted(PACKAGE.rglob("*.py"))  # sub-packages (pccc/) too


def imported_roots(source: str) -> set[str]:
    roots: set[str] = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            roots.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            roots.add(node.module.split(".")[0])
    return roots


def test_the_package_has_its_cores() -> None:
    names = {path.relative_to(PACKAGE).as_posix() for path in MODULES}
    assert {"framing/decoder.py", "full_duplex/datalink.py", "full_duplex/transaction.py", "pccc/codec.py",
            "address.py", "half_duplex/master.py"} <= names


@pytest.mark.parametrize("path", MODULES, ids=lambda path: str(path.relative_to(PACKAGE)))
def test_no_io_imports(path: Path) -> None:
    forbidden = imported_roots(path.read_text()) & FORBIDDEN
    where = path.relative_to(PACKAGE)
    assert not forbidden, f"{where} imports {sorted(forbidden)}: protocol cores do no I/O (ARCHITECTURE.md rule 1)"


def test_the_check_sees_imports_in_any_form() -> None:
    source = "import time\nfrom asyncio import sleep\ndef f():\n    import socket.x\nimport os.path as p\n"
    assert imported_roots(source) == {"time", "asyncio", "socket", "os"}
