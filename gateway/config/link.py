"""``[[link]]``: the keys every link has, whatever its protocol, and ``writable`` ranges.

Each protocol's link model (``gateway.kinds.slc_ascii.config``, ``gateway.kinds.df1.config``) subclasses
:class:`LinkBase`: it fixes ``protocol`` to its name (the tag of the discriminated union in
``gateway.config.links``), gives its serial defaults and adds the keys only it has. Unknown keys
are refused by the model (``extra="forbid"``), so no list of "keys only for protocol X" is kept.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, ClassVar, Final, Literal, get_args

from pydantic import Field, ValidationInfo, field_validator, model_validator

from gateway.config._common import Loc, Model, Problems, array, check_port_url, optional_output_path, show
from gateway.config.writer import table_lines
from gateway.freshness import Offline
from gateway.frozen import frozen
from gateway.link_health import DEFAULT_DOWN_AFTER
from gateway.retries import DEFAULT_RETRIES
from gateway.schedule import DEFAULT_BACKGROUND_INTERVAL, DEFAULT_DEMAND_HOLD, DEFAULT_READ_WAIT, MAX_READ_WAIT
from gateway.streams import SerialSettings

__all__ = [
    "BAUDRATES",
    "DEFAULT_RETRIES",
    "LinkBase",
    "Parity",
    "SerialDefaults",
    "WritableRange",
    "WritableTable",
    "protocol_of",
]

WritableTable = Literal["holding", "coil"]
Parity = Literal["N", "E", "O"]

#: The baud rates a link may use.
BAUDRATES = (110, 300, 600, 1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200)


_NAME_RE = re.compile(r"[A-Za-z0-9_.-]{1,40}")
#: The serial keys' allowed values, and the problem (with the value given) when it is another.
_SERIAL_CHOICES: Final = {
    "baudrate": (BAUDRATES, f"{{}} is not a standard baud rate ({', '.join(map(str, BAUDRATES))})"),
    "bytesize": ((7, 8), "must be 7 or 8 (got {})"),
    "stopbits": ((1, 2), "must be 1 or 2 (got {})"),
}
_WRITABLE_RE = re.compile(r"\s*([a-z]+)\s*:\s*([0-9]{1,6})\s*(?:-\s*([0-9]{1,6})\s*)?")


@frozen
class SerialDefaults:
    """A protocol's line settings and reply timeout: the defaults of its ``[[link]]`` keys."""

    baudrate: int
    bytesize: int
    parity: Parity
    stopbits: int
    timeout: float

    @property
    def settings(self) -> SerialSettings:
        """The line settings as the drivers and simulators take them."""
        return SerialSettings(self.baudrate, self.bytesize, self.parity, self.stopbits)

    def as_keys(self) -> dict[str, object]:
        """``{"baudrate": ..., "bytesize": ..., "parity": ..., "stopbits": ..., "timeout": ...}``: the
        config keys they set."""
        return {
            "baudrate": self.baudrate,
            "bytesize": self.bytesize,
            "parity": self.parity,
            "stopbits": self.stopbits,
            "timeout": self.timeout,
        }


class WritableRange(Model):
    """One entry of ``writable``: Modbus addresses ``first..last`` (inclusive) of ``table``."""

    table: WritableTable
    first: int = Field(ge=0, le=65535)
    last: int = Field(ge=0, le=65535)

    @classmethod
    def parse(cls, text: str) -> WritableRange:
        """Parse ``"holding:0-31"`` or ``"coil:40"``; raises ``ValueError``."""
        match = _WRITABLE_RE.fullmatch(text)
        if match is None:
            raise ValueError(
                f'{show(text)}: expected "table:first-last" or "table:address", e.g. "holding:0-31"'
            )
        table, first_text, last_text = match.groups()
        if table not in ("holding", "coil"):
            raise ValueError(f"{show(text)}: the table must be holding or coil (the writable tables)")
        table_name: WritableTable = "holding" if table == "holding" else "coil"
        first = int(first_text)
        last = int(last_text) if last_text is not None else first
        if last > 65535:
            raise ValueError(f"{show(text)}: Modbus addresses are 0..65535")
        if first > last:
            raise ValueError(f"{show(text)}: the range is backwards ({first} > {last})")
        return cls(table=table_name, first=first, last=last)

    def __contains__(self, item: object) -> bool:
        """``("holding", 12) in writable_range``."""
        if not (isinstance(item, tuple) and len(item) == 2):
            return False
        table, address = item
        return bool(table == self.table and isinstance(address, int) and self.first <= address <= self.last)

    def __str__(self) -> str:
        if self.first == self.last:
            return f"{self.table}:{self.first}"
        return f"{self.table}:{self.first}-{self.last}"


class LinkBase(Model):
    """``[[link]]``: one serial link to one controller, served as one Modbus unit id.

    A subclass per protocol sets ``protocol`` to a one-value ``Literal``, :data:`serial_defaults`
    (which become the defaults of ``baudrate``, ``bytesize``, ``parity``, ``stopbits`` and
    ``timeout``), and ``sim_models``, the ``sim://`` models that speak its protocol.
    """

    #: The line settings and reply timeout the protocol's manual gives (the subclass's defaults).
    serial_defaults: ClassVar[SerialDefaults]
    #: ``sim://`` models of controllers that speak this protocol.
    sim_models: ClassVar[tuple[str, ...]] = ()
    #: Messages for keys of other protocols' links given on this one (default: "only for X links").
    foreign_key_notes: ClassVar[Mapping[str, str]] = {}
    #: The key that selects the kind's mode (df1: ``duplex``); None: the kind has one mode.
    mode_key: ClassVar[str | None] = None
    #: The keys the kind does not use, by mode (the value of ``mode_key``; None: in every mode),
    #: each with why (for the message).  Such a key given in the file is refused
    #: (:meth:`unused_key_problems`); left out, it keeps its default, which nothing reads.
    unused_keys: ClassVar[Mapping[str | None, Mapping[str, str]]] = {}

    name: str
    """Unique name of the link (1 to 40 characters from A-Z a-z 0-9 _ . -), used in logs, metrics and the status
    page."""
    protocol: str
    """The link's kind: which protocol the gateway speaks on the port (each kind's keys are listed below)."""
    port: str
    """The serial port: a device (/dev/ttyUSB0, /dev/serial/by-id/..., COM3), a serial device server
    (socket://host:port, rfc2217://host:port) or a built-in simulator (sim://MODEL?options)."""
    unit: int = Field(ge=1, le=247)
    """The Modbus unit id (1-247) that serves this controller; unique. An unknown unit id answers exception 0x0A."""
    # no defaults here: each kind's are its serial_defaults (__pydantic_init_subclass__)
    baudrate: int
    """Line speed; the default is the protocol's (below)."""
    bytesize: int
    """Data bits, 7 or 8. A port that refuses 7 data bits with even parity (a pty, some USB adapters) is opened at
    8N1 with the parity bit computed by the gateway: the same bits on the wire."""
    parity: Parity
    """"N", "E" or "O"."""
    stopbits: int
    """1 or 2."""
    timeout: float = Field(gt=0, le=60)
    """Seconds the controller may take to answer; the characters' time on the line at baudrate is added."""
    retries: int = Field(DEFAULT_RETRIES, ge=0, le=10)
    """Retries before a request fails (each kind's guide page says what a retry is on its wire); on a line shared by
    several links, the same on every link of the line."""
    stale_after: float = Field(5.0, gt=0)
    """Seconds beyond a value's scan period after which Modbus reads of it answer exception 0x0B (gateway target
    device failed to respond) rather than an old value."""
    down_after_failures: int = Field(DEFAULT_DOWN_AFTER.failures, ge=1, le=1000)
    """The link is reported down (log, status register 1000, metrics) after this many failed transactions in a row,
    not on one failure; each station of a half-duplex line by its own."""
    down_after_seconds: float = Field(DEFAULT_DOWN_AFTER.seconds, gt=0)
    """... or after this many seconds without a valid reply, whichever comes first."""
    read_only: bool = False
    """Every Modbus write answers exception 0x02."""
    writable: tuple[WritableRange, ...] = ()
    """Limits writes to these ranges, e.g. ["holding:0-31", "coil:701-720"] (others answer 0x02); adjacent ranges
    merge. Empty: every writable point."""
    fast_interval: float = Field(0.0, ge=0)
    """Scan period of the fast class, seconds (0: continuous)."""
    slow_interval: float = Field(10.0, ge=0)
    """Scan period of the slow class, seconds."""
    demand_hold: float = Field(DEFAULT_DEMAND_HOLD, gt=0, le=86400)
    """Seconds a block of the read plan stays demanded after a Modbus client (or the status page's register view) read
    any of its addresses: demanded blocks are read first (docs/guide/freshness.md)."""
    background_interval: float = Field(DEFAULT_BACKGROUND_INTERVAL, ge=0, le=86400)
    """Refresh period of the blocks nobody demands when the line cannot read every block at its class period (0: demand
    changes nothing, every block at its class period)."""
    read_wait: float = Field(DEFAULT_READ_WAIT, ge=0, le=MAX_READ_WAIT)
    """Seconds a Modbus read of data not yet read or stale, on a link that is up, may wait for an immediate read of its
    blocks before answering 0x0B (0: answer at once). Other connections never wait."""
    offline: Offline = Field(Offline.EXCEPTION, strict=False)
    """What a Modbus read of data that is not fresh (stale, or the link down) gets: "exception" answers 0x0B (the
    SCADA shows the point bad), "hold" the last value read (a SCADA that shows no quality; register 1011 says stale),
    "zero" 0 (a PLC program or HMI that must never read an old value as current). Sparkplug and the status page show
    the data stale whatever this says (docs/guide/reads-and-writes.md)."""
    write_burst: int = Field(1, ge=1, le=100)
    """Under write load: write transactions in a row before waiting polls get the line (for poll_burst transactions),
    so the data stays fresh under any write load."""
    poll_burst: int = Field(2, ge=1, le=100)
    """Poll transactions that get the line after write_burst writes."""
    write_queue_per_client: int = Field(8, ge=1, le=1000)
    """Writes of one client connection that may wait for the line; beyond, a write answers exception 0x06 (busy) and
    nothing of it is written."""
    write_queue_per_link: int = Field(32, ge=1, le=10000)
    """Writes of all clients that may wait for this link's line; beyond, exception 0x06."""
    write_timeout: float = Field(0.9, gt=0, le=600)
    """Every Modbus write is answered within this many seconds, done or not (below the 1-3 s a SCADA client waits): a
    write still waiting for the line is withdrawn (0x0B, nothing written), one already on the line answers 0x0B
    (outcome unknown) and goes on to its verdict, logged on gateway.audit."""
    trace: Path | None = None
    """A file that records every byte on the link with timestamps and direction (created 0600, rotated per
    [logging]); unset: off."""

    @classmethod
    def __pydantic_init_subclass__(cls, **kwargs: Any) -> None:
        """A kind's serial keys default to its :data:`serial_defaults` (the manual's settings)."""
        super().__pydantic_init_subclass__(**kwargs)
        defaults = cls.__dict__.get("serial_defaults")
        if defaults is None:
            return
        for key, value in defaults.as_keys().items():
            cls.model_fields[key].default = value
        cls.model_rebuild(force=True)

    def values_for(self, target: type, **given: object) -> dict[str, Any]:
        """Keyword arguments for ``target`` (a TypedDict or a dataclass): the values of this link's
        keys that ``target`` names the same way, then ``given`` (the ones it names otherwise or that
        are not taken as they are).  An option added to both is passed on without a list to update."""
        named = {name: getattr(self, name) for name in target.__annotations__ if name in type(self).model_fields}
        return {**named, **given}

    @field_validator("name")
    @classmethod
    def _check_name(cls, value: str) -> str:
        if not _NAME_RE.fullmatch(value):
            raise ValueError(f"{show(value)}: a link name is 1 to 40 characters from A-Z a-z 0-9 _ . -")
        return value

    @field_validator("port")
    @classmethod
    def _check_port(cls, value: str) -> str:
        check_port_url(value, cls.sim_models)
        return value

    @field_validator(*_SERIAL_CHOICES)
    @classmethod
    def _check_serial(cls, value: int, info: ValidationInfo) -> int:
        choices, problem = _SERIAL_CHOICES[str(info.field_name)]
        if value not in choices:
            raise ValueError(problem.format(value))
        return value

    @field_validator("writable", mode="before")
    @classmethod
    def _parse_writable(cls, value: object) -> object:
        ranges: list[WritableRange] = []
        problems: list[tuple[Loc, str]] = []
        for index, item in enumerate(array(value)):
            if isinstance(item, WritableRange):
                ranges.append(item)
            elif not isinstance(item, str):
                problems.append(((index,), f'must be a string such as "holding:0-31" (got {show(item)})'))
            else:
                try:
                    ranges.append(WritableRange.parse(item))
                except ValueError as exc:
                    problems.append(((index,), str(exc)))
        if problems:
            raise Problems(*problems)
        return tuple(ranges)

    @field_validator("trace", mode="before")
    @classmethod
    def _trace_path(cls, value: object, info: ValidationInfo) -> Path | None:
        return optional_output_path(value, info)

    @model_validator(mode="after")
    def _check_link(self) -> LinkBase:
        problems = self.unused_key_problems() + self.problems()
        if problems:
            raise Problems(*problems)
        return self

    @property
    def link_mode(self) -> str | None:
        """The value of ``mode_key`` (None: the kind has one mode)."""
        return None if self.mode_key is None else str(getattr(self, self.mode_key))

    @classmethod
    def modes(cls) -> tuple[str, ...]:
        """The modes a link of this kind can be in (the values of ``mode_key``; none: one mode)."""
        if cls.mode_key is None:
            return ()
        return tuple(str(value) for value in get_args(cls.model_fields[cls.mode_key].annotation))

    def mode_text(self) -> str:
        """The link's mode as its key sets it, for messages (``duplex = "half"``)."""
        return f"{self.mode_key} = {show(self.link_mode)}"

    def unused(self) -> dict[str, str]:
        """The keys this link's kind does not use in its mode, each with why (``unused_keys``)."""
        modes, mode = self.unused_keys, self.link_mode
        return {**modes.get(None, {}), **(modes.get(mode, {}) if mode is not None else {})}

    def unused_key_problems(self) -> list[tuple[Loc, str]]:
        """A key the kind does not use in this link's mode, given in the file: nothing would read it."""
        where = f"{self.protocol} links"
        if self.mode_key is not None:
            where += f" with {self.mode_text()}"
        return [
            ((key,), f"not used by {where} ({why})")
            for key, why in self.unused().items()
            if key in self.model_fields_set
        ]

    @classmethod
    def problems_across(cls, links: Sequence[LinkBase]) -> list[tuple[Loc, str]]:
        """Rules across the ``[[link]]`` tables of this kind (``links``: every link, in file order),
        at ``("link", index, key)``; none by default (a kind whose links share a line adds its own)."""
        return []

    def problems(self) -> list[tuple[Loc, str]]:
        """Rules across keys (after each key is valid); a subclass adds its own to these."""
        if self.read_only and self.writable:
            return [(("writable",), "a read_only link accepts no writes: drop writable or read_only")]
        return []

    @property
    def line_settings(self) -> SerialSettings:
        """The link's line settings as the drivers and simulators take them."""
        return SerialSettings(self.baudrate, self.bytesize, self.parity, self.stopbits)

    @property
    def is_simulated(self) -> bool:
        return self.port.startswith("sim://")

    def is_writable(self, table: str, address: int) -> bool:
        """Whether a Modbus write to ``table`` ``address`` passes ``read_only`` and ``writable``.

        Whether the address is mapped at all is the mapping's business, not this method's.
        """
        if self.read_only or table not in ("holding", "coil"):
            return False
        return not self.writable or any((table, address) in r for r in self.writable)

    def deadbands(self) -> dict[tuple[str, int], float]:
        """The Sparkplug deadband of each Modbus address that has one (``table``, ``address``): a change
        no larger is not published (``gateway.sparkplug``).  None here; a kind with map entries gives them."""
        return {}

    def describe_lines(self) -> list[str]:
        """This link as ``[[link]]`` TOML (the resolved-config writer's part for it), without the
        keys its kind does not use in its mode (refused if given)."""
        return table_lines("[[link]]", self, skip=self.unused())


def protocol_of(model: type[LinkBase]) -> str:
    """The protocol name of a link model: the one value of its ``protocol`` Literal."""
    (name,) = get_args(model.model_fields["protocol"].annotation)
    return str(name)
