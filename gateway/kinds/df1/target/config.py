"""``[[link.file]]`` of a DF1 link with ``role = "target"``: the data files a PLC's MSG reads and writes.

::

    [[link.file]]
    file = 7          # N7
    type = "N"        # N (16-bit integer), B (bits), F (float), L (32-bit integer)
    elements = 100
    table = "holding" # or "input", "coil" / "discrete" (B files: one coil per bit)
    start = 0         # first Modbus address; an F or L element takes two registers

Only data files a PLC can read and write as plain words are served: timers, counters, control,
string and ASCII files (T, C, R, ST, A) are the controller's own structures, and a gateway that
pretended to be one would invent their status bits.  This module checks one file alone and a
link's files together (numbers, Modbus ranges, the status block); the data table itself is
:mod:`gateway.protocols.df1.pccc.target`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

from pydantic import Field, field_validator, model_validator

from gateway.config._common import Loc, Model, Problems, show
from gateway.modbus.mapping import STATUS_BASE, STATUS_REGISTERS
from gateway.protocols.df1.pccc.target_table import TableFileKind

__all__ = ["FILE_TYPES", "TargetFile", "target_file_problems"]

#: the file types a target serves, letter -> what it is (their layout: TableFileKind, the table's own)
FILE_TYPES = {"N": "16-bit integer", "B": "16 bits", "F": "IEEE float", "L": "32-bit integer"}

#: the most elements of one file (a PLC-5 file holds up to 1000 elements; an SLC 500 file 256)
MAX_ELEMENTS = 1000


class TargetFile(Model):
    """One data file of the target's table and where Modbus sees it."""

    file: int = Field(ge=0, le=999)
    """The data file number a PLC's MSG names (7 for N7)."""
    type: str
    """N (16-bit integer), B (16 bits), F (IEEE float) or L (32-bit integer); timers, counters, control and string
    files are refused (a controller's own structures)."""
    elements: int = Field(ge=1, le=MAX_ELEMENTS)
    """Elements of the file (an SLC 500 file holds up to 256, a PLC-5 file up to 1000)."""
    table: Literal["holding", "input", "coil", "discrete"] = "holding"
    """Where Modbus sees the file: "holding" or "input"; a B file may also go to "coil" or "discrete" (16 per
    element)."""
    start: int = Field(0, ge=0, le=65535)
    """The first Modbus address; F and L elements take two registers each."""
    word_order: Literal["high-first", "low-first"] = "high-first"
    """F and L: which of an element's two registers holds the high word."""
    initial: float | int | None = None
    """The value every element has at start, before anyone writes it; unset: reads answer 0x0B until it is written
    (no invented zero)."""

    @field_validator("type")
    @classmethod
    def _check_type(cls, value: str) -> str:
        letter = value.upper()
        if letter not in FILE_TYPES:
            kinds = ", ".join(f"{k} ({what})" for k, what in FILE_TYPES.items())
            raise ValueError(f"{show(value)} is not a file type a target serves: choose {kinds}; timers, counters, "
                             "control and string files are a controller's own structures")
        return letter

    @property
    def kind(self) -> TableFileKind:
        return TableFileKind.from_letter(self.type)

    @property
    def words(self) -> int:
        """Words per element."""
        return self.kind.words

    @property
    def is_bits(self) -> bool:
        return self.table in ("coil", "discrete")

    @property
    def size(self) -> int:
        """Modbus addresses covered: registers, or bits for a coil / discrete table."""
        return self.elements * 16 if self.is_bits else self.elements * self.words

    @property
    def last(self) -> int:
        return self.start + self.size - 1

    @property
    def name(self) -> str:
        return f"{self.type}{self.file}"

    def describe(self) -> str:
        unit = "bits" if self.is_bits else "registers"
        return (f"{self.name}:0-{self.elements - 1} ({FILE_TYPES[self.type]}) -> {self.table} {self.start}-"
                f"{self.last} ({self.size} {unit})")

    @model_validator(mode="after")
    def _check(self) -> TargetFile:
        problems: list[tuple[Loc, str]] = []
        if self.is_bits and self.type != "B":
            problems.append((("table",), f"{self.name}: only a B file maps to {self.table} bits (one per bit); "
                                         "map it to holding or input registers"))
        if self.last > 65535:
            problems.append((("elements",), f"{self.name} ends at {self.table} {self.last}: past 65535; "
                                            "lower start or elements"))
        if self.initial is not None:
            problems.extend(self._initial_problems(self.initial))
        if problems:
            raise Problems(*problems)
        return self

    def _initial_problems(self, value: float | int) -> list[tuple[Loc, str]]:
        if isinstance(value, float) and self.type != "F":
            return [(("initial",), f"{self.name}: an integer file takes an integer initial value (got {value})")]
        try:
            self.kind.to_raw(value)  # the table's own rule for what an element holds
        except ValueError as exc:
            return [(("initial",), f"{self.name}: initial {value}: {exc}")]
        return []


def target_file_problems(files: Sequence[TargetFile]) -> list[tuple[Loc, str]]:
    """Rules across a target link's files, at ``("file", index, key)``."""
    problems: list[tuple[Loc, str]] = []
    if not files:
        return [(("file",), 'a link with role = "target" needs at least one [[link.file]] (file, type, elements)')]
    seen: dict[int, int] = {}
    status_last = STATUS_BASE + sum(width for _, width in STATUS_REGISTERS) - 1
    spans: list[tuple[str, int, int, int]] = []
    for index, entry in enumerate(files):
        if entry.file in seen:
            problems.append((("file", index, "file"), f"file {entry.file} is declared twice (file[{seen[entry.file]}] "
                                                      f"and file[{index}])"))
        seen.setdefault(entry.file, index)
        if entry.table == "input" and entry.start <= status_last and entry.last >= STATUS_BASE:
            status = f"input {STATUS_BASE}-{status_last}"
            problems.append((("file", index, "start"), f"{entry.name} covers input {entry.start}-{entry.last}, "
                                                       f"which overlaps the status block ({status})"))
        for table, first, last, other in spans:
            if table == entry.table and entry.start <= last and first <= entry.last:
                problems.append((("file", index, "start"), f"{entry.name} ({entry.table} {entry.start}-{entry.last}) "
                                                           f"overlaps {files[other].name} ({table} {first}-{last})"))
        spans.append((entry.table, entry.start, entry.last, index))
    return problems
