"""The variant soak: the whole gateway under the harsh fault mix, in every reading of the SLC manual.

For the simulator's default reading, each other reading alone and all of them at once: 1 in 4
replies garbled, 1 in 6 dropped, a power cycle every 25 commands, while a SCADA client reads
all 31 presets (holding 32-62) and writes one every few seconds (``bench/availability.py``
does the measuring).  Checked: at least 90 % of the reads after the first scan answered fresh,
no value the controller never held, every acknowledged write applied exactly once, none twice.

Quick mode (default, CI): 4 s per reading, about a minute.  Long mode (``--soak``): 60 s per
reading under the harsh mix and 30 s under the realistic one; ``-s`` prints the figures
(RELIABILITY.md).
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

import pytest

from gateway.sim import reset_simulators

BENCH = Path(__file__).resolve().parents[2] / "bench"


def _availability() -> ModuleType:
    sys.path.insert(0, str(BENCH))
    spec = importlib.util.spec_from_file_location("availability", BENCH / "availability.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


availability = _availability()
READINGS = availability.variant_list(everything=True)


@pytest.mark.soak
@pytest.mark.parametrize("variants", READINGS, ids=[availability.describe(v).replace(" ", "-") for v in READINGS])
async def test_variant_soak(variants: dict[str, str], request: pytest.FixtureRequest) -> None:
    long = bool(request.config.getoption("--soak", default=False))
    mixes = [("harsh", 60.0), ("realistic", 30.0)] if long else [("harsh", 4.0)]
    for mix, seconds in mixes:
        reset_simulators()
        figures = await availability.measure(variants, availability.MIXES[mix], seconds, seed=7,
                                             write_every=1.0 if not long else 3.0)
        print(f"\nvariant soak {availability.describe(variants)} {mix} {seconds:g} s: {figures}")
        assert figures["wrong"] == 0, figures["wrong_examples"]
        assert figures["double_writes"] == 0
        assert figures["lost_writes"] == 0
        assert figures["fresh"] >= 0.9, figures
        assert figures["reads"] > 10 * seconds
        assert figures["power_cycles"] > 0 or mix == "clean"
