"""Facts that several layers use, each stated in one module and imported by the others.

The values are stated here from the manuals; the identity checks show that the other modules
take the one value instead of a copy of it.
"""

from __future__ import annotations

import inspect
import subprocess
import sys

from gateway import retries, tools_common
from gateway.config.link import LinkBase
from gateway.protocols.df1 import write_verdict
from gateway.protocols.df1.full_duplex import transaction
from gateway.protocols.df1.half_duplex import transactions as half_duplex_transactions


def test_one_retries_default() -> None:
    # 3: the SLC 500 / MicroLogix "Message Retries" default (1766-RM001A p. 600)
    assert retries.DEFAULT_RETRIES == 3
    assert LinkBase.model_fields["retries"].default is retries.DEFAULT_RETRIES
    assert tools_common.DEFAULT_RETRIES is retries.DEFAULT_RETRIES
    assert write_verdict.DEFAULT_RETRIES is retries.DEFAULT_RETRIES
    for core in (transaction.Df1Transactions, half_duplex_transactions.HalfDuplexTransactions):
        assert inspect.signature(core).parameters["retries"].default is retries.DEFAULT_RETRIES, core


def test_the_healthcheck_packs_the_servers_mbap_header_and_stays_light() -> None:
    """MBAP (Modbus Messaging on TCP/IP Implementation Guide V1.0b §3.1.3): transaction id,
    protocol id, length, unit id, big-endian, 7 bytes; the health check starts nothing heavy."""
    from gateway import healthcheck
    from gateway.modbus import mbap

    assert healthcheck.MBAP is mbap.MBAP
    assert mbap.MBAP.pack(0x4843, 0, 6, 1) == bytes.fromhex("48 43 00 00 00 06 01")
    code = "import sys, gateway.healthcheck; print(sorted(m for m in sys.modules if m.split('.')[0] in " \
           "('gateway', 'pymodbus', 'pydantic', 'asyncio')))"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    assert done.stdout.strip() == str(["gateway", "gateway.errors", "gateway.healthcheck", "gateway.modbus",
                                        "gateway.modbus.mbap"])


def test_one_never() -> None:
    """The time of what has not happened yet: before every loop time, in the schedule, the cache's
    stamps and the images' deadlines alike (a comparison with any of them must agree)."""
    from gateway import cache, image, schedule

    assert schedule.NEVER == float("-inf")
    assert vars(cache)["NEVER"] is vars(image)["NEVER"] is schedule.NEVER
