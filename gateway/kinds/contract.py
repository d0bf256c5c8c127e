"""What a link kind (a protocol) provides: :class:`LinkKind`, and what its factory returns.

A kind is one package under ``gateway/kinds/`` that exports one ``KIND``; the registry
(:mod:`gateway.kinds`) maps protocol names to kinds.  Nothing outside a kind's package names its
protocol: the app, the config, the CLI and the simulators ask the registry.

The unit factory gets the ``[[link]]`` tables of its kind on one line at once (``build(links)``:
the links whose ports name the same line, ``gateway.config._common.port_key``; the Gateway builds
each line on its own so that a config reload can restart one line and keep the others) and returns
the units and the *runners* (:class:`LinkRunner`: what owns a serial line and moves bytes).  A
full-duplex kind returns one runner per unit (its driver); a kind whose controllers share one
port (several ``[[link]]`` on one half-duplex line, polled by one master) returns one runner for
the line and as many units as links.  The Gateway runs the runners and the units' pollers, and
closes the runners when it stops.
"""

from __future__ import annotations

import argparse
from collections.abc import Awaitable, Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Generic, Protocol, TypeVar, cast

from gateway.config.link import LinkBase, SerialDefaults, protocol_of
from gateway.frozen import frozen
from gateway.line_driver import LineDriverOptions, OpenStream
from gateway.modbus.mapping import Plan, PointLabel, Table
from gateway.sim.models import SimModel
from gateway.unit import Unit, UnitOptions
from gateway.unit_writes import WritableRange

__all__ = [
    "Built",
    "LinkKind",
    "LinkRunner",
    "PointLabels",
    "ToolHints",
    "block_lines",
    "line_options",
    "protocol_of",
    "unit_options",
]

C = TypeVar("C", bound=LinkBase)


class LinkRunner(Protocol):
    """What owns a line: runs until cancelled (reconnecting as needed); ``close`` ends it."""

    @property
    def name(self) -> str: ...

    async def run(self) -> None: ...

    async def close(self) -> None: ...


@frozen
class Built:
    """What a kind's factory made of its links: one unit per link, and the runners of their lines."""

    units: Sequence[Unit[Any, Any]]
    runners: Sequence[LinkRunner]


#: per ``(table, Modbus address)`` of a link's plan: what the point is in the controller
PointLabels = Mapping[tuple[Table, int], PointLabel]

#: ``(command, parsed arguments, opener)`` -> exit status: a kind's diagnostic commands (probe, read ...)
ToolRunner = Callable[[str, argparse.Namespace, OpenStream], Awaitable[int]]


@frozen
class ToolHints:
    """What the CLI says after no valid answer came: which protocol the bytes look like, what to check."""

    #: whether bytes that came back look like this kind's protocol
    looks_like: Callable[[bytes], bool]
    #: "DF1 (DLE-framed): an SLC 500 or PLC-5?": what such bytes are, for "the bytes ... look like ..."
    wire: str
    #: "an SLC 500 or PLC-5": the controllers that speak it, for "or try --protocol X for ..."
    controllers: str
    #: "the cable, baud rate and parity (SLC 100/150: 9600 7E1)": what to check when nothing came back
    check: str


def block_lines(plan: Plan[Any, Any]) -> list[str]:
    """One line per block of a read plan (``check-config``): its scan class and label."""
    return [f"{block.scan.value:4} {block.label}" for block in plan.blocks]


@dataclass(frozen=True)
class LinkKind(Generic[C]):
    """One protocol: its config model, unit factory, plan, simulators and CLI tool.

    The protocol name is the config model's ``protocol`` Literal; the serial defaults are the
    model's :attr:`~gateway.config.link.LinkBase.serial_defaults` (one place each).
    """

    #: ``[[link]]`` of this kind (a LinkBase subclass with ``protocol: Literal["name"]``)
    config_model: type[C]
    #: the links of this kind on one line at once -> units and runners (see the module doc)
    build: Callable[[Sequence[C]], Built]
    #: the read plan of one link (``check-config`` shows it without opening a port)
    plan: Callable[[C], Plan[Any, Any]]
    #: "SLC 100/150": the controllers, for help texts
    controllers: str
    #: the plan's blocks as lines for ``check-config``
    plan_lines: Callable[[Plan[Any, Any]], list[str]] = block_lines
    #: what each point of a link's plan is in the controller (tag names, types: ``export-tags``);
    #: None: points are named by table and address
    point_labels: Callable[[C], PointLabels] | None = None
    #: the ``sim://`` models of controllers of this kind (their names: ``config_model.sim_models``)
    simulators: Sequence[SimModel] = ()
    #: the diagnostic commands (``slc-gateway probe/read/write ... --protocol name``); None: none
    tool: ToolRunner | None = None
    #: hints after a failed tool command (None: no hints)
    hints: ToolHints | None = None
    #: adds the tool's own command-line options (``--station`` ...) to a tool command's parser
    tool_options: Callable[[argparse.ArgumentParser], None] | None = None
    #: adds the kind's own options to ``slc-gateway simulate`` (its simulators' fault options)
    simulate_options: Callable[[argparse.ArgumentParser], None] | None = None
    #: examples of the items of ``slc-gateway read`` and ``write``, for help texts
    item_examples: tuple[str, str] = ("", "")
    #: the class of a link's unit (``check-config`` asks it whether the unit is polled)
    unit_class: Callable[[C], type[Unit[Any, Any]]] = lambda link: Unit
    #: (tag name, description) of the status block's kind counter, input registers 1009-1010
    #: (:attr:`gateway.unit.Unit.kind_counter`)
    status_counter: tuple[str, str] = ("kind_counter", "not used by this kind (always 0)")

    @property
    def name(self) -> str:
        return protocol_of(self.config_model)

    def is_polled(self, link: C) -> bool:
        """Whether ``link``'s unit is polled: its unit class says (:attr:`gateway.unit.Unit.POLLED`)."""
        return self.unit_class(link).POLLED

    @property
    def serial_defaults(self) -> SerialDefaults:
        return self.config_model.serial_defaults

    def links_of(self, links: Sequence[LinkBase]) -> list[C]:
        """The links of this kind among ``links``, in order."""
        return [link for link in links if isinstance(link, self.config_model)]

    def build_units(self, links: Sequence[LinkBase]) -> Built:
        return self.build(self.links_of(links))

    def plan_of(self, link: LinkBase) -> Plan[Any, Any]:
        if not isinstance(link, self.config_model):
            raise TypeError(f"link {link.name} is not a {self.name} link")
        return self.plan(link)


_TABLES = {"holding": Table.HOLDING, "input": Table.INPUT, "coil": Table.COIL, "discrete": Table.DISCRETE}


def _writable(link: LinkBase) -> list[WritableRange]:
    """The link's ``writable`` ranges, overlapping and adjacent ones merged.

    A write is checked against one range at a time, so FC16 across ``holding:40-41`` and
    ``holding:42-43`` is allowed only once they are one range ``holding:40-43``.
    """
    merged: list[list[int]] = []
    tables: list[str] = []
    for r in sorted(link.writable, key=lambda r: (r.table, r.first)):
        if merged and tables[-1] == r.table and r.first <= merged[-1][1] + 1:
            merged[-1][1] = max(merged[-1][1], r.last)
        else:
            merged.append([r.first, r.last])
            tables.append(r.table)
    return [(_TABLES[table], first, last) for table, (first, last) in zip(tables, merged, strict=True)]


def unit_options(link: LinkBase) -> UnitOptions:
    """The :class:`~gateway.unit.Unit` keyword arguments every link has (whatever its kind)."""
    return cast(UnitOptions, link.values_for(UnitOptions, unit_id=link.unit, writable=_writable(link)))


def line_options(link: LinkBase) -> LineDriverOptions:
    """The :class:`~gateway.line_driver.LineDriver` keyword arguments every link has (whatever its
    kind), for a driver that is the link's own (one controller per port)."""
    return cast(LineDriverOptions, link.values_for(LineDriverOptions))
