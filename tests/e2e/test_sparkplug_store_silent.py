"""Store and forward end to end (issue 43): the gateway's connection cut silently.

The runs and their checks: ``sparkplug_store_support.py``.
"""

from __future__ import annotations

from pathlib import Path

from mosquitto_support import Broker, broker  # noqa: F401 (the fixture)
from sparkplug_store_support import run_outage


async def test_every_value_change_of_a_silent_cut_reaches_the_host(broker: Broker, tmp_path: Path) -> None:  # noqa: F811
    """Every packet dropped both ways: only the keepalive finds it, and the window before it is replayed too."""
    await run_outage(broker, tmp_path, "silent")
