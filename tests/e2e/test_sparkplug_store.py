"""Store and forward end to end (issue 43): the broker stopped for a minute, and a store that fills.

The runs and their checks: ``sparkplug_store_support.py``.
"""

from __future__ import annotations

from pathlib import Path

from mosquitto_support import Broker, broker  # noqa: F401 (the fixture)
from sparkplug_store_support import run_full_store, run_outage


async def test_every_value_change_of_an_outage_reaches_the_host(broker: Broker, tmp_path: Path) -> None:  # noqa: F811
    """The broker is stopped for ``OUTAGE`` seconds (the gateway's reconnects are refused)."""
    await run_outage(broker, tmp_path, "broker")


async def test_a_full_store_drops_the_oldest_says_so_and_live_data_goes_on(broker: Broker,  # noqa: F811
                                                                           tmp_path: Path) -> None:
    await run_full_store(broker, tmp_path)
