"""The catalogue of simulator models: ``sim://NAME`` -> how to make the controller, its variants.

Each model is a :class:`SimModel`; :mod:`gateway.sim` looks models up here.  Every model belongs
to a link kind, which lists it in its ``simulators``; the registry of kinds (:mod:`gateway.kinds`)
adds them here when it is imported (the built-in kinds, marked ``builtin``) or when a kind is
registered.  This module sits below the drivers (``gateway.transport`` opens ``sim://`` URLs
through :mod:`gateway.sim`), so it knows no kind: it is filled from above.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import field
from typing import TypeVar

from gateway.frozen import frozen
from gateway.sim.serve import SimDevice
from gateway.streams import SerialSettings

__all__ = ["SimFactory", "SimModel", "read_sim_option", "register_sim_model", "sim_models", "unregister_sim_model"]

T = TypeVar("T")

#: (fault options, ladder running, variant values) -> a new simulated controller
SimFactory = Callable[[Mapping[str, str], bool, Mapping[str, str]], SimDevice]


@frozen
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


def read_sim_option(options: Mapping[str, str], key: str, parse: Callable[[str], T], default: T, *,
                    what: str = "simulator option") -> T:
    """``options[key]`` (a ``sim://`` URL's option, white space stripped) read by ``parse``, or
    ``default`` when it is not given; a ValueError names the option (``what key=text``)."""
    text = options.get(key)
    if text is None:
        return default
    try:
        return parse(text.strip())
    except ValueError:
        raise ValueError(f"{what} {key}={text!r} cannot be read") from None


_models: dict[str, SimModel] = {}
#: the models of the built-in kinds (registered by :mod:`gateway.kinds`): never unregistered
_builtin: set[str] = set()


def sim_models() -> Mapping[str, SimModel]:
    """Every simulator model by name, built-in ones first."""
    return _models


def register_sim_model(model: SimModel, *, builtin: bool = False) -> None:
    """Add a model (a link kind's); the same model again is a no-op, another of the same name an error.

    ``builtin``: a model of a kind that ships with the gateway (never unregistered).
    """
    known = _models.get(model.name)
    if known is not None and known is not model:
        raise ValueError(f"sim://{model.name}: a simulator of that name is already registered")
    _models[model.name] = model
    if builtin:
        _builtin.add(model.name)


def unregister_sim_model(name: str) -> None:
    """Remove a registered model (tests); built-in models stay."""
    if name not in _builtin:
        _models.pop(name, None)
