"""The type check of ``make mutation`` (``type_check_command`` in pyproject.toml): mypy, without the
errors that only mutmut's copies of a method cause.

mutmut puts each mutant of a method in a method of its own (``xǁClassǁ__init____mutmut_12``) beside
the original.  mypy then reports, in every copy of an ``__init__`` but the first it reads, that an
attribute annotated there is "already defined" and that a ``Final`` one may not be declared,
redeclared or assigned outside ``__init__``.  Those errors say nothing of the mutant, yet mutmut
would count each such mutant as caught by the type check, untested.  They are dropped here
(mypy's JSON lines pass through otherwise unchanged), so those mutants run their tests like any
other.

So are errors outside every mutant (a line in no function whose name has ``__mutmut_``): the tree
is clean under ``mypy --strict`` (``make lint``), so such an error is one of mutmut's rewriting
(a class whose methods became trampolines no longer matching a ``Protocol`` it is passed as, in
the kinds' drivers), which mutmut cannot pin on a mutant and stops the run for.
"""

from __future__ import annotations

import ast
import functools
import json
import re
import subprocess
import sys
from pathlib import Path

#: errors about where an attribute is declared, never about a mutated value
COPY_ERRORS = re.compile(
    r'^(Attribute "[^"]+" already defined on line \d+'
    r'|Cannot assign to final attribute "[^"]+"'
    r"|Can only declare a final attribute in class body or __init__"
    r"|Cannot redefine an existing name as final)$"
)


@functools.cache
def _functions(path: str) -> list[tuple[int, int, str]]:
    """(first line, last line, name) of every function in ``path``."""
    tree = ast.parse(Path(path).read_text(encoding="utf-8"))
    return [(node.lineno, node.end_lineno or node.lineno, node.name) for node in ast.walk(tree)
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef)]


def in_a_mutant(path: str, line: int) -> bool:
    """Whether ``line`` of ``path`` lies in a mutant (a function named ``...__mutmut_<n>``)."""
    try:
        spans = _functions(path)
    except (OSError, SyntaxError):
        return True  # cannot tell: let mutmut judge it
    inner = [(first, name) for first, last, name in spans if first <= line <= last]
    return bool(inner) and "__mutmut_" in max(inner)[1]


def main() -> int:
    checker, *args = sys.argv[1:]  # "mypy": mutmut reads the report as mypy's when the command names it
    if checker != "mypy":
        raise SystemExit(f"usage: {sys.argv[0]} mypy [mypy arguments]")
    done = subprocess.run([sys.executable, "-m", "mypy", *args], capture_output=True, text=True, check=False)
    for line in done.stdout.splitlines():
        if not line.strip():
            continue
        error = json.loads(line)
        if COPY_ERRORS.match(error.get("message", "")):
            continue
        if "file" in error and "line" in error and not in_a_mutant(error["file"], int(error["line"])):
            continue
        print(line)
    sys.stderr.write(done.stderr)
    return done.returncode


if __name__ == "__main__":
    sys.exit(main())
