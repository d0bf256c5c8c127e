"""``NEED_DATA``: what every sans-I/O core's ``next_event()`` returns when it has nothing to report
until it gets more input (as in h11).  One sentinel for every protocol."""

from __future__ import annotations

import enum
from typing import Final

__all__ = ["NEED_DATA", "NeedData"]


class NeedData(enum.Enum):
    """Sentinel type: a sans-I/O core needs more input before it can report anything."""

    NEED_DATA = "NEED_DATA"

    def __repr__(self) -> str:
        return "NEED_DATA"


NEED_DATA: Final = NeedData.NEED_DATA
