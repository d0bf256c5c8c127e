"""Modbus address <-> controller memory: pure data, computed once per link.

A *plan* lists the blocks the poller reads (each one controller transaction) and, for every
Modbus address of every table, the *point* that says where its value lives inside a block and
how a write to it reaches the controller.  The cache stores each block's raw bytes with the time
it was read and decodes them at once into the images of the four tables (``gateway.image``);
serving a Modbus read is a slice of an image, never controller I/O.

Default map of an SLC 100/150 (``slc_ascii_plan``), Modbus protocol addresses (0-based):

=================  ============  ======================================================  ========
table              address       content                                                 writable
=================  ============  ======================================================  ========
holding register   0-31          accumulators of 901-932 (word at byte 2n, MSB first)     0-9999
holding register   32-63         presets of 901-932 (protect bit masked)                 0-9999
coil               701-868       internal relays                                         701-820
discrete input     1-610         inputs (user bit addresses, incl. 9, 10, 109 ... 610)
discrete input     11-618        outputs
discrete input     701-876       relays, fine timer bits, AUTO/MAN
discrete input     901-932       timer/counter/sequencer outputs
discrete input     951-982       timer/counter/sequencer overflow
input register     0-31          sequencer step counters of 901-932
input register     66            error bits 84H (high byte) and 85H (low byte)
input register     67-74         force select table 86H-95H (word at byte 2n)
input register     129-136       force state table 102H-111H (word at byte 2n)
input register     1000-1010     status block (see ``STATUS_REGISTERS``), always served
=================  ============  ======================================================  ========
"""

from __future__ import annotations

import enum
import functools
from collections.abc import Iterable
from dataclasses import dataclass, field

from gateway.protocols.slc_ascii import memory_map as mm

__all__ = [
    "STATUS_BASE",
    "STATUS_REGISTERS",
    "BitPoint",
    "Block",
    "Codec",
    "Plan",
    "RegisterPoint",
    "Scan",
    "SlcBitWrite",
    "SlcWordWrite",
    "Table",
    "plan_byte_blocks",
    "slc_ascii_plan",
]


class Table(enum.Enum):
    HOLDING = "holding"
    INPUT = "input"
    COIL = "coil"
    DISCRETE = "discrete"


class Scan(enum.Enum):
    """Fast: read continuously.  Slow: read every ``slow_interval`` seconds (10 s by default)."""

    FAST = "fast"
    SLOW = "slow"


class Codec(enum.Enum):
    """How a register's 16 bits come out of a block's bytes."""

    U16_BE = "u16be"  # SLC 100/150 word, MSB first
    U16_BE_MASKED = "u16be-masked"  # SLC 100/150 preset/accumulator: protect bit (bit 15) masked
    U8 = "u8"  # one byte (step counters)
    U16_LE = "u16le"  # PCCC word (little-endian); int16 is the same bits
    F32_HIGH = "f32-high"  # high word of a PCCC float (4 bytes little-endian)
    F32_LOW = "f32-low"  # low word of a PCCC float


@dataclass(frozen=True, slots=True)
class Block:
    """One read transaction.  ``request`` is protocol specific (an address and count, a PCCC read)."""

    request: object
    size: int  # bytes returned
    scan: Scan
    label: str = ""


@dataclass(frozen=True, slots=True)
class SlcWordWrite:
    """SLC 100/150 holding register write: write-word command at ``address``."""

    address: int


@dataclass(frozen=True, slots=True)
class SlcBitWrite:
    """SLC 100/150 coil write: read the relay byte fresh, write it back with ``bit`` changed."""

    address: int
    bit: int


@dataclass(frozen=True, slots=True)
class RegisterPoint:
    block: int
    offset: int
    codec: Codec
    write: object | None = None  # protocol-specific write target; None = read only
    max_value: int = 0xFFFF
    word_order_low_first: bool = False


@dataclass(frozen=True, slots=True)
class BitPoint:
    block: int
    offset: int
    bit: int
    write: object | None = None


@dataclass
class Plan:
    """Everything a link serves: blocks to read and the points of the four Modbus tables."""

    blocks: list[Block] = field(default_factory=list)
    holding: dict[int, RegisterPoint] = field(default_factory=dict)
    input: dict[int, RegisterPoint] = field(default_factory=dict)
    coils: dict[int, BitPoint] = field(default_factory=dict)
    discrete: dict[int, BitPoint] = field(default_factory=dict)

    def registers(self, table: Table) -> dict[int, RegisterPoint]:
        return self.holding if table is Table.HOLDING else self.input

    def bits(self, table: Table) -> dict[int, BitPoint]:
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
    ("id_resyncs", 2),  # 1009-1010
)


def plan_byte_blocks(addresses: Iterable[int], scan: Scan, max_count: int = 2) -> list[tuple[int, int, Scan]]:
    """Cover byte ``addresses`` with the fewest reads of at most ``max_count`` readable bytes.

    Left-to-right greedy, which is optimal for covering points on a line with segments of a
    fixed maximum length.  Never reads a byte that is not readable (``**`` cells).
    """
    blocks: list[tuple[int, int, Scan]] = []
    pending = sorted(set(addresses))
    i = 0
    while i < len(pending):
        start = pending[i]
        count = 1
        while count < max_count and i + count < len(pending) and pending[i + count] == start + count:
            count += 1
        if not mm.is_readable(start, count):
            count = 1
        if not mm.is_readable(start, 1):
            # 0x3F / 0x7F: the last byte of a word table is readable only as the second of two
            blocks.append((start - 1, 2, scan))
        else:
            blocks.append((start, count, scan))
        i += count
    return blocks


@functools.cache
def slc_ascii_plan() -> Plan:
    """The default map of an SLC 100/150 (module docstring).

    Built once and shared by every SLC 100/150 link (a plan is never changed once built), so
    that 64 links hold one plan and one image layout (``gateway.image``), not 64.
    """
    plan = Plan()
    fast: set[int] = set()
    slow: set[int] = set()
    fast.update(range(0x00, 0x40))  # accumulators
    slow.update(range(0x40, 0x80))  # presets
    fast.update(range(0x96, 0xBC))  # outputs, inputs, relays, fine timer bits
    fast.update(range(0xDC, 0xE4))  # timer/counter/sequencer outputs and overflow
    slow.update(range(0xBC, 0xDC))  # step counters
    slow.update(range(0x84, 0x96))  # error bits, force select table
    slow.update(range(0x102, 0x112))  # force state table
    where: dict[int, tuple[int, int]] = {}  # byte address -> (block, offset)
    for scan, addresses in ((Scan.FAST, fast), (Scan.SLOW, slow)):
        for start, count, _ in plan_byte_blocks(addresses, scan):
            index = len(plan.blocks)
            plan.blocks.append(Block((start, count), count, scan, f"{count} byte(s) at 0x{start:04X}"))
            for k in range(count):
                where.setdefault(start + k, (index, k))

    def word(address: int, codec: Codec, write: object | None = None, max_value: int = 0xFFFF) -> RegisterPoint:
        block, offset = where[address]
        if offset + 2 > plan.blocks[block].size:
            raise AssertionError(f"word at 0x{address:04X} split across blocks")
        return RegisterPoint(block, offset, codec, write, max_value)

    for n in range(32):
        plan.holding[n] = word(2 * n, Codec.U16_BE_MASKED, SlcWordWrite(2 * n), 9999)
        plan.holding[32 + n] = word(0x40 + 2 * n, Codec.U16_BE_MASKED, SlcWordWrite(0x40 + 2 * n), 9999)
        block, offset = where[0xBC + n]
        plan.input[n] = RegisterPoint(block, offset, Codec.U8)
    plan.input[0x84 // 2] = word(0x84, Codec.U16_BE)
    for address in range(0x86, 0x96, 2):
        plan.input[address // 2] = word(address, Codec.U16_BE)
    for address in range(0x102, 0x112, 2):
        plan.input[address // 2] = word(address, Codec.U16_BE)
    for user in mm.all_user_bits():
        byte, bit = mm.user_bit_to_byte(user)
        block, offset = where[byte]
        plan.discrete[user] = BitPoint(block, offset, bit)
        if 701 <= user <= 868:
            writable = SlcBitWrite(byte, bit) if mm.is_writable_user_bit(user) else None
            plan.coils[user] = BitPoint(block, offset, bit, writable)
    return plan
