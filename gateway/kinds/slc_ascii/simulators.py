"""The ``sim://`` models of the SLC 100/150 kind: ``slc150`` and ``slc100``."""

from __future__ import annotations

from collections.abc import Mapping

from gateway.kinds.slc_ascii.config import SLC_ASCII_DEFAULTS
from gateway.kinds.slc_ascii.sim import FaultPlan, SlcAsciiSimulator
from gateway.protocols.slc_ascii.commands import ControllerType
from gateway.sim.models import SimFactory, SimModel
from gateway.sim.serve import SimDevice

__all__ = ["SLC100", "SLC150"]


def _slc_ascii(model: str) -> SimFactory:
    def create(faults: Mapping[str, str], ladder: bool, variants: Mapping[str, str]) -> SimDevice:
        return SlcAsciiSimulator(ControllerType[model.upper()], faults=FaultPlan.from_options(dict(faults)),
                                 ladder=ladder, variants=dict(variants))

    return create


def _slc_ascii_variants() -> Mapping[str, tuple[str, ...]]:
    return SlcAsciiSimulator.VARIANTS


_ASCII_LINE = SLC_ASCII_DEFAULTS.settings
_ASCII_OPTIONS = frozenset({"power_cycle_every", "fault_every"})

SLC150 = SimModel("slc150", _slc_ascii("slc150"), _ASCII_LINE, _slc_ascii_variants, _ASCII_OPTIONS)
SLC100 = SimModel("slc100", _slc_ascii("slc100"), _ASCII_LINE, _slc_ascii_variants, _ASCII_OPTIONS)
