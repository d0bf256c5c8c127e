"""Soak plans: quick by default (CI), long with ``--soak`` (by hand).

The ``--soak`` option itself is declared in ``tests/conftest.py`` (pytest only takes options
from conftest files it loads at start-up, and it does not load ``tests/soak/conftest.py`` then
unless ``tests/soak`` is named on the command line).

Environment overrides (both modes): ``SOAK_SEED`` (the proxies' RNG seed), ``SOAK_MINUTES``
(total fault time of the long mode), ``SOAK_REPORT`` (write the figures as JSON to this path).
"""

from __future__ import annotations

import os
import subprocess
from dataclasses import dataclass
from pathlib import Path

import pytest


@dataclass(frozen=True)
class SoakPlan:
    """``cycles`` times: ``fault_seconds`` of faults, then an outage of ``outage_seconds``."""

    name: str
    cycles: int
    fault_seconds: float
    outage_seconds: float
    calm_seconds: float
    seed: int
    report: str | None
    revision: str = ""


def _revision() -> str:
    """The commit under test, ``+dirty`` with uncommitted changes (for the report)."""
    root = Path(__file__).resolve().parents[2]
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True,
                              timeout=10, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "gateway"], cwd=root,
                               capture_output=True, text=True, timeout=10, check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return head + ("+dirty" if dirty else "")


@pytest.fixture
def soak_plan(request: pytest.FixtureRequest) -> SoakPlan:
    seed = int(os.environ.get("SOAK_SEED", "20240606"))
    report = os.environ.get("SOAK_REPORT") or None
    if request.config.getoption("--soak", default=False):
        minutes = float(os.environ.get("SOAK_MINUTES", "10"))
        cycles = max(1, round(minutes / 2.5))
        fault_seconds = minutes * 60 / cycles
        return SoakPlan("long", cycles, fault_seconds, 10.0, 5.0, seed, report, _revision())
    return SoakPlan("quick", 1, 15.0, 10.0, 3.0, seed, report, _revision())
