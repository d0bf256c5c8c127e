"""Half-duplex DF1 lines from ``[[link]]`` tables: grouping and the checks across the links of a line.

Each station stays one ``[[link]]`` (its own ``unit``, ``station`` and map).  Links with the same
``port``, ``protocol = "df1"`` and ``duplex = "half"`` are the stations of one line and share one
line master (``gateway.drivers.df1_half.Df1HalfDuplexLine``).  Across the links of a line:

* the serial settings (baud rate, data bits, parity, stop bits), the checksum, the gateway's own
  address (``source``) and the line keys (delays, RTS / DTR, echo, ACK timeout, message retries,
  duplicate detection, link reset) must agree: one wire cannot have two;
* station numbers must be unique on the line.

Each problem names both links and says what to change.  Pure: no I/O.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from gateway.config._common import Loc, show
from gateway.config.df1 import Df1LinkConfig

__all__ = ["LINE_KEYS", "HalfDuplexLine", "group_lines", "line_problems"]

#: Keys every link of one line must give the same value (the wire's and the master's settings).
LINE_KEYS: tuple[str, ...] = (
    "baudrate",
    "bytesize",
    "parity",
    "stopbits",
    "checksum",
    "source",
    "pre_transmit_delay",
    "rts_send_delay",
    "rts_off_delay",
    "rts",
    "dtr",
    "echo",
    "ack_timeout",
    "message_retries",
    "duplicate_detect",
    "link_reset",
    "trace",
)


@dataclass(frozen=True, slots=True)
class HalfDuplexLine:
    """The links (stations) of one half-duplex line, in file order, with their indexes in ``[[link]]``."""

    port: str
    links: tuple[Df1LinkConfig, ...]
    indexes: tuple[int, ...]

    @property
    def first(self) -> Df1LinkConfig:
        """The link whose line keys the line uses (all agree once :func:`line_problems` is empty)."""
        return self.links[0]

    @property
    def name(self) -> str:
        """The line's name for logs: its stations' link names joined with ``+``."""
        return "+".join(link.name for link in self.links)


def _line_key(port: str) -> str:
    """Ports that name the same line: a local device is case-sensitive, a URL scheme / host is not."""
    if "://" in port:
        scheme, rest = port.split("://", 1)
        host, _, tail = rest.partition("/")
        return f"{scheme.lower()}://{host.lower()}/{tail}"
    return port.upper() if port.upper().startswith("COM") else port


def group_lines(links: Sequence[object]) -> list[HalfDuplexLine]:
    """The half-duplex lines among ``links`` (any ``[[link]]`` configs; others are skipped), in file order."""
    groups: dict[str, list[tuple[int, Df1LinkConfig]]] = {}
    for index, link in enumerate(links):
        if isinstance(link, Df1LinkConfig) and link.duplex == "half":
            groups.setdefault(_line_key(link.port), []).append((index, link))
    return [
        HalfDuplexLine(members[0][1].port, tuple(link for _, link in members), tuple(i for i, _ in members))
        for members in groups.values()
    ]


def line_problems(links: Sequence[object]) -> list[tuple[Loc, str]]:
    """Problems across the links of each half-duplex line, at ``("link", index, key)`` of the later link.

    Also a full-duplex DF1 link on the port of a half-duplex line (one port cannot be both).
    """
    problems: list[tuple[Loc, str]] = []
    lines = group_lines(links)
    for line in lines:
        first, first_index = line.links[0], line.indexes[0]
        stations: dict[int, tuple[int, Df1LinkConfig]] = {}
        for index, link in zip(line.indexes, line.links, strict=True):
            for key in LINE_KEYS:
                mine, theirs = getattr(link, key), getattr(first, key)
                if index != first_index and mine != theirs:
                    problems.append((
                        ("link", index, key),
                        f"link {show(link.name)} and link {show(first.name)} (link[{first_index}]) share the "
                        f"half-duplex line on {link.port} but give {key} = {_value(mine)} and {_value(theirs)}: "
                        f"one line has one {key}; give both the same",
                    ))
            if link.station in stations:
                other_index, other = stations[link.station]
                problems.append((
                    ("link", index, "station"),
                    f"link {show(link.name)} and link {show(other.name)} (link[{other_index}]) are both station "
                    f"{link.station} on the half-duplex line on {link.port}: each station on a line needs its "
                    "own number",
                ))
            else:
                stations[link.station] = (index, link)
            if link.station == link.source:
                problems.append((
                    ("link", index, "station"),
                    f"link {show(link.name)}: station {link.station} is the gateway's own address (source); "
                    "give the station or the source another number",
                ))
    half_ports = {_line_key(line.port): line for line in lines}
    for index, candidate in enumerate(links):
        if isinstance(candidate, Df1LinkConfig) and candidate.duplex == "full":
            shared = half_ports.get(_line_key(candidate.port))
            if shared is not None:
                problems.append((
                    ("link", index, "duplex"),
                    f"link {show(candidate.name)} is full duplex on {candidate.port}, where link "
                    f"{show(shared.first.name)} (link[{shared.indexes[0]}]) is a station of a half-duplex line: "
                    "one port is one or the other",
                ))
    return problems


def _value(value: object) -> str:
    return "unset" if value is None else show(value)
