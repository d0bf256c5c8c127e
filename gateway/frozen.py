"""``@frozen``: the one spelling of an immutable record in ``gateway/``.

The events a sans-I/O core hands out, PCCC requests and replies, addresses, plan entries and
config values are records: their fields are set once, at construction, compared by value, and
they hold nothing but their fields.  Each is declared ``@frozen``, a dataclass that is frozen and
slotted (``dataclass(frozen=True, slots=True)``, as attrs spells it ``@frozen``); type checkers
read it as a frozen dataclass (PEP 681).

A record that needs something else (identity equality, no slots for a generic alias) says so with
:func:`dataclasses.dataclass` and its own arguments.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TypeVar, dataclass_transform

__all__ = ["frozen"]

_T = TypeVar("_T")


@dataclass_transform(frozen_default=True)
def frozen(cls: type[_T]) -> type[_T]:
    """Make ``cls`` a frozen, slotted dataclass (a new class, as ``slots=True`` makes one)."""
    return dataclass(frozen=True, slots=True)(cls)
