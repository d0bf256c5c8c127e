"""The registry of link kinds: protocol name -> :class:`~gateway.kinds.contract.LinkKind`.

Everything that depends on the protocol of a link (its config model, serial defaults, plan,
unit factory, simulators, CLI commands) is found here by the link's ``protocol``; no module
outside a kind's package decides by protocol name.  Adding a protocol means adding one package
under ``gateway/kinds/`` that exports a ``KIND``, and one entry in :data:`BUILTIN_KINDS` (or a
call to :func:`register_link_kind` from outside, as the tests do).

An unknown protocol name is an error naming the known ones (:func:`link_kind`), never a fallback.
"""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType
from typing import Any

from gateway.config.link import LinkBase
from gateway.config.links import use_link_kinds
from gateway.kinds import df1, slc_ascii
from gateway.kinds.contract import Built, LinkKind, LinkRunner, ToolHints, unit_options
from gateway.sim.models import register_sim_model, unregister_sim_model

__all__ = [
    "BUILTIN_KINDS",
    "LINK_KINDS",
    "Built",
    "LinkKind",
    "LinkRunner",
    "ToolHints",
    "kind_names",
    "link_kind",
    "link_kinds",
    "register_link_kind",
    "registry_version",
    "unit_options",
    "unregister_link_kind",
]

#: The kinds that ship with the gateway, in the order help texts list them (the first is the
#: CLI's default protocol).
BUILTIN_KINDS: tuple[LinkKind[Any], ...] = (slc_ascii.KIND, df1.KIND)

_kinds: dict[str, LinkKind[Any]] = {kind.name: kind for kind in BUILTIN_KINDS}
for _kind in BUILTIN_KINDS:
    for _model in _kind.simulators:
        register_sim_model(_model, builtin=True)
_version = [0]

#: Every registered kind by protocol name (a read-only view: use register_link_kind to add one).
LINK_KINDS: Mapping[str, LinkKind[Any]] = MappingProxyType(_kinds)


def _config_models() -> Mapping[str, type[LinkBase]]:
    return {name: kind.config_model for name, kind in _kinds.items()}


use_link_kinds(_config_models)


def link_kinds() -> Mapping[str, LinkKind[Any]]:
    """Every registered kind by protocol name, built-in ones first."""
    return LINK_KINDS


def kind_names() -> tuple[str, ...]:
    """The protocol names, built-in ones first."""
    return tuple(_kinds)


def registry_version() -> int:
    """A number that changes whenever a kind is registered or unregistered (caches key on it)."""
    return _version[0]


def link_kind(protocol: str) -> LinkKind[Any]:
    """The kind of ``protocol``; KeyError naming the known protocols."""
    kind = _kinds.get(protocol)
    if kind is None:
        raise KeyError(f"unknown protocol {protocol!r}: known are {', '.join(_kinds)}")
    return kind


def register_link_kind(kind: LinkKind[Any]) -> None:
    """Add a kind: its links are accepted in ``[[link]]``, its simulators open as ``sim://NAME``.

    Its config model must name every simulator it brings in ``sim_models``.  A second kind of
    the same name is an error.
    """
    if kind.name in _kinds:
        raise ValueError(f"a link kind named {kind.name!r} is already registered")
    names = {model.name for model in kind.simulators}
    if not names <= set(kind.config_model.sim_models):
        raise ValueError(f"{kind.name}: simulators {sorted(names)} missing from the config model's sim_models")
    for model in kind.simulators:
        register_sim_model(model)
    _kinds[kind.name] = kind
    _version[0] += 1


def unregister_link_kind(name: str) -> None:
    """Remove a registered kind and its simulators (tests); built-in kinds stay."""
    if any(kind.name == name for kind in BUILTIN_KINDS):
        raise ValueError(f"{name} is a built-in link kind")
    kind = _kinds.pop(name, None)
    if kind is not None:
        for model in kind.simulators:
            unregister_sim_model(model.name)
        _version[0] += 1
