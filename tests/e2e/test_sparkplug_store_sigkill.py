"""Store and forward end to end (issue 43): the gateway SIGKILLed in the middle of the outage.

The runs and their checks: ``sparkplug_store_support.py``.
"""

from __future__ import annotations

from pathlib import Path

from mosquitto_support import Broker, broker  # noqa: F401 (the fixture)
from sparkplug_store_support import run_outage


async def test_every_value_change_committed_before_a_sigkill_reaches_the_host(broker: Broker,  # noqa: F811
                                                                              tmp_path: Path) -> None:
    """The broker stopped, the gateway killed once every value written is committed, and started again."""
    await run_outage(broker, tmp_path, "sigkill")
