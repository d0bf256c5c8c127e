"""deploy/grafana: every metric the dashboard queries is exported by a running gateway (the demo)."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

from prometheus_client.parser import text_string_to_metric_families

from gateway.app import Gateway
from gateway.config import load_config
from tests.e2e.modbus_support import connect, exception_code
from tests.test_metrics import get

ROOT = Path(__file__).resolve().parent.parent
DASHBOARD = ROOT / "deploy" / "grafana" / "slc-gateway.json"
METRIC = re.compile(r"\bslc_gateway_[a-z0-9_]+")


def expressions(node: Any) -> list[str]:
    """Every PromQL ``expr`` of the dashboard (panels and their targets, at any depth)."""
    if isinstance(node, dict):
        found = [node["expr"]] if isinstance(node.get("expr"), str) else []
        return found + [e for value in node.values() for e in expressions(value)]
    if isinstance(node, list):
        return [e for value in node for e in expressions(value)]
    return []


def test_the_dashboard_covers_the_issue_list() -> None:
    dashboard = json.loads(DASHBOARD.read_text(encoding="utf-8"))
    queried = {name for expr in expressions(dashboard) for name in METRIC.findall(expr)}
    for needed in ("slc_gateway_link_up", "slc_gateway_data_age_seconds", "slc_gateway_transactions_total",
                   "slc_gateway_errors_total", "slc_gateway_retries_total", "slc_gateway_modbus_requests_total",
                   "slc_gateway_modbus_exceptions_total", "slc_gateway_write_duration_seconds_bucket"):
        assert needed in queried, needed
    query = next(v for v in dashboard["templating"]["list"] if v["name"] == "link")["query"]
    assert METRIC.findall(query) == ["slc_gateway_link_up"]
    scrape = (DASHBOARD.parent / "prometheus.yml").read_text(encoding="utf-8")
    assert "metrics_path: /metrics" in scrape and "127.0.0.1:9108" in scrape


async def test_every_metric_the_dashboard_queries_is_exported() -> None:
    dashboard = json.loads(DASHBOARD.read_text(encoding="utf-8"))
    queried = {name for expr in expressions(dashboard) for name in METRIC.findall(expr)}
    query = next(v for v in dashboard["templating"]["list"] if v["name"] == "link")["query"]
    queried |= set(METRIC.findall(query))
    config = load_config(ROOT / "config" / "demo.toml")
    assert config.metrics is not None
    config = config.model_copy(update={
        "modbus": config.modbus.model_copy(update={"listen": "127.0.0.1:0"}),
        "metrics": config.metrics.model_copy(update={"listen": "127.0.0.1:0"}),
    })
    async with Gateway(config) as gateway, connect(gateway.port) as client:
        assert gateway.metrics is not None
        # A read, a refused write (exception 2: not mapped) and a written value: every family has samples.
        assert exception_code(await client.read_input_registers(1000, count=1, device_id=1)) is None
        assert exception_code(await client.write_register(5000, 1, device_id=3)) == 2
        await client.write_register(0, 7, device_id=3)
        text = (await get(gateway.metrics.port, "/metrics")).body.decode()
    exported = {sample.name for family in text_string_to_metric_families(text) for sample in family.samples}
    missing = sorted(queried - exported)
    assert not missing, f"the dashboard queries metrics the gateway does not export: {missing}"
    assert len(queried) >= 12
