"""No import circles in gateway/, and the package's structure rules.

The graph is built from the source with :mod:`ast`, not by importing: every ``import`` and
``from ... import`` anywhere in a module counts, at module level, inside functions and under
``if TYPE_CHECKING:``, because a late import only hides a circle from the interpreter, not from
the reader.  ``from package import name`` counts as an edge to ``package.name`` when that is a
module, else to ``package``.  A package's ``__init__`` is the package's module, and importing
``a.b.c`` runs the ``__init__`` of ``a`` and ``a.b`` first: an import counts as an edge to every
package above its target too, except the importer's own packages (those are already running when
it is imported).  So a module that imports a sibling package's submodule whose package
``__init__`` leads back to it is a circle, though no ``import`` line names the package.
"""

from __future__ import annotations

import ast
import re
from collections.abc import Iterable
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def module_names(root: Path, package: str) -> dict[str, Path]:
    """Dotted module name -> file, for every ``.py`` under ``root / package``."""
    modules: dict[str, Path] = {}
    for path in sorted((root / package).rglob("*.py")):
        parts = list(path.relative_to(root).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        modules[".".join(parts)] = path
    return modules


def _resolve(module: str, level: int, current: str, is_package: bool) -> str:
    if level == 0:
        return module
    base = current.split(".")
    if not is_package:
        base.pop()
    if level > 1:
        base = base[: len(base) - (level - 1)]
    return ".".join([*base, module] if module else base)


def _owner(name: str, modules: Iterable[str]) -> str | None:
    """The longest known module that ``name`` is or lies in."""
    known = set(modules)
    while name:
        if name in known:
            return name
        name = name.rpartition(".")[0]
    return None


def import_graph(root: Path, package: str) -> dict[str, set[str]]:
    """Module -> the modules of ``package`` it imports (anywhere in its source)."""
    modules = module_names(root, package)
    graph: dict[str, set[str]] = {name: set() for name in modules}
    for name, path in modules.items():
        is_package = path.name == "__init__.py"
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            targets: list[str] = []
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = _resolve(node.module or "", node.level, name, is_package)
                for alias in node.names:
                    submodule = f"{base}.{alias.name}"
                    targets.append(submodule if submodule in modules else base)
            for target in targets:
                owner = _owner(target, modules)
                if owner is not None and owner != name:
                    graph[name].add(owner)
                    graph[name].update(_parent_packages(owner, name, modules))
    return graph


def _parent_packages(target: str, importer: str, modules: Iterable[str]) -> set[str]:
    """The packages whose ``__init__`` importing ``target`` runs, less those of ``importer``."""
    known = set(modules)
    parts = target.split(".")
    above = {".".join(parts[:end]) for end in range(1, len(parts))}
    return {package for package in above & known if importer != package and not importer.startswith(package + ".")}


def find_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for successor in sorted(graph.get(node, ())):
            if successor not in index:
                visit(successor)
                low[node] = min(low[node], low[successor])
            elif successor in on_stack:
                low[node] = min(low[node], index[successor])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                components.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return sorted(components)


def _write(root: Path, files: dict[str, str]) -> None:
    for relative, text in files.items():
        path = root / relative
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding="utf-8")


def test_gateway_has_no_import_cycles() -> None:
    graph = import_graph(ROOT, "gateway")
    assert len(graph) > 40, "the walk found too few modules; is ROOT right?"
    assert "gateway.protocols.df1.pccc.codec" in graph["gateway.protocols.df1.pccc"]
    cycles = find_cycles(graph)
    assert cycles == [], "import circles (move the shared item to a module both can import):\n" + "\n".join(
        " <-> ".join(cycle) for cycle in cycles
    )


@pytest.mark.parametrize(
    ("files", "expected"),
    [
        pytest.param(
            {"pkg/__init__.py": "", "pkg/a.py": "from pkg import b\n", "pkg/b.py": "import pkg.a\n"},
            [["pkg.a", "pkg.b"]],
            id="module-level",
        ),
        pytest.param(
            {
                "pkg/__init__.py": "",
                "pkg/a.py": "from pkg.b import thing\n",
                "pkg/b.py": "thing = 1\ndef late() -> None:\n    from pkg.c import other\n",
                "pkg/c.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from . import a\nother = 2\n",
            },
            [["pkg.a", "pkg.b", "pkg.c"]],
            id="function-level-and-type-checking-relative",
        ),
        pytest.param(
            {
                "pkg/__init__.py": "from pkg.sub import x\n",
                "pkg/sub/__init__.py": "from pkg.sub.inner import x\n",
                "pkg/sub/inner.py": "from .. import y\nx = 1\n",
            },
            [["pkg", "pkg.sub", "pkg.sub.inner"]],
            id="through-package-inits",
        ),
        pytest.param(
            {
                "pkg/__init__.py": "",
                "pkg/config/__init__.py": "from pkg.config.links import models\n",
                "pkg/config/base.py": "class Base: ...\n",
                "pkg/config/links.py": "def models() -> None:\n    from pkg.kinds import registry\n",
                "pkg/kinds.py": "from pkg.config.base import Base\nregistry = [Base]\n",
            },
            [["pkg.config", "pkg.config.links", "pkg.kinds"]],
            id="through-the-parent-package-init-of-an-imported-module",
        ),
        pytest.param(
            {
                "pkg/__init__.py": "from pkg.sub import x\n",
                "pkg/sub/__init__.py": "from pkg.sub.a import x\n",
                "pkg/sub/a.py": "from pkg.sub.b import y\nx = y\n",
                "pkg/sub/b.py": "y = 1\n",
            },
            [],
            id="siblings-under-a-package-that-re-exports-them",
        ),
        pytest.param(
            {"pkg/__init__.py": "", "pkg/a.py": "from pkg import b\nimport os\n", "pkg/b.py": "import json\n"},
            [],
            id="no-cycle",
        ),
    ],
)
def test_the_check_finds_a_deliberate_cycle(tmp_path: Path, files: dict[str, str], expected: list[list[str]]) -> None:
    _write(tmp_path, files)
    assert find_cycles(import_graph(tmp_path, "pkg")) == expected


#: The modules that must not know any protocol: they find a link's kind in the registry.
GENERIC = (
    "gateway.app",
    "gateway.cache",
    "gateway.cli",
    "gateway.config",
    "gateway.config.link",
    "gateway.config.links",
    "gateway.config.schema",
    "gateway.image",
    "gateway.line_driver",
    "gateway.metrics",
    "gateway.modbus.backend",
    "gateway.modbus.handler",
    "gateway.modbus.mapping",
    "gateway.poller",
    "gateway.sim",
    "gateway.sim.models",
    "gateway.sim.serve",
    "gateway.status",
    "gateway.tags",
    "gateway.tools",
    "gateway.transport",
    "gateway.unit",
    "gateway.writes",
)
#: What names a protocol: its sans-I/O core, its driver, its kind package, its config model.
PROTOCOL_MODULES = (
    "gateway.protocols.",
    "gateway.kinds.slc_ascii.driver",
    "gateway.kinds.df1.full.driver",
    "gateway.kinds.slc_ascii",
    "gateway.kinds.df1",
    "gateway.kinds.slc_ascii.config",
    "gateway.kinds.df1.config",
)


def test_generic_modules_import_no_protocol() -> None:
    graph = import_graph(ROOT, "gateway")
    found = {
        module: sorted(target for target in graph[module] if target.startswith(PROTOCOL_MODULES))
        for module in GENERIC
    }
    assert {module: targets for module, targets in found.items() if targets} == {}


def test_nothing_climbs_to_the_app() -> None:
    """The app is the top floor: it wires the others, and only the command line imports it (the Modbus
    server's backend is on the Modbus floor, ``gateway.modbus.backend``, beside ``mbap``)."""
    graph = import_graph(ROOT, "gateway")
    assert sorted(module for module, targets in graph.items() if "gateway.app" in targets) == ["gateway.cli"]


def test_protocol_names_are_spelt_out_in_at_most_three_modules() -> None:
    """String literals ``"slc-ascii"`` and ``"df1"`` (code, not comments) live with the config models."""
    spelt: set[str] = set()
    for name, path in module_names(ROOT, "gateway").items():
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Constant) and node.value in ("slc-ascii", "df1"):
                spelt.add(name)
    assert spelt == {"gateway.kinds.slc_ascii.config", "gateway.kinds.df1.config"}


MAX_MODULE_LINES = 600


def test_no_module_is_over_600_lines() -> None:
    modules = module_names(ROOT, "gateway")
    sizes = {name: len(path.read_text(encoding="utf-8").splitlines()) for name, path in modules.items()}
    assert {name: lines for name, lines in sizes.items() if lines > MAX_MODULE_LINES} == {}


def top_level_names(root: Path, package: str) -> dict[str, list[str]]:
    """Function and class name -> the modules that define it at their top level."""
    defined: dict[str, list[str]] = {}
    for name, path in module_names(root, package).items():
        for node in ast.parse(path.read_text(encoding="utf-8")).body:
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
                defined.setdefault(node.name, []).append(name)
    return defined


def test_no_name_is_defined_in_two_modules() -> None:
    """One meaning per name: a function or class name is defined in one module of gateway/ only
    (private ones too), so that a name found in a traceback or a grep means one thing."""
    twice = {name: modules for name, modules in top_level_names(ROOT, "gateway").items() if len(modules) > 1}
    assert twice == {}


def test_the_name_check_finds_a_name_defined_twice(tmp_path: Path) -> None:
    _write(tmp_path, {"pkg/__init__.py": "", "pkg/a.py": "def verdict() -> None: ...\n",
                      "pkg/b.py": "class verdict: ...\nclass Other: ...\n"})
    names = top_level_names(tmp_path, "pkg")
    assert names["verdict"] == ["pkg.a", "pkg.b"] and names["Other"] == ["pkg.b"]


def module_constants(root: Path, package: str) -> dict[str, list[str]]:
    """UPPER_CASE name -> the modules that assign it at their top level (``X = ...``, ``X: T = ...``,
    ``X, Y = ...``).  Left out: a single capital letter (a type variable or a table's short name for
    an enum, local to its module by convention), and a name bound to another name or an attribute
    (``_MBAP: Final = mbap.MBAP``, ``_DLE = Symbol.DLE``): such an alias states nothing, it takes
    the value from its one place."""
    defined: dict[str, list[str]] = {}
    for name, path in module_names(root, package).items():
        found: set[str] = set()
        for node in ast.parse(path.read_text(encoding="utf-8")).body:
            targets: list[ast.expr] = []
            if isinstance(node, ast.Assign):
                targets = list(node.targets)
            elif isinstance(node, ast.AnnAssign) and node.value is not None:
                targets = [node.target]
            if not targets or isinstance(getattr(node, "value", None), ast.Name | ast.Attribute):
                continue
            for target in targets:
                elements = target.elts if isinstance(target, ast.Tuple) else [target]
                found |= {e.id for e in elements if isinstance(e, ast.Name) and _CONSTANT.fullmatch(e.id)}
        for constant in found:
            defined.setdefault(constant, []).append(name)
    return defined


_CONSTANT = re.compile(r"_?[A-Z][A-Z0-9_]+")

#: Names that several modules define on purpose, each meaning "this module's own" by a contract
#: the reader knows from the name's one definition of that contract:
SAME_NAME_BY_CONTRACT = {
    # every kind's package exports its LinkKind as KIND (gateway/kinds/__init__.py's docstring)
    "KIND": ["gateway.kinds.df1", "gateway.kinds.slc_ascii"],
    # every state machine's table of (state, input) -> (action, next state) is its module's
    # TRANSITIONS, which the table walker (tests/protocols/test_transitions.py) reads by that name
    "TRANSITIONS": [
        "gateway.protocols.df1.full_duplex.table",
        "gateway.protocols.df1.full_duplex.transaction",
        "gateway.protocols.df1.half_duplex.master",
        "gateway.protocols.df1.write_verdict",
        "gateway.protocols.slc_ascii.session_table",
    ],
}


def test_no_constant_is_defined_in_two_modules() -> None:
    """One place per fact: a module-level constant of gateway/ is assigned in one module, and the
    others import it (so that two values cannot drift apart); two facts get two names."""
    twice = {name: modules for name, modules in module_constants(ROOT, "gateway").items() if len(modules) > 1}
    assert {name: modules for name, modules in twice.items() if SAME_NAME_BY_CONTRACT.get(name) != modules} == {}


def test_the_constant_check_finds_a_constant_defined_twice(tmp_path: Path) -> None:
    _write(tmp_path, {
        "pkg/__init__.py": "",
        "pkg/a.py": "from typing import Final, TypeVar\nT = TypeVar('T')\nDEFAULT_RETRIES: Final = 3\n_MBAP = 7\n",
        "pkg/b.py": "T = 1\nDEFAULT_RETRIES = 3\nONE, _MBAP = 1, 2\nlower = 4\n",
        "pkg/c.py": "from pkg.a import DEFAULT_RETRIES\nfrom pkg import a\nONE = 1\n_MBAP = a._MBAP\n",
    })
    assert module_constants(tmp_path, "pkg") == {
        "DEFAULT_RETRIES": ["pkg.a", "pkg.b"], "_MBAP": ["pkg.a", "pkg.b"], "ONE": ["pkg.b", "pkg.c"]}
