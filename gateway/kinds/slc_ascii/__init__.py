"""The SLC 100/150 link kind (ASCII protocol): one controller per port, the fixed default map.

Its rooms: the sans-I/O protocol in :mod:`gateway.protocols.slc_ascii`, the driver in
:mod:`gateway.kinds.slc_ascii.driver`, the simulator in :mod:`gateway.kinds.slc_ascii.sim`, the ``[[link]]``
model in :mod:`gateway.kinds.slc_ascii.config`; here the plan (``plan``), the unit (``unit``) and the
CLI commands (``tool``).
"""

from __future__ import annotations

from gateway.kinds.contract import LinkKind
from gateway.kinds.slc_ascii.config import SlcAsciiLinkConfig
from gateway.kinds.slc_ascii.plan import plan_lines, point_labels, slc_ascii_plan
from gateway.kinds.slc_ascii.simulators import SLC100, SLC150
from gateway.kinds.slc_ascii.tool import (
    SLC_ASCII_TOOL_HINTS,
    add_slc_ascii_options,
    add_slc_ascii_sim_options,
    run_slc_ascii_tool,
)
from gateway.kinds.slc_ascii.unit import build_slc_ascii

__all__ = ["KIND"]

KIND: LinkKind[SlcAsciiLinkConfig] = LinkKind(
    config_model=SlcAsciiLinkConfig,
    build=build_slc_ascii,
    plan=lambda link: slc_ascii_plan(),
    controllers="SLC 100/150",
    plan_lines=plan_lines,
    point_labels=lambda link: point_labels(),
    simulators=(SLC150, SLC100),
    tool=run_slc_ascii_tool,
    hints=SLC_ASCII_TOOL_HINTS,
    tool_options=add_slc_ascii_options,
    simulate_options=add_slc_ascii_sim_options,
    item_examples=("901.ACC 901.PRE 701 11 @0x84", "905.PRE=1234 701=1"),
    status_counter=("id_resyncs", "ID resyncs"),
)
