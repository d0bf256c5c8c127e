"""Smoke test of ``bench/half_duplex.py --quick``: it runs against the current code and prints its
RESULT line (no timing asserted; about 15 s)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parent.parent / "bench"


def test_half_duplex_bench_quick() -> None:
    done = subprocess.run([sys.executable, str(BENCH / "half_duplex.py"), "--quick"], capture_output=True,
                          text=True, timeout=180, cwd=BENCH.parent, check=False)
    assert done.returncode == 0, f"{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
    result = [line for line in done.stdout.splitlines() if line.startswith("RESULT ")]
    assert result and "busy_16st_19200=" in result[0] and "dead_station_age_ratio=" in result[0]
