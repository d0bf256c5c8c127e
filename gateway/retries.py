"""The ``retries`` key's default, one value for every layer that has one.

Tries after the first before a transaction fails: the default of the ``[[link]]`` key
(:mod:`gateway.config.link`), of every kind's driver, of the sans-I/O cores (a read gets
``retries + 1`` tries, a write as many read-backs, :mod:`gateway.protocols.df1.write_verdict`) and
of the CLI's ``--retries``.  A module of its own because the cores must not import the config.
"""

from __future__ import annotations

from typing import Final

__all__ = ["DEFAULT_RETRIES"]

DEFAULT_RETRIES: Final = 3
