"""``slc-gateway read`` of all 32 presets on a bad line, under every reading of the manual.

1 in 6 replies garbled, 1 in 8 dropped, a power cycle every 40 commands: the read succeeds and
prints the controller's values (issue 9: it used to exit 1 at the first power cycle when the
controller kept its pre-power-up ID).
"""

from __future__ import annotations

import pytest
from cli_support import cli, fails, ok_json

from gateway.kinds.slc_ascii.sim import SlcAsciiSimulator

PRESETS = [f"{901 + n}.PRE" for n in range(32)]
#: the simulator's presets: 100 + 10 n, and 932 protected (bit 15 masked when read: 500)
EXPECTED = {f"{901 + n}.PRE": 100 + 10 * n for n in range(31)} | {"932.PRE": 500}


def readings() -> list[dict[str, str]]:
    out: list[dict[str, str]] = [{}]
    for name, values in SlcAsciiSimulator.VARIANTS.items():
        out += [{name: value} for value in values[1:]]
    out.append({name: values[-1] for name, values in SlcAsciiSimulator.VARIANTS.items()})
    return out


@pytest.mark.parametrize("variants", readings(), ids=lambda v: ",".join(f"{k}={x}" for k, x in v.items()) or "default")
@pytest.mark.parametrize("seed", [1, 2])
def test_read_all_presets_on_a_bad_line(variants: dict[str, str], seed: int) -> None:
    query = "&".join([f"variant={k}={v}" for k, v in variants.items()] + [
        "garble=6", "drop=8", "power_cycle_every=40", "ladder=0", f"seed={seed}"])
    assert ok_json("read", f"sim://slc150?{query}", *PRESETS) == EXPECTED


def test_simulate_refuses_an_unknown_variant() -> None:
    assert "not one of zero, retained" in fails("simulate", "slc150", "--variant", "power_up_id=kept")
    assert "unknown variant 'nope'" in fails("simulate", "slc150", "--variant", "nope=1")
    result = cli("simulate", "slc150", "--variant", "power_up_id")
    assert result.returncode != 0 and "expected name=value" in result.stderr
