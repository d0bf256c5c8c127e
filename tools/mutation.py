"""Mutation testing of the protocol cores and the safety-critical generic modules (``make mutation``).

Runs mutmut (``[tool.mutmut]`` in pyproject.toml: the modules, the fast unit tests) and prints,
per module, how many mutants the tests killed, and every surviving mutant, marked when
``docs/mutation.md`` lists it as equivalent::

    .venv/bin/python tools/mutation.py                    # all modules, from scratch
    .venv/bin/python tools/mutation.py gateway/writes.py  # one module (or several; a glob works)
    .venv/bin/python tools/mutation.py --report           # the table of the last run, no run
    .venv/bin/python tools/mutation.py --keep ...         # keep mutmut's results of unchanged code

The score of a module is the share of its mutants killed (a timeout counts as killed) among
those tested; ``no tests`` (no selected test runs the function) counts as surviving.  The
second score leaves out the mutants ``docs/mutation.md`` lists as equivalent.  Exit status 1
when a module is below ``--min`` (95 %) counting the equivalent ones out.

mutmut works on a copy of the tree in ``mutants/`` (git-ignored).  Without ``--keep`` that copy
is removed first: mutmut keeps a mutant's result until the code of its function changes, so a
test added since would not be given the chance to kill an old survivor.
"""

from __future__ import annotations

import argparse
import fnmatch
import json
import os
import re
import shutil
import subprocess
import sys
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
MUTANTS = ROOT / "mutants"
EQUIVALENTS_DOC = ROOT / "docs" / "mutation.md"

# mutmut's exit codes of a mutant run (mutmut/stats.py)
KILLED = {1, 3}
TIMEOUT = {36, 24, -24, 152, 255}
SURVIVED = {0}
NO_TESTS = {5, 33}
SKIPPED = {34}
TYPE_CHECKED = {37}


@dataclass
class Module:
    path: str
    killed: int = 0
    timeout: int = 0
    survived: list[str] = field(default_factory=list)
    no_tests: list[str] = field(default_factory=list)
    other: list[str] = field(default_factory=list)  # not checked, suspicious, segfault
    skipped: int = 0

    @property
    def tested(self) -> int:
        return self.killed + self.timeout + len(self.survived) + len(self.no_tests) + len(self.other)

    def score(self, equivalent: frozenset[str] | set[str] = frozenset()) -> float | None:
        alive = [m for m in self.survived + self.no_tests + self.other if m not in equivalent]
        total = self.tested - (len(self.survived + self.no_tests + self.other) - len(alive))
        return None if total == 0 else 100.0 * (self.killed + self.timeout) / total


def configured_modules() -> list[str]:
    config = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["mutmut"]
    patterns: list[str] = config["only_mutate"]
    found = sorted(
        str(p.relative_to(ROOT))
        for source in config["source_paths"]
        for p in (ROOT / source).rglob("*.py")
        if any(fnmatch.fnmatch(str(p.relative_to(ROOT)), pattern) for pattern in patterns)
    )
    return [m for m in found if not m.endswith("__init__.py") or (ROOT / m).stat().st_size > 0]


def dotted(module: str) -> str:
    return module.removesuffix(".py").replace("/", ".")


def equivalent_mutants() -> set[str]:
    """The mutant names ``docs/mutation.md`` lists (in backquotes) as equivalent."""
    if not EQUIVALENTS_DOC.exists():
        return set()
    return set(re.findall(r"`(gateway\.[\w.ǁ]+__mutmut_\d+)`", EQUIVALENTS_DOC.read_text(encoding="utf-8")))


def load(module: str) -> Module:
    result = Module(module)
    meta = MUTANTS / (module + ".meta")
    if not meta.exists():
        return result
    codes: dict[str, int | None] = json.loads(meta.read_text(encoding="utf-8"))["exit_code_by_key"]
    for name, code in sorted(codes.items(), key=lambda item: _natural(item[0])):
        if code in KILLED or code in TYPE_CHECKED:
            result.killed += 1
        elif code in TIMEOUT:
            result.timeout += 1
        elif code in SURVIVED:
            result.survived.append(name)
        elif code in NO_TESTS:
            result.no_tests.append(name)
        elif code in SKIPPED:
            result.skipped += 1
        else:
            result.other.append(name)
    return result


def _natural(name: str) -> tuple[str, int]:
    stem, _, number = name.rpartition("__mutmut_")
    return stem, int(number) if number.isdigit() else 0


def run_mutmut(selected: list[str], children: int) -> None:
    names = [] if selected == configured_modules() else [dotted(m) + ".*" for m in selected]
    command = [str(Path(sys.executable).parent / "mutmut"), "run", "--max-children", str(children), *names]
    print("$", " ".join(command), flush=True)
    # type_check_command runs "mypy": the one of this interpreter's environment
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}")
    subprocess.run(command, cwd=ROOT, check=False, stdout=subprocess.DEVNULL, env=env)


def report(modules: list[str], minimum: float) -> bool:
    equivalent = equivalent_mutants()
    rows = [load(m) for m in modules]
    width = max(len(m) for m in modules)
    print()
    print(f"{'module':<{width}}  mutants  killed  timeout  survived  no tests  score  w/o equiv.")
    ok = True
    for row in rows:
        raw, net = row.score(), row.score(equivalent)
        if net is not None and net < minimum:
            ok = False
        print(f"{row.path:<{width}}  {row.tested:7d}  {row.killed:6d}  {row.timeout:7d}  {len(row.survived):8d}  "
              f"{len(row.no_tests):8d}  {_pct(raw)}  {_pct(net)}")
    print()
    for row in rows:
        for kind, names in (("survived", row.survived), ("no tests", row.no_tests), ("not killed", row.other)):
            for name in names:
                mark = "  (equivalent: docs/mutation.md)" if name in equivalent else ""
                print(f"{kind}: {name}{mark}")
    print()
    print("Show one: .venv/bin/mutmut show <name>.  Rerun: .venv/bin/python tools/mutation.py [module ...]")
    return ok


def _pct(value: float | None) -> str:
    return "    -" if value is None else f"{value:5.1f}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("modules", nargs="*", help="module paths or globs (default: all in [tool.mutmut])")
    parser.add_argument("--report", action="store_true", help="print the last run's results, run nothing")
    parser.add_argument("--keep", action="store_true", help="keep mutmut's results of unchanged functions")
    parser.add_argument("--children", type=int, default=os.cpu_count() or 2, help="parallel mutants (CPU count)")
    parser.add_argument("--min", type=float, default=95.0, help="lowest acceptable score per module (95)")
    args = parser.parse_args()
    every = configured_modules()
    selected = [m for m in every if not args.modules or any(fnmatch.fnmatch(m, p) for p in args.modules)]
    if not selected:
        parser.error(f"no configured module matches {args.modules}")
    if not args.report:
        if not args.keep and not args.modules and MUTANTS.exists():
            shutil.rmtree(MUTANTS)
        elif not args.keep:
            for module in selected:  # forget these modules' results, keep the others'
                (MUTANTS / (module + ".meta")).unlink(missing_ok=True)
                (MUTANTS / module).unlink(missing_ok=True)
        start = time.monotonic()
        run_mutmut(selected, args.children)
        print(f"mutmut ran {(time.monotonic() - start) / 60:.1f} min")
    return 0 if report(selected, args.min) else 1


if __name__ == "__main__":
    sys.exit(main())
