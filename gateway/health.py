"""``GET /healthz``: 200 when every link's verdict is up, 503 otherwise, with each link's state.

The verdict is the one of ``gateway.freshness`` (the controller answers and its fast-class data is
younger than its stale limit); nothing here decides it again.  The body names each link's unit id,
up, fresh, data age and last error (credentials redacted): no paths, no configuration beyond the
link names and unit ids.  A container health check (``gateway.healthcheck``) asks it.
"""

from __future__ import annotations

import asyncio
import json
import math

from gateway.http import JSON_CONTENT_TYPE, Response
from gateway.logutil import public_error
from gateway.view import GatewayView

__all__ = ["Health", "health"]


def health(gateway: GatewayView, now: float) -> tuple[bool, dict[str, object]]:
    """``(healthy, body)`` of ``/healthz`` at loop time ``now``."""
    links: dict[str, object] = {}
    healthy = True
    for unit in gateway.units:
        verdict = unit.verdict(now)
        age = verdict.age
        healthy = healthy and verdict.fresh
        links[unit.name] = {
            "unit": unit.unit_id,
            "up": verdict.up,
            "fresh": verdict.fresh,
            "age_seconds": round(age, 3) if math.isfinite(age) else None,
            "last_error": public_error(unit.driver.last_error),
        }
    return healthy, {"status": "ok" if healthy else "degraded", "links": links}


class Health:
    """The ``/healthz`` room of the HTTP listener (``gateway.http``)."""

    def __init__(self, gateway: GatewayView) -> None:
        self.gateway = gateway

    def route(self, path: str, query: str) -> Response:
        healthy, document = health(self.gateway, asyncio.get_running_loop().time())
        body = (json.dumps(document, separators=(",", ":")) + "\n").encode()
        return (200 if healthy else 503), JSON_CONTENT_TYPE, body, []
