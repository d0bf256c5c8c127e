"""Options shared by the whole test suite."""

from __future__ import annotations

import math
import os
import signal
import sys
from collections.abc import Iterator
from typing import Any

import pytest
from hypothesis import Phase, settings
from looptime._internal import loops as looptime_loops

# The built-in kinds register their sim:// models when the registry is imported (the app, the CLI
# and the tools import it); tests that open simulators directly need them too.
import gateway.kinds  # noqa: F401
from gateway.sim import reset_simulators

# `make mutation` runs the tests with --hypothesis-profile=mutation: the same examples for every
# mutant (derandomize, no example database) and no shrinking (a mutant is killed by the first
# failure; nobody reads the minimal example).
settings.register_profile(
    "mutation", derandomize=True, database=None, phases=[Phase.explicit, Phase.generate], print_blob=False
)


@pytest.fixture
def forget_simulators() -> Iterator[None]:
    """Forget every in-process simulator after the test (``sim://`` URLs name the same device while it
    lives).  A module uses it with ``pytestmark = pytest.mark.usefixtures("forget_simulators")``."""
    yield
    reset_simulators()


#: Modules whose tests start processes (the gateway, its tools, a broker, mbpoll, a browser) and run in
#: real time: marked ``process`` (``-m "not process"`` for a quick run; CI runs them all).
PROCESS_MODULES = frozenset({
    "test_cli.py", "test_cli_df1.py", "test_cli_df1_half.py", "test_cli_paths.py", "test_cli_reload.py",
    "test_bench_smoke.py", "test_bench_half_duplex.py", "test_df1_target_processes.py", "test_packaging.py",
    "test_sparkplug_kill.py", "test_sparkplug_host.py", "test_sparkplug_store.py",
    "test_sparkplug_store_silent.py", "test_sparkplug_store_sigkill.py", "test_status_page_browser.py",
    "test_df1py3_initiator.py",
})
#: Modules that build or run the container image or make network namespaces: marked ``container``.
CONTAINER_MODULES = frozenset({"test_container_image.py", "test_access_control_netns.py"})


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        name = item.path.name
        if name in PROCESS_MODULES:
            item.add_marker(pytest.mark.process)
        elif name in CONTAINER_MODULES:
            item.add_marker(pytest.mark.container)


def _looptime_ceil(self: Any, seconds: float | None) -> int | None:
    """looptime's seconds -> whole microseconds, rounded up instead of to the nearest.

    When every task waits, looptime moves its clock by the wait to the next timer in whole
    microseconds.  Rounded to the nearest, a timer at ``now + timeout`` (0.29000000000000004 after
    0.28 + 0.01) is reached at 0.29: asyncio calls it (due within its resolution), but a driver that
    checks ``loop.time() >= deadline`` before it acts (the SLC 100/150 transaction loop) sees the
    deadline not yet come, waits again, and the clock never moves.  Rounded up, the clock reaches
    the deadline (at most 1 us past it), as a real clock would.  looptime is pinned (``test`` extra),
    this private method with it."""
    if seconds is None:
        return None
    reciprocal: int = self._LoopTimeEventLoop__resolution_reciprocal
    return math.ceil(seconds * reciprocal)


looptime_loops.LoopTimeEventLoop._LoopTimeEventLoop__time2int = _looptime_ceil  # type: ignore[attr-defined]


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--soak",
        action="store_true",
        default=False,
        help="run the long fault soak in tests/soak (10+ minutes) instead of its quick mode",
    )


def _mutation_test_cpu_limit(nodeid: str) -> float | None:
    """The CPU seconds a test may take with a mutant in place, or None outside a mutant's run.

    mutmut bounds a mutant's whole test run at 3 x the clean time of all its tests (+ 1 s), so a
    mutant that makes the first test loop for ever holds a worker for minutes before it is called a
    timeout.  Under `make mutation` each test is bounded on its own, at the same 3 x + 1 s of its own
    clean time, which mutmut measured in this process before forking the mutant's run.  A test whose
    clean time is unknown (the fresh-interpreter recheck, a test mutmut did not time) is not bounded.
    """
    if "__mutmut_" not in os.environ.get("MUTANT_UNDER_TEST", ""):
        return None
    try:
        from mutmut.state import state
    except ImportError:
        return None
    clean = state().duration_by_test.get(nodeid)
    return None if not clean else 3.0 * clean + 1.0


def _timed_out(signum: int, frame: object) -> None:
    # mutmut reads exit code 36 as "timeout" (killed); pytest is not unwound, this mutant is done
    os._exit(36)


def _clear_gateway_caches() -> None:
    """Empty every ``functools`` cache of the gateway's modules, under `make mutation` only.

    mutmut forks each mutant's run from the process that ran the clean tests, so a cache filled
    there (the SLC 100/150 plan, the shared DF1 and PLC-5 plans) hands the mutant's tests the
    unmutated result, and a mutant of the cached function, or of anything it calls, never runs:
    it survives whatever the tests check."""
    for name, module in list(sys.modules.items()):
        if name == "gateway" or name.startswith("gateway."):
            for value in list(vars(module).values()):
                if callable(getattr(value, "cache_clear", None)) and hasattr(value, "cache_info"):
                    value.cache_clear()


def pytest_runtest_setup(item: pytest.Item) -> None:
    if "__mutmut_" in os.environ.get("MUTANT_UNDER_TEST", ""):
        _clear_gateway_caches()


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_call(item: pytest.Item) -> Iterator[None]:
    limit = _mutation_test_cpu_limit(item.nodeid)
    if limit is None:
        yield
        return
    previous = signal.signal(signal.SIGPROF, _timed_out)
    signal.setitimer(signal.ITIMER_PROF, limit)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_PROF, 0)
        signal.signal(signal.SIGPROF, previous)
