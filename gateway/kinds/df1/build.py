"""Every DF1 ``[[link]]`` as a unit, and the runners of their lines (the DF1 kind's ``build``).

* A full-duplex link (``duplex = "full"``, the default) gets its own
  :class:`~gateway.kinds.df1.full.driver.Df1Driver`: one controller per port, the driver is the runner.
* Links with the same ``port`` and ``duplex = "half"`` are the stations of one multi-drop line
  (``gateway.kinds.df1.config.group_lines``): one :class:`~gateway.kinds.df1.half.driver.Df1HalfDuplexLine`
  master per line is the runner, and each link's unit talks through its station's handle
  (``line.station(n)``, the same ``execute`` API as the full-duplex driver).

Whatever the line, ``processor = "plc5"`` gets a :class:`~gateway.kinds.df1.plc5_unit.Plc5Unit` (word
range commands, PLC-5 addresses), every SLC 500 processor a :class:`~gateway.kinds.df1.unit.Df1Unit`
(typed logical commands).  A station with ``receive_words`` serves its register table (the words it
sends with MSG instructions, and their ages) from ``receive_start`` (``gateway.kinds.df1.half.receive``).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from gateway.kinds.contract import Built, LinkRunner, PointLabels, line_options, unit_options
from gateway.kinds.df1.config import Df1LinkConfig, HalfDuplexLine, group_lines
from gateway.kinds.df1.full.driver import Df1Driver
from gateway.kinds.df1.half.driver import Df1HalfDuplexLine
from gateway.kinds.df1.half.receive import ReceiveWindow
from gateway.kinds.df1.plan import MapItem, point_labels_df1, shared_plan_df1
from gateway.kinds.df1.plc5_unit import Plc5Unit, point_labels_plc5, shared_plan_plc5
from gateway.kinds.df1.target.build import build_target, target_link_labels, target_link_plan
from gateway.kinds.df1.target.unit import TargetUnit
from gateway.kinds.df1.unit import PROCESSORS, Df1Unit, PcccDriver, PcccUnit
from gateway.link_health import DownAfter
from gateway.modbus.mapping import Plan, Table
from gateway.poller import LineShare
from gateway.protocols.df1.framing import Checksum
from gateway.protocols.df1.half_duplex.events import StationConfig
from gateway.protocols.df1.half_duplex.slave_messages import RegisterTable
from gateway.protocols.df1.pccc import ProcessorFamily
from gateway.protocols.df1.pccc.limits import PLC5_WORD_RANGE, SizeLimits
from gateway.protocols.df1.pccc.target_table import ElementRef
from gateway.unit import Unit

__all__ = [
    "build_df1",
    "build_line",
    "df1_plan",
    "df1_plan_lines",
    "df1_point_labels",
    "map_items",
    "station_config",
    "station_unit",
]


def map_items(link: Df1LinkConfig) -> list[MapItem]:
    return [MapItem(e.table, e.start, e.address, e.count, e.type, e.word_order, e.scan) for e in link.map]


def _is_plc5(link: Df1LinkConfig) -> bool:
    return PROCESSORS[link.processor] is ProcessorFamily.PLC5


def size_limits(link: Df1LinkConfig) -> SizeLimits:
    """The data bytes of a master link's packets: its family's limits (a PLC-5 is polled with word range
    commands), lowered by ``max_read_bytes`` / ``max_write_bytes``, never raised above them."""
    family = PLC5_WORD_RANGE if _is_plc5(link) else PROCESSORS[link.processor].limits
    return family.lowered(link.max_read_bytes, link.max_write_bytes)


def df1_unit_class(link: Df1LinkConfig) -> type[Unit[Any, Any]]:
    """The class of a link's unit: a target's files, a PLC-5 or an SLC 500 polled over DF1."""
    if link.role == "target":
        return TargetUnit
    return Plc5Unit if _is_plc5(link) else Df1Unit


def df1_plan(link: Df1LinkConfig) -> Plan[Any, Any]:
    """The read plan of a DF1 link (shared by links with the same map): PLC-5 or SLC 500 addresses;
    a target's files."""
    if link.role == "target":
        return target_link_plan(link)
    if _is_plc5(link):
        return shared_plan_plc5(map_items(link), size_limits(link).max_read_bytes)
    return shared_plan_df1(map_items(link), size_limits(link).max_read_bytes)


def df1_plan_lines(plan: Plan[Any, Any]) -> list[str]:
    """``check-config``'s lines for a plan: a read plan's blocks, or a target's files (one block per
    element, listed as one line per file)."""
    lines: list[str] = []
    files: dict[int, list[Any]] = {}
    for block in plan.blocks:
        if isinstance(block.request, ElementRef):
            files.setdefault(block.request.file, []).append(block)
        else:
            lines.append(f"{block.scan.value:4} {block.label}")
    for blocks in files.values():
        first, last = blocks[0].label, blocks[-1].label.rpartition(":")[2]
        lines.append(f"file {first}-{last}: {len(blocks)} elements, each with its own time of last write")
    return lines


def df1_point_labels(link: Df1LinkConfig) -> PointLabels:
    """What each point of :func:`df1_plan` is in the controller (PLC-5 or SLC 500 addresses)."""
    if link.role == "target":
        return target_link_labels(link)
    return point_labels_plc5(map_items(link)) if _is_plc5(link) else point_labels_df1(map_items(link))


def station_unit(driver: PcccDriver, link: Df1LinkConfig, share: LineShare | None = None) -> PcccUnit[Any, Any]:
    """The unit of one link over ``driver`` (its own full-duplex driver, or its station on a line whose
    pollers share ``share``)."""
    items = map_items(link)
    options = unit_options(link)
    options["line_share"] = share
    limits = size_limits(link)
    if _is_plc5(link):
        return Plc5Unit(driver=driver, items=items, max_read_bytes=limits.max_read_bytes,
                        max_write_bytes=limits.max_write_bytes, **options)
    return Df1Unit(driver=driver, items=items, max_read_bytes=limits.max_read_bytes,
                   max_write_bytes=limits.max_write_bytes, family=PROCESSORS[link.processor], **options)


def _checksum(link: Df1LinkConfig) -> Checksum:
    return Checksum.CRC if link.checksum == "crc" else Checksum.BCC


def full_duplex_driver(link: Df1LinkConfig) -> Df1Driver:
    """The driver of one full-duplex link (one controller per port)."""
    return Df1Driver(
        link.port,
        settings=link.line_settings,
        checksum=_checksum(link),
        station=link.station,
        source=link.source,
        family=PROCESSORS[link.processor],
        timeout=link.timeout,
        retries=link.retries,
        **line_options(link),
    )


def station_config(link: Df1LinkConfig) -> StationConfig:
    """The station keys of one half-duplex link (``timeout`` is the reply timeout after the ACK)."""
    return StationConfig(**link.values_for(StationConfig, reply_timeout=link.timeout))


def build_line(line: HalfDuplexLine) -> Df1HalfDuplexLine:
    """The line master of ``line`` (its links passed ``line_problems``: they agree on the line keys,
    ``LINE_KEYS``, so the first link's are the line's); each station goes down by its own link's
    ``down_after_failures`` / ``down_after_seconds``."""
    first = line.first
    tables = {
        link.station: RegisterTable(file_number=link.receive_file, size=link.receive_words)
        for link in line.links if link.receive_words
    }
    return Df1HalfDuplexLine(
        first.port,
        [station_config(link) for link in line.links],
        name=line.name,
        settings=first.line_settings,
        checksum=_checksum(first),
        source=first.source,
        ack_timeout=first.ack_timeout,
        message_retries=first.message_retries,
        retries=first.retries,
        pre_transmit_delay=first.pre_transmit_delay,
        rts_send_delay=first.rts_send_delay,
        rts_off_delay=first.rts_off_delay,
        rts_mode=first.rts,
        dtr=first.dtr,
        echo=first.echo,
        duplicate_detect=first.duplicate_detect,
        link_reset=first.link_reset,
        station_names={link.station: link.name for link in line.links},
        down_after={link.station: DownAfter(link.down_after_failures, link.down_after_seconds) for link in line.links},
        register_tables=tables,
        trace=first.trace,
    )


def build_df1(links: Sequence[Df1LinkConfig]) -> Built:
    """Every DF1 link's unit, in ``links`` order; runners: each full-duplex driver, each line master,
    each target's runner."""
    units: dict[int, Unit[Any, Any]] = {}
    runners: list[LinkRunner] = []
    for index, link in enumerate(links):
        if link.role == "target":
            target = units[index] = build_target(link)
            runners.append(target.driver)
    for line in group_lines(links):
        master = build_line(line)
        runners.append(master)
        share = LineShare()  # one station's background waits while another's demanded blocks are read
        for index, link in zip(line.indexes, line.links, strict=True):
            unit = units[index] = station_unit(master.station(link.station), link, share)
            table = master.register_tables.get(link.station)
            if table is not None:
                unit.receive = ReceiveWindow(Table(link.receive_table), link.receive_start, table)
    for index, link in enumerate(links):
        if index not in units:
            driver = full_duplex_driver(link)
            runners.append(driver)
            units[index] = station_unit(driver, link)
    return Built([units[index] for index in range(len(links))], runners)
