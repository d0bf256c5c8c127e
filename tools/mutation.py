"""Mutation testing of the protocol cores and the safety-critical generic modules (``make mutation``).

Runs mutmut (``[tool.mutmut]`` in pyproject.toml: the modules, the fast unit tests) and prints,
per module, how many mutants the tests killed, and every surviving mutant, marked when
``docs/develop/mutation.md`` lists it as equivalent::

    .venv/bin/python tools/mutation.py                    # all modules, from scratch
    .venv/bin/python tools/mutation.py gateway/writes.py  # one module (or several; a glob works)
    .venv/bin/python tools/mutation.py --report           # the table of the last run, no run
    .venv/bin/python tools/mutation.py --keep ...         # keep mutmut's results of unchanged code
    .venv/bin/python tools/mutation.py --changed          # only the modules changed since their last run

The score of a module is the share of its mutants killed (a timeout counts as killed) among
those tested; ``no tests`` (no selected test runs the function) counts as surviving.  The
second score leaves out the mutants ``docs/develop/mutation.md`` lists as equivalent.  Exit status 1
when a module's first score is below ``--min`` (95 %: the listed equivalent mutants count as
surviving), when it has mutants not run, or a surviving mutant the document does not list.
Listed mutants that did not survive (killed since, or renumbered by a change to their function)
are printed, to be taken off the list.

mutmut runs every mutant in a process forked after the modules were imported, so a function that
runs only at import (a table built once: ``_crc_table``, ``_build_user_bits``) is never run
mutated there, and its mutants would survive whatever the tests check; the same holds for the
functions a test module calls while it is collected (``parametrize`` lists of commands built by the
builders under test).  This script finds the functions called while the modules are imported and
the tests collected, and gives each surviving mutant of one a fresh
interpreter (``MUTANT_UNDER_TEST`` set before the import) with the tests of its module; killed
there counts as killed (the ``import`` column).

mutmut works on a copy of the tree in ``mutants/`` (git-ignored).  Without ``--keep`` that copy
is removed first: mutmut keeps a mutant's result until the code of its function changes, so a
test added since would not be given the chance to kill an old survivor.

The whole run no longer fits in an hour on 2 cores since the kinds' drivers and units joined (their
tests wait on simulated lines).  ``--changed`` runs only the modules whose source differs from the
one their last results were made with (``mutants/sources.json``, a SHA-256 per module, written
after each run), or that have no results; all of them when ``[tool.mutmut]`` changed (other tests,
other modules).  The other modules' results are kept as they are, and the table covers them all.
"""

from __future__ import annotations

import argparse
import fnmatch
import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
import time
import tomllib
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
MUTANTS = ROOT / "mutants"
EQUIVALENTS_DOC = ROOT / "docs" / "develop" / "mutation.md"
FRESH = MUTANTS / "fresh-interpreter.json"  # import-time mutants rechecked: name -> killed
SOURCES = MUTANTS / "sources.json"  # module -> SHA-256 of the source its results were made with
#: the key of SOURCES for the [tool.mutmut] table the results were made with
CONFIG_KEY = "[tool.mutmut]"
#: tells the tests they run under mutation (the reference-comparison properties take fewer examples)
MUTATION_ENV = {"SLC_GATEWAY_MUTATION": "1"}

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
    other: list[str] = field(default_factory=list)  # suspicious, segfault, interrupted
    skipped: int = 0
    not_run: int = 0  # no result yet (the run was stopped, or the module not selected)
    import_killed: int = 0  # survived mutmut, killed in a fresh interpreter (import-time code)

    @property
    def tested(self) -> int:
        return (self.killed + self.timeout + self.import_killed + len(self.survived) + len(self.no_tests)
                + len(self.other))

    @property
    def mutants(self) -> int:
        return self.tested + self.skipped + self.not_run

    @property
    def alive(self) -> list[str]:
        """The mutants the tests ran and did not kill."""
        return self.survived + self.no_tests + self.other

    def score(self, equivalent: frozenset[str] | set[str] = frozenset()) -> float | None:
        listed = sum(m in equivalent for m in self.alive)
        total = self.tested - listed
        return None if total == 0 else 100.0 * (self.killed + self.timeout + self.import_killed) / total


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
    """The mutant names ``docs/develop/mutation.md`` lists (in backquotes) as equivalent."""
    if not EQUIVALENTS_DOC.exists():
        return set()
    return set(re.findall(r"`(gateway\.[\w.ǁ]+__mutmut_\d+)`", EQUIVALENTS_DOC.read_text(encoding="utf-8")))


def load(module: str) -> Module:
    result = Module(module)
    meta = MUTANTS / (module + ".meta")
    if not meta.exists():
        return result
    codes: dict[str, int | None] = json.loads(meta.read_text(encoding="utf-8"))["exit_code_by_key"]
    fresh: dict[str, bool] = json.loads(FRESH.read_text(encoding="utf-8")) if FRESH.exists() else {}
    for name, code in sorted(codes.items(), key=lambda item: _natural(item[0])):
        if code in SURVIVED and fresh.get(name):
            result.import_killed += 1
        elif code in KILLED or code in TYPE_CHECKED:
            result.killed += 1
        elif code in TIMEOUT:
            result.timeout += 1
        elif code in SURVIVED:
            result.survived.append(name)
        elif code in NO_TESTS:
            result.no_tests.append(name)
        elif code in SKIPPED:
            result.skipped += 1
        elif code is None:
            result.not_run += 1
        else:
            result.other.append(name)
    return result


def _natural(name: str) -> tuple[str, int]:
    stem, _, number = name.rpartition("__mutmut_")
    return stem, int(number) if number.isdigit() else 0


def prune_stale_copies() -> None:
    """Remove from ``mutants/`` the copies (and results) of files the tree no longer has.

    mutmut copies the tree into ``mutants/`` but never deletes there: a module moved or removed
    since the last run stays importable in the copy, and a test that walks the packages (the
    transition-table walker) imports it and fails against the moved code, which stops mutmut's
    test-map collection."""
    for top in ("gateway", "tests"):
        for copy in sorted((MUTANTS / top).rglob("*")) if (MUTANTS / top).is_dir() else []:
            relative = copy.relative_to(MUTANTS)
            source = ROOT / str(relative).removesuffix(".meta").removesuffix(".spans")
            if copy.is_file() and copy.suffix in {".py", ".meta", ".spans"} and not source.exists():
                copy.unlink()


def run_mutmut(selected: list[str], children: int) -> None:
    names = [] if selected == configured_modules() else [dotted(m) + ".*" for m in selected]
    command = [str(Path(sys.executable).parent / "mutmut"), "run", "--max-children", str(children), *names]
    print("$", " ".join(command), flush=True)
    # type_check_command runs "mypy": the one of this interpreter's environment
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}",
               **MUTATION_ENV)
    subprocess.run(command, cwd=ROOT, check=False, env=env)


def _in_mutants(code: str, env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-c", code], cwd=MUTANTS, env=env, capture_output=True, text=True,
                          check=False)


def import_time_functions(modules: list[str]) -> set[str]:
    """The mutated functions that run while the modules are imported or the tests collected
    (a ``parametrize`` list built by the functions under test): mutmut's stats mode records them."""
    config = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["mutmut"]
    collect = ["--collect-only", "-qq", "-p", "no:cacheprovider", *config["pytest_add_cli_args_test_selection"]]
    code = ("import importlib, io, contextlib, pytest\nfrom mutmut.state import state\n"
            f"for m in {[dotted(m) for m in modules]!r}: importlib.import_module(m)\n"
            f"with contextlib.redirect_stdout(io.StringIO()): pytest.main({collect!r})\n"
            "print('\\n'.join(sorted(state()._stats)))")
    done = _in_mutants(code, dict(os.environ, MUTANT_UNDER_TEST="stats"))
    if done.returncode:
        raise SystemExit(f"importing the mutated modules failed:\n{done.stderr}")
    return set(done.stdout.split())


#: run in ``mutants/``: reads jobs (a mutant's name and its stages of tests) from stdin, one JSON
#: list, and prints ``name killed`` or ``name survived`` for each.  pytest, hypothesis and the other
#: libraries are imported once, the mutated tree never: each job is a fork that sets
#: ``MUTANT_UNDER_TEST`` and then imports the tree afresh, as a new interpreter would, without paying
#: for the interpreter and the libraries every time.  A stage's tests run (in a fork of their own)
#: only if the stage before passed: the module's own test files first, then the others that run its
#: functions.
FORKING_RECHECK = """
import collections, json, os, sys
import hypothesis, pydantic, pytest  # noqa: F401  (the libraries, imported once)
assert not any(m == "gateway" or m.startswith("gateway.") for m in sys.modules), "tree imported early"
jobs, children, args = json.load(sys.stdin)
queue = collections.deque((name, stages) for name, stages in jobs)
sys.path.insert(0, os.getcwd())
running = {}
def reap():
    pid, status = os.wait()
    name, later = running.pop(pid)
    if os.waitstatus_to_exitcode(status) != 0:
        print(name, "killed", flush=True)
    elif later:
        queue.appendleft((name, later))
    else:
        print(name, "survived", flush=True)
while queue or running:
    if not queue or len(running) >= children:
        reap()
        continue
    name, stages = queue.popleft()
    pid = os.fork()
    if pid == 0:
        os.environ["MUTANT_UNDER_TEST"] = name
        fd = os.open(os.devnull, os.O_WRONLY)
        os.dup2(fd, 1); os.dup2(fd, 2)
        os._exit(int(pytest.main([*args, *stages[0]])))
    running[pid] = (name, stages[1:])
"""


def recheck_import_time_mutants(modules: list[str], children: int) -> None:
    """Run each survivor of an import-time function in a fresh import of the tree, with the tests of
    its module."""
    functions = import_time_functions(modules)
    stats = json.loads((MUTANTS / "mutmut-stats.json").read_text(encoding="utf-8"))
    tests_of: dict[str, list[str]] = stats["tests_by_mangled_function_name"]
    fresh: dict[str, bool] = json.loads(FRESH.read_text(encoding="utf-8")) if FRESH.exists() else {}
    jobs: list[tuple[str, list[list[str]]]] = []
    for module in modules:
        row = load(module)
        prefix = dotted(module) + "."
        counts = Counter(t.split("::")[0] for f, ts in tests_of.items() if f.startswith(prefix) for t in set(ts))
        files = sorted(counts)
        if not files:
            continue
        stem = Path(module).stem.strip("_")
        # the module's own test files: named after it, else the one that runs its functions most
        own = [f for f in files if stem in Path(f).stem] or [max(files, key=counts.__getitem__)]
        stages = [own] + ([[f for f in files if f not in own]] if own != files else [])
        for name in row.survived:
            if name.rpartition("__mutmut_")[0] in functions:
                jobs.append((name, stages))
    if not jobs:
        return
    print(f"{len(jobs)} surviving mutants of import-time functions: rechecking each in a fresh import of the tree",
          flush=True)
    pytest_args = ["-x", "-q", "-p", "no:cacheprovider", "--hypothesis-profile=mutation"]
    env = dict(os.environ, **MUTATION_ENV)
    env.pop("MUTANT_UNDER_TEST", None)
    done = subprocess.run([sys.executable, "-c", FORKING_RECHECK], cwd=MUTANTS, env=env, text=True,
                          input=json.dumps([jobs, children, pytest_args]), capture_output=True, check=False)
    if done.returncode:
        raise SystemExit(f"the fresh-import recheck failed:\n{done.stderr}")
    for line in done.stdout.split("\n"):
        name, _, verdict = line.partition(" ")
        if verdict in ("killed", "survived"):
            fresh[name] = verdict == "killed"
    FRESH.write_text(json.dumps(fresh, indent=1), encoding="utf-8")


def report(modules: list[str], minimum: float) -> bool:
    equivalent = equivalent_mutants()
    rows = [load(m) for m in modules]
    width = max(len(m) for m in modules)
    print()
    print(f"{'module':<{width}}  mutants  killed  timeout  import  survived  no tests  not run  score  w/o equiv.")
    ok = True
    for row in rows:
        if not row.mutants:
            continue  # nothing to mutate (an __init__, a module of constants)
        raw, net = row.score(), row.score(equivalent)
        unlisted = [n for n in row.alive if n not in equivalent]
        if (raw is not None and raw < minimum) or row.not_run or unlisted:
            ok = False
        print(f"{row.path:<{width}}  {row.mutants:7d}  {row.killed:6d}  {row.timeout:7d}  {row.import_killed:6d}  "
              f"{len(row.survived):8d}  "
              f"{len(row.no_tests):8d}  {row.not_run:7d}  {_pct(raw)}  {_pct(net)}")
    print()
    for row in rows:
        for kind, names in (("survived", row.survived), ("no tests", row.no_tests), ("not killed", row.other)):
            for name in names:
                mark = "  (equivalent: docs/develop/mutation.md)" if name in equivalent else ""
                print(f"{kind}: {name}{mark}")
    seen = {n for row in rows for n in row.alive}
    prefixes = tuple(dotted(row.path) + "." for row in rows if not row.not_run)
    stale = sorted(n for n in equivalent if n.startswith(prefixes) and n not in seen)
    for name in stale:
        print(f"listed as equivalent, but not a survivor of this run (killed, or renamed by a change): {name}")
    print()
    print("Show one: .venv/bin/mutmut show <name>.  Rerun: .venv/bin/python tools/mutation.py [module ...]")
    return ok


def source_hashes(modules: list[str]) -> dict[str, str]:
    """SHA-256 of each module's source, and of the ``[tool.mutmut]`` table (``CONFIG_KEY``)."""
    config = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["mutmut"]
    hashes = {m: hashlib.sha256((ROOT / m).read_bytes()).hexdigest() for m in modules}
    hashes[CONFIG_KEY] = hashlib.sha256(json.dumps(config, sort_keys=True).encode()).hexdigest()
    return hashes


def changed_modules(modules: list[str]) -> list[str]:
    """The modules whose source is not the one of their last results, or without results (all of
    them when ``[tool.mutmut]`` changed since)."""
    last: dict[str, str] = json.loads(SOURCES.read_text(encoding="utf-8")) if SOURCES.exists() else {}
    now = source_hashes(modules)
    if last.get(CONFIG_KEY) != now[CONFIG_KEY]:
        return modules
    return [m for m in modules if last.get(m) != now[m] or not (MUTANTS / (m + ".meta")).exists()]


def record_sources(now: dict[str, str]) -> None:
    """After a run: the results of the modules in ``now`` (:func:`source_hashes` taken before the run)
    are of those sources."""
    last: dict[str, str] = json.loads(SOURCES.read_text(encoding="utf-8")) if SOURCES.exists() else {}
    if last.get(CONFIG_KEY) != now[CONFIG_KEY]:
        last = {}  # the other modules' results were made with other tests or settings
    SOURCES.write_text(json.dumps(last | now, indent=1, sort_keys=True), encoding="utf-8")


def _pct(value: float | None) -> str:
    return "    -" if value is None else f"{value:5.1f}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("modules", nargs="*", help="module paths or globs (default: all in [tool.mutmut])")
    parser.add_argument("--report", action="store_true", help="print the last run's results, run nothing")
    parser.add_argument("--keep", action="store_true", help="keep mutmut's results of unchanged functions")
    parser.add_argument("--changed", action="store_true",
                        help="run only the modules changed since their last run (module doc); report all")
    parser.add_argument("--children", type=int, default=os.cpu_count() or 2, help="parallel mutants (CPU count)")
    parser.add_argument("--min", type=float, default=95.0, help="lowest acceptable score per module (95)")
    args = parser.parse_args()
    every = configured_modules()
    selected = [m for m in every if not args.modules or any(fnmatch.fnmatch(m, p) for p in args.modules)]
    if not selected:
        parser.error(f"no configured module matches {args.modules}")
    to_run = changed_modules(selected) if args.changed else selected
    if args.changed:
        print(f"changed since their last run: {len(to_run)} of {len(selected)} modules", flush=True)
        for module in to_run:
            print(f"  {module}", flush=True)
    whole = not args.modules and not args.changed
    if not args.report and to_run:
        if not args.keep and whole and MUTANTS.exists():
            shutil.rmtree(MUTANTS)
        elif not args.keep:
            for module in to_run:  # forget these modules' results, keep the others'
                (MUTANTS / (module + ".meta")).unlink(missing_ok=True)
                (MUTANTS / module).unlink(missing_ok=True)
        prune_stale_copies()
        start = time.monotonic()
        sources = source_hashes(to_run)  # before the run: an edit made while it runs is not in its results
        run_mutmut(to_run, args.children)
        if whole:
            FRESH.unlink(missing_ok=True)
        recheck_import_time_mutants(to_run, args.children)
        record_sources(sources)
        print(f"mutmut ran {(time.monotonic() - start) / 60:.1f} min")
    return 0 if report(selected, args.min) else 1


if __name__ == "__main__":
    sys.exit(main())
