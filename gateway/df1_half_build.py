"""Build half-duplex DF1 lines and their station units from ``[[link]]`` configs (issue #12 wiring).

The integrator's wiring is then, in ``gateway.app``::

    lines = {index: unit for index, unit in build_half_duplex_units(config.links, common_for)}
    # and for every other df1 link: build_plc5_unit(link, common) if link.processor == "plc5"
    #                                else build_df1_unit(link, common)

plus ``line_problems(config.links)`` in the config's cross-link checks and
``gateway.config.df1.HALF_DUPLEX_SERVED = True``.  Each half-duplex link becomes a unit whose driver
is its station's :class:`~gateway.drivers.df1_half.Df1Station` on a shared
:class:`~gateway.drivers.df1_half.Df1HalfDuplexLine` (one per port; the first station's ``run()``
starts it, the last ``close()`` closes it).  A PLC-5 station gets a :class:`~gateway.plc5_unit.Plc5Unit`
(word range commands), an SLC station a :class:`~gateway.unit_df1.Df1Unit`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, cast

from gateway.config.df1 import Df1LinkConfig
from gateway.config.df1_lines import HalfDuplexLine, group_lines
from gateway.drivers.df1 import Df1Driver
from gateway.drivers.df1_half import Df1HalfDuplexLine
from gateway.modbus.mapping_df1 import MapItem
from gateway.plc5_unit import Plc5Unit
from gateway.protocols.df1.half_duplex import StationConfig
from gateway.protocols.df1.half_duplex_framing import Checksum
from gateway.protocols.df1.slave_messages import RegisterTable
from gateway.transport import SerialSettings
from gateway.unit import Unit
from gateway.unit_df1 import PROCESSORS, Df1Unit

__all__ = ["build_half_duplex_units", "build_line", "build_plc5_unit", "map_items", "station_config"]


def map_items(link: Df1LinkConfig) -> list[MapItem]:
    return [MapItem(e.table, e.start, e.address, e.count, e.type, e.word_order, e.scan) for e in link.map]


def station_config(link: Df1LinkConfig) -> StationConfig:
    """The station keys of one half-duplex link (``timeout`` is the reply timeout after the ACK)."""
    return StationConfig(
        link.station,
        poll_timeout=link.poll_timeout,
        reply_timeout=link.timeout,
        reply_wait=link.reply_wait,
        max_polls=link.max_polls,
        retries=link.demote_after,
        poll_interval=link.poll_interval,
        slow_poll_interval=link.slow_poll_interval,
    )


def build_line(line: HalfDuplexLine) -> Df1HalfDuplexLine:
    """The line master of ``line`` (its links must have passed ``line_problems``)."""
    first = line.first
    tables = {
        link.station: RegisterTable(file_number=link.receive_file, size=link.receive_words)
        for link in line.links if link.receive_words
    }
    return Df1HalfDuplexLine(
        first.port,
        [station_config(link) for link in line.links],
        name=line.name,
        settings=SerialSettings(first.baudrate, first.bytesize, first.parity, first.stopbits),
        checksum=Checksum.CRC if first.checksum == "crc" else Checksum.BCC,
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
        register_tables=tables,
        trace=first.trace,
    )


def _unit(driver: Any, link: Df1LinkConfig, common: dict[str, Any]) -> Unit:
    items = map_items(link)
    if link.processor == "plc5":
        return Plc5Unit(driver=driver, items=items, max_read_bytes=link.max_read_bytes,
                        max_write_bytes=link.max_write_bytes, **common)
    family = PROCESSORS[link.processor]
    return Df1Unit(driver=cast(Df1Driver, driver), items=items,
                   max_read_bytes=link.max_read_bytes or family.max_read_bytes,
                   max_write_bytes=link.max_write_bytes or family.max_write_bytes, **common)


def build_half_duplex_units(
    links: Sequence[object], common_for: Callable[[Df1LinkConfig], dict[str, Any]]
) -> list[tuple[int, Unit]]:
    """A unit per half-duplex link, with its index in ``links``; one line master per line."""
    units: list[tuple[int, Unit]] = []
    for line in group_lines(links):
        master = build_line(line)
        for index, link in zip(line.indexes, line.links, strict=True):
            units.append((index, _unit(master.station(link.station), link, common_for(link))))
    return units


def build_plc5_unit(link: Df1LinkConfig, common: dict[str, Any]) -> Plc5Unit:
    """A full-duplex PLC-5 link (``processor = "plc5"``): word range commands over a ``Df1Driver``."""
    family = PROCESSORS[link.processor]
    driver = Df1Driver(
        link.port,
        name=link.name,
        settings=SerialSettings(link.baudrate, link.bytesize, link.parity, link.stopbits),
        checksum=Checksum.CRC if link.checksum == "crc" else Checksum.BCC,
        station=link.station,
        source=link.source,
        family=family,
        timeout=link.timeout,
        retries=link.retries,
        trace=link.trace,
    )
    return Plc5Unit(driver=driver, items=map_items(link), max_read_bytes=link.max_read_bytes,
                    max_write_bytes=link.max_write_bytes, **common)
