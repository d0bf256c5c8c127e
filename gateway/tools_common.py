"""What every link kind's CLI tool shares: result printing and the retry default.

Every link kind's tool (``gateway.kinds.<kind>.tool``) uses these, and :mod:`gateway.tools`
re-exports them; keeping them here lets ``tools`` hand a command to a kind's tool without the
tool importing ``tools`` back, which would close an import circle.
"""

from __future__ import annotations

import json
from typing import Any

from gateway.config.link import DEFAULT_RETRIES

__all__ = ["DEFAULT_RETRIES", "PROBE_RETRIES", "print_result", "resolve_retries"]


def print_result(result: dict[str, Any], as_json: bool) -> None:
    """``key = value`` lines, or one JSON object with ``--json``."""
    if as_json:
        print(json.dumps(result))
    else:
        for key, value in result.items():
            print(f"{key} = {str(value).lower() if isinstance(value, bool) else value}")


#: Retries per transaction when --retries is not given: ``DEFAULT_RETRIES``, the ``retries`` key's
#: default.  A probe asks "does anything answer?": with one retry it gives up within a few seconds
#: on either protocol (DF1: 2 tries of 2 ACK waits).
PROBE_RETRIES = 1


def resolve_retries(command: str, retries: int | None) -> int:
    if retries is not None:
        return retries
    return PROBE_RETRIES if command == "probe" else DEFAULT_RETRIES
