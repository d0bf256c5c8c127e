"""Smoke test of the benchmarks: each bench script runs with ``--quick`` and prints its RESULT line.

No timing is asserted (the CI machine is shared and noisy); this only proves the scripts still
run against the current code.  About 40 s in all.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parent.parent / "bench"
SCRIPTS = [
    "wire_efficiency.py",
    "plan_quality.py",
    "scale.py",
    "modbus_serving.py",
    "modbus_fast_path.py",
    "write_latency.py",
    "write_fairness.py",
    "cpu_per_transaction.py",
    "availability.py",
    "target_persist.py",
    "slc_write_verdicts.py",
    "freshness.py",
    "schedule_cost.py",
    "sparkplug_publishing.py",  # needs mosquitto (Debian package): CI installs it
    "sparkplug_cpu.py",  # the same
    "sparkplug_store.py",  # the same
    "opcua.py",  # 8 links x 150 tags monitored by asyncua's client, and a bare asyncua server
    "faces.py",  # every face on (Sparkplug, OPC UA, the page) beside Modbus only: needs mosquitto
]


@pytest.mark.parametrize("script", SCRIPTS)
def test_bench_quick(script: str) -> None:
    done = subprocess.run(
        [sys.executable, str(BENCH / script), "--quick"],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=BENCH.parent,
        check=False,
    )
    assert done.returncode == 0, f"{script} failed:\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
    results = [line for line in done.stdout.splitlines() if line.startswith("RESULT ")]
    assert results, f"{script} printed no RESULT line:\n{done.stdout[-3000:]}"
    assert done.stdout.rstrip().splitlines()[-1].startswith("RESULT "), "RESULT must be the final line"
    assert all("=" in field for field in results[-1].split()[1:])
