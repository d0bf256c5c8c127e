"""Modbus address <-> controller memory: the plan types, pure data, computed once per link; the table
of each function code (:data:`FUNCTION_TABLES`).

A *plan* lists the blocks the poller reads (each one controller transaction) and, for every
Modbus address of every table, the *point* that says where its value lives inside a block and
how a write to it reaches the controller.  The cache stores each block's raw bytes with the time
it was read and decodes them at once into the images of the four tables (``gateway.image``);
serving a Modbus read is a slice of an image, never controller I/O.

Generic: each link kind builds its plans (``gateway.kinds.<kind>.plan``) with its own
:class:`Codec` values and write targets; a plan is generic in its write target types
(``Plan[R, B]``: ``R`` for holding registers, ``B`` for coils).  A controller whose memory is
words has the targets ``WordWrite[A]`` and ``BitWrite[A]``, ``A`` its address type.
"""

from __future__ import annotations

import enum
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Final, Generic, TypeVar

from gateway.frozen import frozen
from gateway.modbus.mbap import FunctionCode

__all__ = [
    "FUNCTION_TABLES",
    "STATUS_BASE",
    "STATUS_REGISTERS",
    "BitPoint",
    "BitWrite",
    "Block",
    "Codec",
    "Half",
    "Plan",
    "PointLabel",
    "RegisterPoint",
    "Scan",
    "Table",
    "WordWrite",
]

#: A plan's write target types: R for a holding register, B for a coil (the link kind's own).
R = TypeVar("R")
B = TypeVar("B")
#: The address type of a word-addressed controller (``WordWrite[A]``, ``BitWrite[A]``).
A = TypeVar("A")


class Table(enum.Enum):
    HOLDING = "holding"
    INPUT = "input"
    COIL = "coil"
    DISCRETE = "discrete"

    # Members are singletons compared by identity: hashed by identity too, in C.  Enum's own
    # __hash__ (a Python call hashing the name) cost 0.25 us per read on the read path, where a
    # table keys the image's segments and the demand of each request (gateway.schedule.DemandLog).
    __hash__ = object.__hash__

    @property
    def writable(self) -> bool:
        """Whether Modbus writes this table (holding registers and coils; the other two are read-only)."""
        return self in (Table.HOLDING, Table.COIL)


#: The table each function code served reads or writes (Modbus Application Protocol V1.1b3,
#: 6.1-6.12), its one place: the backend (``gateway.modbus.backend``) serves that table, and the
#: handler's audit line of a write names it.
FUNCTION_TABLES: Final[dict[int, Table]] = {
    FunctionCode.READ_COILS: Table.COIL,
    FunctionCode.READ_DISCRETE_INPUTS: Table.DISCRETE,
    FunctionCode.READ_HOLDING_REGISTERS: Table.HOLDING,
    FunctionCode.READ_INPUT_REGISTERS: Table.INPUT,
    FunctionCode.WRITE_SINGLE_COIL: Table.COIL,
    FunctionCode.WRITE_SINGLE_REGISTER: Table.HOLDING,
    FunctionCode.WRITE_MULTIPLE_COILS: Table.COIL,
    FunctionCode.WRITE_MULTIPLE_REGISTERS: Table.HOLDING,
}


class Scan(enum.Enum):
    """Fast: read continuously.  Slow: read every ``slow_interval`` seconds (10 s by default)."""

    FAST = "fast"
    SLOW = "slow"


class Half(enum.Enum):
    """Which half of a 32-bit value a register is (the two are written together)."""

    HIGH = "high"
    LOW = "low"


@frozen
class Codec:
    """How a register's 16 bits come out of a block's bytes.

    ``msb`` and ``lsb``: where the register's high and low byte are, counted from the point's
    offset in its block (``msb`` None: the high byte is 0); ``mask``: bit 7 of the high byte is
    cleared (a flag the controller keeps there); ``half``: the register is one half of a 32-bit
    value, written with its other half in one command.  Each link kind defines its own codecs;
    the image turns them into strided copies once per plan (``gateway.image``).
    """

    name: str
    msb: int | None
    lsb: int
    mask: bool = False
    half: Half | None = None

    def __repr__(self) -> str:
        return f"Codec({self.name})"


@frozen
class Block:
    """One read transaction.  ``request`` is protocol specific (an address and count, a PCCC read)."""

    request: object
    size: int  # bytes returned
    scan: Scan
    label: str = ""


@frozen
class RegisterPoint(Generic[R]):
    block: int
    offset: int
    codec: Codec
    write: R | None = None  # the link kind's write target; None = read only
    max_value: int = 0xFFFF
    word_order_low_first: bool = False


@frozen
class BitPoint(Generic[B]):
    block: int
    offset: int
    bit: int
    write: B | None = None


# Not slotted: a slotted frozen generic dataclass cannot be made through its alias
# (``WordWrite[SlcAddress](address)``) on Python 3.11.
@dataclass(frozen=True)
class WordWrite(Generic[A]):
    """A holding register's write target: the word (or the 32-bit value) at ``address``."""

    address: A


@dataclass(frozen=True)
class BitWrite(Generic[A]):
    """A coil's write target: bit ``bit`` of the word at ``address``."""

    address: A
    bit: int


@frozen
class PointLabel:
    """What a point is in the controller, for tag lists: ``address`` in the controller's own notation
    (``N7:10``, ``901.PRE``), ``type`` (``int16``, ``uint16``, ``float32``, ``bool`` ...) and a description.

    A 32-bit value's two registers carry the same label."""

    address: str
    type: str
    description: str = ""


@dataclass
class Plan(Generic[R, B]):
    """Everything a link serves: blocks to read and the points of the four Modbus tables."""

    blocks: list[Block] = field(default_factory=list)
    holding: dict[int, RegisterPoint[R]] = field(default_factory=dict)
    input: dict[int, RegisterPoint[R]] = field(default_factory=dict)
    coils: dict[int, BitPoint[B]] = field(default_factory=dict)
    discrete: dict[int, BitPoint[B]] = field(default_factory=dict)

    def registers(self, table: Table) -> dict[int, RegisterPoint[R]]:
        return self.holding if table is Table.HOLDING else self.input

    def bits(self, table: Table) -> dict[int, BitPoint[B]]:
        return self.coils if table is Table.COIL else self.discrete

    def ranges(self, table: Table) -> list[tuple[int, int]]:
        """The mapped addresses of ``table`` as (first, last) runs."""
        points: Iterable[int] = (
            self.registers(table) if table in (Table.HOLDING, Table.INPUT) else self.bits(table)
        )
        runs: list[tuple[int, int]] = []
        for address in sorted(points):
            if runs and runs[-1][1] == address - 1:
                runs[-1] = (runs[-1][0], address)
            else:
                runs.append((address, address))
        return runs


#: The status block of every unit, input registers from 1000; 32-bit counters high word first.
STATUS_BASE = 1000
STATUS_REGISTERS = (
    ("link_up", 1),  # 1000: 1 = the controller answers, 0 = link down
    ("data_age", 1),  # 1001: age of the oldest fast-class value, 100 ms units, saturating at 65535
    ("last_fault", 1),  # 1002: last controller fault number (SLC ;T error number, PCCC STS), 0 = none
    ("transactions", 2),  # 1003-1004
    ("errors", 2),  # 1005-1006
    ("retries", 2),  # 1007-1008
    ("kind_counter", 2),  # 1009-1010: a counter the link's kind names (LinkKind.status_counter)
    ("state", 1),  # 1011: the link's state by the one verdict (gateway.freshness): 0 up, 1 stale, 2 down
)
