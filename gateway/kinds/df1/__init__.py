"""The DF1 link kind: SLC 500 and PLC-5 controllers over DF1, polled or answering their MSGs.

One package per role, each over the sans-I/O protocol in :mod:`gateway.protocols.df1`:

* :mod:`gateway.kinds.df1.full` - the full-duplex master: one controller per port;
* :mod:`gateway.kinds.df1.half` - the half-duplex master: the stations of a multi-drop line;
* :mod:`gateway.kinds.df1.target` - the target: a PLC's MSG instructions read and write the gateway.

Shared by every role, here: the ``[[link]]`` model (``config``), the units and the read plan
(``unit``, ``plc5_unit``, ``plan``), the build that picks the role (``build``), the CLI commands
(``tool``) and the simulators (``sim``, ``simulators``).
"""

from __future__ import annotations

from gateway.kinds.contract import LinkKind
from gateway.kinds.df1.build import build_df1, df1_plan, df1_plan_lines, df1_point_labels, df1_unit_class
from gateway.kinds.df1.config import Df1LinkConfig
from gateway.kinds.df1.simulators import DF1LINE, PLC5, PLC_MSG, SLC504
from gateway.kinds.df1.tool import DF1_TOOL_HINTS, add_df1_options, add_df1_sim_options, run_df1_tool

__all__ = ["KIND"]

KIND: LinkKind[Df1LinkConfig] = LinkKind(
    config_model=Df1LinkConfig,
    build=build_df1,
    plan=df1_plan,
    point_labels=df1_point_labels,
    controllers="SLC 500 / PLC-5",
    simulators=(SLC504, PLC5, DF1LINE, PLC_MSG),
    plan_lines=df1_plan_lines,
    unit_class=df1_unit_class,
    status_counter=("kind_counter", "DF1 master: always 0; DF1 target: duplicate messages (acknowledged, not run)"),
    tool=run_df1_tool,
    hints=DF1_TOOL_HINTS,
    tool_options=add_df1_options,
    simulate_options=add_df1_sim_options,
    item_examples=("N7:0 T4:1.ACC F8:2", "N7:0=5 B3:0/3=1"),
)
