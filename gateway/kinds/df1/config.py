"""``[[link]]`` with ``protocol = "df1"``: an SLC 500 / PLC-5 over DF1 full duplex, and its
``[[link.map]]`` entries.

Map addresses are checked by the parser of the link's processor: an SLC 500's by
:func:`gateway.protocols.df1.address.parse_address`, a PLC-5's (``processor = "plc5"``: ``B3/5``,
``N7:300``, octal ``I:010``) by :func:`gateway.protocols.df1.plc5_address.parse_plc5_address`; the map
rules read the file letter and whether the address names a bit from what it returns.  The entry alone
checks its keys; the link checks its addresses (only the link knows its processor).
This module is the one place that holds the protocol's serial defaults.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, ClassVar, Final, Literal, NamedTuple

from pydantic import Field, ValidationInfo, field_validator, model_validator

from gateway.config._common import Loc, Model, Problems, optional_output_path, port_key, show
from gateway.config.link import LinkBase, SerialDefaults
from gateway.config.writer import table_lines
from gateway.frozen import frozen
from gateway.kinds.df1.target.config import TargetFile, target_file_problems
from gateway.modbus.mapping import STATUS_BASE, STATUS_REGISTERS
from gateway.protocols.df1.address import parse_address
from gateway.protocols.df1.framing import DEFAULT_ACK_TIMEOUT, DEFAULT_CHECKSUM
from gateway.protocols.df1.half_duplex.events import (
    DEFAULT_MESSAGE_RESENDS,
    HALF_DUPLEX_ACK_TIMEOUT,
    StationConfig,
)
from gateway.protocols.df1.pccc.limits import MAX_DATA_BYTES
from gateway.protocols.df1.plc5_address import parse_plc5_address

__all__ = [
    "DF1_DEFAULTS",
    "LINE_KEYS",
    "Df1LinkConfig",
    "HalfDuplexLine",
    "MapEntry",
    "Processor",
    "Table",
    "ValueType",
    "classify_address",
    "group_lines",
    "line_problems",
]

Table = Literal["holding", "input", "coil", "discrete"]
ValueType = Literal["int16", "uint16", "float32", "bool"]
Processor = Literal["slc500", "slc5/01", "slc5/02", "slc5/03", "slc5/04", "slc5/05", "plc5"]

#: DF1 full duplex line settings unless a link gives its own: 19200 baud 8N1, 1 s for a reply.
DF1_DEFAULTS = SerialDefaults(baudrate=19200, bytesize=8, parity="N", stopbits=1, timeout=1.0)

_BIT_TABLES = ("coil", "discrete")
_BIT_FILES = frozenset({"B", "N", "I", "O", "S", "R"})
"""Files whose elements are words of addressable bits (SLC 500 addressing reference)."""

#: a station's defaults, the line core's own (its station keys default to them)
_STATION_DEFAULTS: Final = StationConfig(0)


class AddressKind(NamedTuple):
    letter: str
    is_bit: bool


def classify_address(text: str, processor: str = "slc5/04") -> AddressKind:
    """The file letter of an address of ``processor`` and whether it names a bit.

    Raises ``ValueError`` (an ``AddressError`` of the SLC 500 or the PLC-5 parser) saying why
    ``text`` is not an address.
    """
    if processor == "plc5":
        plc5 = parse_plc5_address(text)
        return AddressKind(plc5.file_type, plc5.bit is not None)
    address = parse_address(text)
    return AddressKind(address.file_type.letter, address.bit is not None)


def _processor_name(processor: str) -> str:
    return "PLC-5" if processor == "plc5" else "SLC 500"


class MapEntry(Model):
    """``[[link.map]]``: ``count`` values from SLC ``address`` on, at ``table`` addresses from ``start``."""

    table: Table
    """The Modbus table: "holding", "input", "coil" or "discrete"."""
    start: int = Field(ge=0, le=65535)
    """The first Modbus address (0-based protocol address)."""
    address: str
    """The first controller address, in the link's processor's addressing (SLC 500: N7:0, T4:0.ACC, B3:0/0, F8:0;
    PLC-5: N7:300, B3/5, octal I:010). Structured members step through consecutive elements, bits of word files
    through consecutive bits."""
    count: int = Field(ge=1, le=2000)
    """Values mapped (a float32 takes two registers each)."""
    type: ValueType = "int16"
    """int16 or uint16 (one register per word; the same 16 bits), float32 (F files, two registers) or bool (coil and
    discrete tables; their default)."""
    word_order: Literal["high-first", "low-first"] = "high-first"
    """float32: which register holds the high word."""
    scan: Literal["fast", "slow"] = "fast"
    """The scan class: "fast" (fast_interval) or "slow" (slow_interval)."""
    deadband: float = Field(0.0, ge=0)
    """Sparkplug: a change of the value by no more than this is not published (0: every change)."""

    @model_validator(mode="before")
    @classmethod
    def _bool_by_default_for_bits(cls, data: Any) -> Any:
        if isinstance(data, dict) and "type" not in data and data.get("table") in _BIT_TABLES:
            return {**data, "type": "bool"}
        return data

    @property
    def width(self) -> int:
        """Modbus addresses per value: 2 for float32, else 1."""
        return 2 if self.type == "float32" else 1

    @property
    def size(self) -> int:
        """Modbus addresses covered: ``count * width``."""
        return self.count * self.width

    @property
    def last(self) -> int:
        """The last Modbus address covered (inclusive)."""
        return self.start + self.size - 1

    def describe_range(self) -> str:
        return f"{self.table} {self.start}-{self.last}"

    @model_validator(mode="after")
    def _check(self) -> MapEntry:
        problems: list[tuple[Loc, str]] = []
        bit_table = self.table in _BIT_TABLES
        if bit_table and self.type != "bool":
            problems.append((("type",), f'a {self.table} table holds bits: the type must be "bool"'))
        elif not bit_table and self.type == "bool":
            problems.append(
                (("type",), f'type "bool" is for coil and discrete tables (this is a {self.table} table)')
            )
        if self.last > 65535:
            problems.append(
                (
                    ("count",),
                    f"the entry ends past Modbus address 65535: start {self.start} + count {self.count}"
                    f" x {self.width} - 1 = {self.last}",
                )
            )
        if problems:
            raise Problems(*problems)
        return self

    def address_problems(self, processor: str) -> list[tuple[Loc, str]]:
        """The address's problems on a link of ``processor`` (at ``("address",)`` or ``("type",)``)."""
        try:
            kind = classify_address(self.address, processor)
        except ValueError as exc:  # AddressError is an InvalidRequest, a ValueError
            return [(("address",), f"not a valid {_processor_name(processor)} address: {exc}")]
        return self._address_problems(kind)

    def _address_problems(self, kind: AddressKind) -> list[tuple[Loc, str]]:
        address = show(self.address)
        if self.table in _BIT_TABLES:
            if kind.letter == "F":
                return [
                    (("address",), f"{address} is a floating-point element: a {self.table} table needs bits")
                ]
            if not kind.is_bit and kind.letter not in _BIT_FILES:
                return [
                    (
                        ("address",),
                        f"{address}: a {self.table} table needs a bit address (e.g. B3:0/0 or N7:0/0) "
                        "or an element of a bit file (B, N, I, O, S, R)",
                    )
                ]
            return []
        if kind.is_bit:
            return [(("address",), f"{address} is a bit address: a {self.table} table needs a word address")]
        if self.type == "float32" and kind.letter != "F":
            return [
                (("address",), f'{address}: type "float32" needs a floating-point file address such as F8:0')
            ]
        if self.type != "float32" and kind.letter == "F":
            return [(("type",), f'{address} is a floating-point element: use type = "float32"')]
        return []


#: keys only a target uses: refused on a master link
_TARGET_ONLY: Final[Mapping[str, str]] = dict.fromkeys(
    ("file", "persist", "check_dst"),
    'a key of a link with role = "target" (the gateway answers a PLC\'s MSG instructions)',
)


class Df1LinkConfig(LinkBase):
    """``[[link]]`` of an SLC 500 or PLC-5 over DF1 full duplex, with its ``[[link.map]]``, or of a
    station on a DF1 half-duplex line (``duplex = "half"``).  Each mode refuses the keys it does not
    use (``unused_keys``)."""

    serial_defaults: ClassVar[SerialDefaults] = DF1_DEFAULTS
    sim_models: ClassVar[tuple[str, ...]] = ("slc504", "plc5", "df1line", "plc-msg")
    mode_key: ClassVar[str | None] = "duplex"
    unused_keys: ClassVar[Mapping[str | None, Mapping[str, str]]] = {
        "half": {
            **dict.fromkeys(
                ("write_burst", "poll_burst"), "the line master schedules writes; see docs/guide/df1-half-duplex.md"
            ),
            **_TARGET_ONLY,
        },
        "full": {
            **dict.fromkeys(
                ("pre_transmit_delay", "rts_send_delay", "rts_off_delay", "rts", "dtr", "echo", "duplicate_detect",
                 "link_reset"),
                "a half-duplex line key: the full-duplex driver has no turnaround, RTS / DTR keying, echo, "
                "duplicate-detect switch or link reset",
            ),
            "ack_timeout": "a half-duplex line key: the full-duplex driver waits timeout for the ACK",
            "message_retries": "a half-duplex line key: the full-duplex driver sends a frame again up to retries times",
            **dict.fromkeys(
                ("poll_timeout", "reply_wait", "max_polls", "poll_interval", "demote_after", "slow_poll_interval"),
                "a half-duplex station key: a full-duplex controller answers without being polled",
            ),
            **dict.fromkeys(
                ("receive_file", "receive_words", "receive_table", "receive_start"),
                "a half-duplex station key: on a full-duplex link the gateway takes no messages from the "
                "controller",
            ),
            **_TARGET_ONLY,
        },
        "target": {
            **dict.fromkeys(
                ("map", "processor", "source", "max_read_bytes", "max_write_bytes", "fast_interval", "slow_interval",
                 "demand_hold", "background_interval", "read_wait", "write_burst", "poll_burst", "retries", "timeout",
                 "write_queue_per_client", "write_queue_per_link",
                 "write_timeout", "down_after_failures", "down_after_seconds"),
                "the PLC sends the commands; the gateway answers from [[link.file]] and never polls",
            ),
            **dict.fromkeys(
                ("pre_transmit_delay", "rts_send_delay", "rts_off_delay", "rts", "dtr", "echo", "message_retries",
                 "link_reset", "poll_timeout", "reply_wait", "max_polls", "poll_interval", "demote_after",
                 "slow_poll_interval", "receive_file", "receive_words", "receive_table", "receive_start", "duplex"),
                "a target answers on a DF1 full-duplex link",
            ),
        },
    }

    @classmethod
    def modes(cls) -> tuple[str, ...]:
        return (*super().modes(), "target")

    @property
    def link_mode(self) -> str | None:
        """``duplex`` of a master link; ``"target"`` for a target (its keys are another set)."""
        return "target" if self.role == "target" else self.duplex

    def mode_text(self) -> str:
        return 'role = "target"' if self.role == "target" else f"duplex = {show(self.duplex)}"

    protocol: Literal["df1"]
    station: int = Field(1, ge=0, le=254)
    """Master: the controller's DF1 node (destination). Target: the gateway's own node."""
    source: int = Field(0, ge=0, le=254)
    """The gateway's own DF1 node (source) as a master; a half-duplex station's MSG writes address it."""
    checksum: Literal["bcc", "crc"] = DEFAULT_CHECKSUM.value
    """"crc" (CRC-16) or "bcc": as the controller's channel 0 is set."""
    processor: Processor = "slc5/04"
    """slc500, slc5/01 ... slc5/05 or plc5: the size limits of a command and, for plc5, PLC-5 addresses and commands
    (word range read / write, read-modify-write)."""
    max_read_bytes: int = Field(0, ge=0, le=MAX_DATA_BYTES)
    """Lower the processor's PCCC read size limit (0: the family's: SLC 500, 5/01, 5/02: 82 data bytes; 5/03,
    5/04, 5/05: 236; PLC-5, word range reads: 244). A value above the family's limit gets the family's."""
    max_write_bytes: int = Field(0, ge=0, le=MAX_DATA_BYTES)
    """Lower the processor's PCCC write size limit (0: the family's: SLC 500, 5/01, 5/02: 82; 5/03, 5/04, 5/05:
    228; PLC-5, word range writes: 239 with the address). A value above the family's limit gets the family's."""
    map: tuple[MapEntry, ...] = Field((), strict=False)
    """[[link.map]]: the controller addresses a master link polls and where Modbus sees them (required for a master)."""

    # --- half duplex (docs/develop/df1-half-duplex-line.md) ---------------------------------------------
    duplex: Literal["full", "half"] = "full"
    """"full": point to point; "half": a station on a multi-drop line or radio channel, polled by the gateway. Links
    with the same port and duplex = "half" are the stations of one line and share one line master."""
    # Line keys: every link of one line must give the same values (gateway.kinds.df1.config).
    pre_transmit_delay: float = Field(0.0, ge=0, le=10)
    """Line key: quiet time after the last byte heard before the master transmits (2-wire turnaround, the remote
    radio's turnaround)."""
    rts_send_delay: float = Field(0.0, ge=0, le=10)
    """Line key: RTS on -> first byte (a radio's key-up time, often 20-100 ms; 1747-RM001 p. 13-59)."""
    rts_off_delay: float = Field(0.0, ge=0, le=10)
    """Line key: last byte -> RTS off."""
    rts: Literal["toggle", "rs485", "on", "off"] = "toggle"
    """Line key: "toggle" (the gateway keys RTS around each transmission), "rs485" (the kernel's RS-485 mode), "on"
    or "off" (held). A socket:// device server has no modem lines: set it to key RTS itself."""
    dtr: bool = True
    """Line key: DTR on while the port is open."""
    echo: bool = False
    """Line key: 2-wire RS-485 where the gateway hears its own bytes: they are stripped, and a byte that comes back
    different is counted as a collision."""
    ack_timeout: float = Field(HALF_DUPLEX_ACK_TIMEOUT, gt=0, le=60)
    """Line key: wait for the DLE ACK of a master message: 0.5 s by default, sized to a wired line (1747-RM001G
    p. 13-61: a message and the slave's turnaround; the SLC channel's 1.0 s allows for modems). On a target, the
    wait for the PLC's DLE ACK of a reply: not given, 1.0 s (the SLC 500 channel's ACK Timeout, 50 x 20 ms,
    p. 13-52)."""
    message_retries: int = Field(DEFAULT_MESSAGE_RESENDS, ge=0, le=10)
    """Line key: identical resends of a message without its DLE ACK."""
    duplicate_detect: bool = True
    """Line key: the slaves detect duplicate messages (1747-RM001 "Duplicate Packet Detect", on by default in the
    SLC's channel 0); false: a frame is never resent. On a target: a frame repeated after a lost ACK is
    acknowledged, never run twice."""
    link_reset: bool = True
    """Line key: DLE NAK (global link reset) when the line starts, as a master does at power-up (Table 2.C); it
    empties the slaves' queued messages."""
    # Station keys (this link's station): the reply ``timeout`` above is from the ACK to the reply.
    poll_timeout: float = Field(_STATION_DEFAULTS.poll_timeout, gt=0, le=60)
    """Station key: wait for the answer to a poll (a message or DLE EOT)."""
    reply_wait: float = Field(_STATION_DEFAULTS.reply_wait, ge=0, le=60)
    """Station key: after the ACK of a command, and after each DLE EOT the station answers while its reply is not
    ready, before the next poll for the reply (1747-RM001 p. 13-67, "Reply Message Wait Time"). While a write
    waits for its reply the line stays free for that poll."""
    max_polls: int = Field(_STATION_DEFAULTS.max_polls, ge=1, le=1000)
    """Station key: DLE EOT answers tolerated while waiting for one reply."""
    poll_interval: float = Field(_STATION_DEFAULTS.poll_interval, gt=0, le=3600)
    """Station key: background poll period for the station's own messages (report by exception)."""
    demote_after: int = Field(_STATION_DEFAULTS.demote_after, ge=1, le=100)
    """Station key: answerless polls or unacknowledged messages in a row before the station is demoted: its unit
    answers 0x0B at once and it is polled every slow_poll_interval."""
    slow_poll_interval: float = Field(_STATION_DEFAULTS.slow_poll_interval, gt=0, le=3600)
    """Station key: poll period of a demoted station."""
    receive_file: int = Field(7, ge=0, le=999)
    """Station key: the station's MSG writes of N<receive_file>:0 onwards are stored (others get STS 10)."""
    receive_words: int = Field(0, ge=0, le=10000)
    """Station key: words of N<receive_file> the station may write to the gateway (0: none)."""
    receive_table: Literal["input", "holding"] = "input"
    """Station key: where the unit serves those words, read-only: "input" or "holding"; word i at receive_start + i,
    its age (0.1 s, 65535: never written) at receive_start + receive_words + i."""
    receive_start: int = Field(0, ge=0, le=65535)
    """Station key: the Modbus address of word 0 of the receive range."""

    # --- target mode (docs/guide/target-mode.md; gateway.kinds.df1.target.config) -------------
    role: Literal["master", "target"] = "master"
    """"master": the gateway polls the controller; "target": the gateway is the station a PLC's MSG instructions read
    and write (station is then the gateway's own node), answering from [[link.file]]."""
    file: tuple[TargetFile, ...] = Field((), strict=False)
    """[[link.file]]: the data files of a target and where Modbus sees them."""
    persist: Path | None = None
    """Target: a SQLite file; every PLC write is committed before its reply goes out and every Modbus write before
    its answer, so the table survives a restart (even kill -9)."""
    check_dst: bool = False
    """Target: answer only frames whose DST is station (full duplex ignores DST by default)."""

    @model_validator(mode="before")
    @classmethod
    def _ack_timeout_of_the_mode(cls, data: Any) -> Any:
        """``ack_timeout`` not given on a target: the SLC channel's (the key's doc), not a line master's."""
        if isinstance(data, dict) and "ack_timeout" not in data and data.get("role") == "target":
            return {**data, "ack_timeout": DEFAULT_ACK_TIMEOUT}
        return data

    @field_validator("persist", mode="before")
    @classmethod
    def _persist_path(cls, value: object, info: ValidationInfo) -> Path | None:
        return optional_output_path(value, info)

    @field_validator("map", mode="after")
    @classmethod
    def _check_addresses(cls, entries: tuple[MapEntry, ...], info: ValidationInfo) -> tuple[MapEntry, ...]:
        """Each entry's address by the parser of this link's processor (skipped when ``processor``
        itself is invalid: that error is reported)."""
        processor = info.data.get("processor")
        if processor is None:
            return entries
        problems = [
            ((index, *loc), message)
            for index, entry in enumerate(entries)
            for loc, message in entry.address_problems(processor)
        ]
        if problems:
            raise Problems(*problems)
        return entries

    def deadbands(self) -> dict[tuple[str, int], float]:
        return {(entry.table, address): entry.deadband for entry in self.map if entry.deadband
                for address in range(entry.start, entry.last + 1)}

    def problems(self) -> list[tuple[Loc, str]]:
        problems = super().problems()
        if self.role == "target":
            return problems + target_file_problems(self.file)
        if not self.map:
            problems.insert(0, (("map",), "a df1 link needs at least one [[link.map]] entry"))
        problems.extend(_overlaps(self.map))
        problems.extend(self._receive_problems())
        if self.duplex == "half" and self.reply_wait >= self.timeout:
            problems.append((("reply_wait",), f"reply_wait {self.reply_wait:g} s is not shorter than timeout "
                             f"{self.timeout:g} s: both count from the ACK of a command, so the reply would "
                             "first be polled for after its timeout; make reply_wait shorter than timeout"))
        return problems

    @property
    def receive_last(self) -> int:
        """The last Modbus address of the receive range: ``receive_words`` words, then as many ages."""
        return self.receive_start + 2 * self.receive_words - 1

    def _receive_problems(self) -> list[tuple[Loc, str]]:
        """The receive range (``receive_words`` words then their ages, from ``receive_start`` in
        ``receive_table``): below 65536, clear of the map and the status block (half duplex only: a
        full-duplex link refuses the keys, ``unused_keys``)."""
        if not self.receive_words or self.duplex != "half":
            return []
        start = self.receive_start
        table, last = self.receive_table, self.receive_last
        what = f"the receive range ({table} {start}-{last}: {self.receive_words} words, then their ages)"
        if last > 65535:
            return [(("receive_start",), f"{what} ends past Modbus address 65535: start {start} + 2 x "
                     f"receive_words {self.receive_words} - 1 = {last}")]
        problems: list[tuple[Loc, str]] = []
        for index, entry in enumerate(self.map):
            if entry.table == table and entry.start <= last and start <= entry.last:
                problems.append((("receive_start",), f"{what} overlaps map[{index}] ({entry.describe_range()}): "
                                 "move receive_start (or use the other receive_table)"))
        status_last = STATUS_BASE + sum(width for _, width in STATUS_REGISTERS) - 1
        if table == "input" and start <= status_last and STATUS_BASE <= last:
            problems.append((("receive_start",), f"{what} overlaps the unit's status block (input {STATUS_BASE}-"
                             f"{status_last}): move it, or use receive_table = \"holding\""))
        return problems

    @classmethod
    def problems_across(cls, links: Sequence[LinkBase]) -> list[tuple[Loc, str]]:
        """The links of each half-duplex line agree on the line; stations are unique on it."""
        return line_problems(links)

    def describe_lines(self) -> list[str]:
        unused = set(self.unused())
        if self.role == "target" and "stale_after" not in self.model_fields_set:
            unused.add("stale_after")
        lines = table_lines("[[link]]", self, skip=("map", "file", *sorted(unused)))
        if "stale_after" in unused:
            lines.insert(-1, "# stale_after not set: a target's values do not go stale when the PLC is silent")
        for entry in self.map:
            lines += table_lines("[[link.map]]", entry, indent="  ")
        for target_file in self.file:
            lines += table_lines("[[link.file]]", target_file, indent="  ")
        return lines


def _overlaps(entries: Sequence[MapEntry]) -> list[tuple[Loc, str]]:
    problems: list[tuple[Loc, str]] = []
    for later in range(len(entries)):
        b = entries[later]
        for earlier in range(later):
            a = entries[earlier]
            if a.table != b.table or a.last < b.start or b.last < a.start:
                continue
            low, high = max(a.start, b.start), min(a.last, b.last)
            where = f"{low}-{high}" if low != high else f"{low}"
            problems.append(
                (
                    ("map", later),
                    f"{b.describe_range()} overlaps map[{earlier}] ({a.describe_range()}) "
                    f"at {b.table} {where}",
                )
            )
            break
    return problems


# --- half-duplex lines ------------------------------------------------------------------------
#
# Half-duplex DF1 lines from ``[[link]]`` tables: grouping and the checks across the links of a line.
#
# Each station stays one ``[[link]]`` (its own ``unit``, ``station`` and map).  Links with the same
# ``port``, ``protocol = "df1"`` and ``duplex = "half"`` are the stations of one line and share one
# line master (``gateway.kinds.df1.half.driver.Df1HalfDuplexLine``).  Across the links of a line:
#
# * the serial settings (baud rate, data bits, parity, stop bits), the checksum, the gateway's own
#   address (``source``) and the line keys (delays, RTS / DTR, echo, ACK timeout, message retries,
#   ``retries`` (the line's one transaction layer retries every station's reads), duplicate
#   detection, link reset, trace) must agree: one wire cannot have two;
# * station numbers must be unique on the line.
#
# Each problem names both links and says what to change.  Pure: no I/O.

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
    "retries",
    "duplicate_detect",
    "link_reset",
    "trace",
)


@frozen
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


def group_lines(links: Sequence[object]) -> list[HalfDuplexLine]:
    """The half-duplex lines among ``links`` (any ``[[link]]`` configs; others are skipped), in file order."""
    groups: dict[str, list[tuple[int, Df1LinkConfig]]] = {}
    for index, link in enumerate(links):
        if isinstance(link, Df1LinkConfig) and link.duplex == "half":
            groups.setdefault(port_key(link.port), []).append((index, link))
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
    half_ports = {port_key(line.port): line for line in lines}
    for index, candidate in enumerate(links):
        if isinstance(candidate, Df1LinkConfig) and candidate.duplex == "full":
            shared = half_ports.get(port_key(candidate.port))
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
