"""The catalogue of simulator models: ``sim://NAME`` -> how to make the controller, its variants.

Each model is a :class:`SimModel`; :mod:`gateway.sim` looks models up here.  The built-in models
are listed in :data:`BUILTIN_MODELS` (their classes are imported when a model is first made, so
that opening one simulator does not load every protocol); a link kind from outside brings its
own and :func:`gateway.links.register_link_kind` adds them with :func:`register_sim_model`.

This module sits below the drivers (``gateway.transport`` opens ``sim://`` URLs through
:mod:`gateway.sim`), so it cannot ask the link kinds' registry for their simulators: the
built-in catalogue is kept here, and each built-in kind points to its entries.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

from gateway.config.df1 import DF1_DEFAULTS
from gateway.config.slc_ascii import SLC_ASCII_DEFAULTS
from gateway.sim.serve import SimDevice
from gateway.streams import SerialSettings

__all__ = ["BUILTIN_MODELS", "DF1LINE", "PLC5", "SLC100", "SLC150", "SLC504", "SimModel", "register_sim_model",
           "sim_models", "unregister_sim_model"]

#: (fault options, ladder running, variant values) -> a new simulated controller
SimFactory = Callable[[Mapping[str, str], bool, Mapping[str, str]], SimDevice]


@dataclass(frozen=True, slots=True)
class SimModel:
    """One ``sim://NAME`` simulator model."""

    name: str
    #: makes a new simulated controller
    create: SimFactory
    #: the line the controller speaks (``simulate --paced`` paces characters at its speed)
    settings: SerialSettings
    #: the variants (readings of the manual) it has: name -> values, the default first
    variants: Callable[[], Mapping[str, tuple[str, ...]]] = dict
    #: the ``slc-gateway simulate`` fault options it takes besides garble, drop, delay, seed (given when not 0)
    cli_options: frozenset[str] = field(default_factory=frozenset)
    #: the ``slc-gateway simulate`` settings it takes (always given: they have defaults)
    cli_settings: frozenset[str] = field(default_factory=frozenset)
    #: the device paces its own bytes (a multi-drop line judging collisions on its own clock): it is
    #: served without line settings, ``turnaround`` is its own option and ``paced`` does not apply
    self_paced: bool = False


def _slc_ascii(model: str) -> SimFactory:
    def create(faults: Mapping[str, str], ladder: bool, variants: Mapping[str, str]) -> SimDevice:
        from gateway.protocols.slc_ascii.commands import ControllerType
        from gateway.sim.slc_ascii import FaultPlan, SlcAsciiSimulator

        return SlcAsciiSimulator(ControllerType[model.upper()], faults=FaultPlan.from_options(dict(faults)),
                                 ladder=ladder, variants=dict(variants))

    return create


def _slc_ascii_variants() -> Mapping[str, tuple[str, ...]]:
    from gateway.sim.slc_ascii import SlcAsciiSimulator

    return SlcAsciiSimulator.VARIANTS


def _slc504(faults: Mapping[str, str], ladder: bool, variants: Mapping[str, str]) -> SimDevice:
    from gateway.sim.slc500 import Slc500Simulator

    return Slc500Simulator.from_options(dict(faults), ladder=ladder, variants=dict(variants))


def _slc504_variants() -> Mapping[str, tuple[str, ...]]:
    from gateway.sim.slc500 import Slc500Simulator

    return Slc500Simulator.VARIANTS


def _plc5(faults: Mapping[str, str], ladder: bool, variants: Mapping[str, str]) -> SimDevice:
    from gateway.sim.df1_half_models import create_plc5

    return create_plc5(faults, ladder=ladder, variants=variants)


def _plc5_variants() -> Mapping[str, tuple[str, ...]]:
    from gateway.sim.plc5 import Plc5Simulator

    return Plc5Simulator.VARIANTS


def _df1line(faults: Mapping[str, str], ladder: bool, variants: Mapping[str, str]) -> SimDevice:
    from gateway.sim.df1_half_models import create_line

    return create_line(faults, ladder=ladder, variants=variants)


def _df1line_variants() -> Mapping[str, tuple[str, ...]]:
    from gateway.sim.df1_half_models import LINE_VARIANTS

    return LINE_VARIANTS


_ASCII_LINE = SLC_ASCII_DEFAULTS.settings
_DF1_LINE = DF1_DEFAULTS.settings
_ASCII_OPTIONS = frozenset({"power_cycle_every", "fault_every"})
_DF1_OPTIONS = frozenset({"withhold_ack", "duplicate", "noise"})
_DF1_SETTINGS = frozenset({"checksum", "station"})

SLC150 = SimModel("slc150", _slc_ascii("slc150"), _ASCII_LINE, _slc_ascii_variants, _ASCII_OPTIONS)
SLC100 = SimModel("slc100", _slc_ascii("slc100"), _ASCII_LINE, _slc_ascii_variants, _ASCII_OPTIONS)
SLC504 = SimModel("slc504", _slc504, _DF1_LINE, _slc504_variants, _DF1_OPTIONS, _DF1_SETTINGS)
#: a PLC-5 on DF1 full duplex (word range commands; ``gateway.sim.plc5``)
PLC5 = SimModel("plc5", _plc5, _DF1_LINE, _plc5_variants, _DF1_OPTIONS, _DF1_SETTINGS)
#: a DF1 half-duplex multi-drop line of SLC 5/04 or PLC-5 stations (``gateway.sim.df1_multidrop``); its
#: stations, faults and timing are URL options (``stations=1,2,3&dead=3&corrupt=6&ignore=10``)
DF1LINE = SimModel("df1line", _df1line, _DF1_LINE, _df1line_variants, cli_settings=frozenset({"checksum"}),
                   self_paced=True)

BUILTIN_MODELS = (SLC150, SLC100, SLC504, PLC5, DF1LINE)

_models: dict[str, SimModel] = {model.name: model for model in BUILTIN_MODELS}


def sim_models() -> Mapping[str, SimModel]:
    """Every simulator model by name, built-in ones first."""
    return _models


def register_sim_model(model: SimModel) -> None:
    """Add a model (a link kind's); the same model again is a no-op, another of the same name an error."""
    known = _models.get(model.name)
    if known is not None and known is not model:
        raise ValueError(f"sim://{model.name}: a simulator of that name is already registered")
    _models[model.name] = model


def unregister_sim_model(name: str) -> None:
    """Remove a registered model (tests); built-in models stay."""
    if name not in {model.name for model in BUILTIN_MODELS}:
        _models.pop(name, None)
