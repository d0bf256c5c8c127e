"""The type check of ``make mutation`` (``type_check_command`` in pyproject.toml): mypy, without the
errors that only mutmut's copies of a method cause.

mutmut puts each mutant of a method in a method of its own (``xǁClassǁ__init____mutmut_12``) beside
the original.  mypy then reports, in every copy of an ``__init__`` but the first it reads, that an
attribute annotated there is "already defined" and that a ``Final`` one may not be declared,
redeclared or assigned outside ``__init__``.  Those errors say nothing of the mutant, yet mutmut
would count each such mutant as caught by the type check, untested.  They are dropped here
(mypy's JSON lines pass through otherwise unchanged), so those mutants run their tests like any
other.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys

#: errors about where an attribute is declared, never about a mutated value
COPY_ERRORS = re.compile(
    r'^(Attribute "[^"]+" already defined on line \d+'
    r'|Cannot assign to final attribute "[^"]+"'
    r"|Can only declare a final attribute in class body or __init__"
    r"|Cannot redefine an existing name as final)$"
)


def main() -> int:
    checker, *args = sys.argv[1:]  # "mypy": mutmut reads the report as mypy's when the command names it
    if checker != "mypy":
        raise SystemExit(f"usage: {sys.argv[0]} mypy [mypy arguments]")
    done = subprocess.run([sys.executable, "-m", "mypy", *args], capture_output=True, text=True, check=False)
    for line in done.stdout.splitlines():
        if line.strip() and not COPY_ERRORS.match(json.loads(line).get("message", "")):
            print(line)
    sys.stderr.write(done.stderr)
    return done.returncode


if __name__ == "__main__":
    sys.exit(main())
