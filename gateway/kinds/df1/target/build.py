"""A DF1 ``[[link]]`` with ``role = "target"`` as a unit and its runner (part of the DF1 kind's build)."""

from __future__ import annotations

import asyncio
from typing import Any

from gateway.kinds.contract import PointLabels, unit_options
from gateway.kinds.df1.config import Df1LinkConfig
from gateway.kinds.df1.target.driver import TargetRunner
from gateway.kinds.df1.target.store import TargetStore
from gateway.kinds.df1.target.unit import TargetUnit, load_table, target_plan, target_point_labels
from gateway.modbus.mapping import Plan
from gateway.protocols.df1.framing import Checksum
from gateway.protocols.df1.pccc.target import PcccTarget

__all__ = ["build_target", "target_link_labels", "target_link_plan"]


def target_link_plan(link: Df1LinkConfig) -> Plan[Any, Any]:
    return target_plan(link.file)


def target_link_labels(link: Df1LinkConfig) -> PointLabels:
    return target_point_labels(link.file)


def _now() -> float:
    try:
        return asyncio.get_running_loop().time()
    except RuntimeError:
        return 0.0


def build_target(link: Df1LinkConfig) -> TargetUnit:
    """The unit of a target link, its table loaded (``initial``, then ``persist``); its runner is ``unit.driver``."""
    store = TargetStore(link.persist) if link.persist is not None else None
    table = load_table(link.file, store, _now())
    runner = TargetRunner(
        link.port,
        name=link.name,
        settings=link.line_settings,
        target=PcccTarget(table),
        station=link.station,
        checksum=Checksum.CRC if link.checksum == "crc" else Checksum.BCC,
        duplicate_detect=link.duplicate_detect,
        check_dst=link.check_dst,
        ack_timeout=link.ack_timeout,
        trace=link.trace,
    )
    options = unit_options(link)
    if "stale_after" not in link.model_fields_set:
        options["stale_after"] = float("inf")  # a PLC may send its MSGs rarely: stale only when asked for
    return TargetUnit(driver=runner, files=link.file, store=store, **options)
