"""The ``sim://`` models of the DF1 kind: ``slc504``, ``plc5`` and the half-duplex line ``df1line``."""

from __future__ import annotations

from collections.abc import Mapping

from gateway.kinds.df1.config import DF1_DEFAULTS
from gateway.kinds.df1.sim.df1_half_models import LINE_VARIANTS, create_line, create_plc5
from gateway.kinds.df1.sim.plc5 import Plc5Simulator
from gateway.kinds.df1.sim.plc_msg import create_plc_msg
from gateway.kinds.df1.sim.slc500 import Slc500Simulator
from gateway.sim.models import SimModel
from gateway.sim.serve import SimDevice

__all__ = ["DF1LINE", "PLC5", "PLC_MSG", "SLC504"]


def _slc504(faults: Mapping[str, str], ladder: bool, variants: Mapping[str, str]) -> SimDevice:
    return Slc500Simulator.from_options(dict(faults), ladder=ladder, variants=dict(variants))


def _slc504_variants() -> Mapping[str, tuple[str, ...]]:
    return Slc500Simulator.VARIANTS


def _plc5(faults: Mapping[str, str], ladder: bool, variants: Mapping[str, str]) -> SimDevice:
    return create_plc5(faults, ladder=ladder, variants=variants)


def _plc5_variants() -> Mapping[str, tuple[str, ...]]:
    return Plc5Simulator.VARIANTS


def _df1line(faults: Mapping[str, str], ladder: bool, variants: Mapping[str, str]) -> SimDevice:
    return create_line(faults, ladder=ladder, variants=variants)


def _df1line_variants() -> Mapping[str, tuple[str, ...]]:
    return LINE_VARIANTS


_DF1_LINE = DF1_DEFAULTS.settings
_DF1_OPTIONS = frozenset({"withhold_ack", "duplicate", "noise"})
_DF1_SETTINGS = frozenset({"checksum", "station"})

SLC504 = SimModel("slc504", _slc504, _DF1_LINE, _slc504_variants, _DF1_OPTIONS, _DF1_SETTINGS)
#: a PLC-5 on DF1 full duplex (word range commands; ``gateway.kinds.df1.sim.plc5``)
PLC5 = SimModel("plc5", _plc5, _DF1_LINE, _plc5_variants, _DF1_OPTIONS, _DF1_SETTINGS)
#: a DF1 half-duplex multi-drop line of SLC 5/04 or PLC-5 stations (``gateway.kinds.df1.sim.df1_multidrop``); its
#: stations, faults and timing are URL options (``stations=1,2,3&dead=3&corrupt=6&ignore=10``)
#: a PLC whose MSG instructions read and write the gateway (DF1 target mode; ``gateway.kinds.df1.sim.plc_msg``)
PLC_MSG = SimModel("plc-msg", create_plc_msg, _DF1_LINE, cli_settings=frozenset({"checksum", "station"}))
DF1LINE = SimModel("df1line", _df1line, _DF1_LINE, _df1line_variants, cli_settings=frozenset({"checksum"}),
                   self_paced=True)
