"""Facts that several layers use, each stated in one module and imported by the others.

The values are stated here from the manuals; the identity checks show that the other modules
take the one value instead of a copy of it.
"""

from __future__ import annotations

import inspect

from gateway import retries, tools_common
from gateway.config.link import LinkBase
from gateway.protocols.df1 import half_duplex_transactions, transaction, write_verdict


def test_one_retries_default() -> None:
    # 3: the SLC 500 / MicroLogix "Message Retries" default (1766-RM001A p. 600)
    assert retries.DEFAULT_RETRIES == 3
    assert LinkBase.model_fields["retries"].default is retries.DEFAULT_RETRIES
    assert tools_common.DEFAULT_RETRIES is retries.DEFAULT_RETRIES
    assert write_verdict.DEFAULT_RETRIES is retries.DEFAULT_RETRIES
    for core in (transaction.Df1Transactions, half_duplex_transactions.HalfDuplexTransactions):
        assert inspect.signature(core).parameters["retries"].default is retries.DEFAULT_RETRIES, core
