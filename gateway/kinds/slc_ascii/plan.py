"""The SLC 100/150 read plan: the fixed default map, its codecs and write targets.  Pure: no I/O.

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
input register     1000-1011     status block (see ``STATUS_REGISTERS``), always served
=================  ============  ======================================================  ========
"""

from __future__ import annotations

import functools
from collections.abc import Iterable
from typing import Any, TypeAlias

from gateway.modbus import mapping
from gateway.modbus.mapping import Codec, PointLabel, Scan, Table
from gateway.protocols.slc_ascii import memory_map as mm

__all__ = [
    "U8",
    "U16_BE",
    "U16_BE_MASKED",
    "SlcAsciiPlan",
    "SlcBitWrite",
    "SlcWordWrite",
    "byte_read",
    "plan_byte_blocks",
    "plan_lines",
    "point_labels",
    "slc_ascii_plan",
]

#: An SLC 100/150 word, MSB first.
U16_BE = Codec("u16be", 0, 1)
#: A preset or accumulator: MSB first, the protect bit (bit 15) masked.
U16_BE_MASKED = Codec("u16be-masked", 0, 1, mask=True)
#: One byte (the step counters).
U8 = Codec("u8", None, 0)


#: SLC 100/150 holding register write: write-word command at ``address``
SlcWordWrite: TypeAlias = mapping.WordWrite[int]
#: SLC 100/150 coil write: read the relay byte fresh, write it back with ``bit`` changed
SlcBitWrite: TypeAlias = mapping.BitWrite[int]


#: The plan of an SLC 100/150 link: word writes to holding registers, bit writes to coils.
SlcAsciiPlan: TypeAlias = mapping.Plan[SlcWordWrite, SlcBitWrite]


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


#: The rows of the memory map read every fast period (what the program changes every scan) and
#: every slow period (what changes by a write or a mode change).
_FAST_REGIONS: tuple[mm.Region, ...] = (
    mm.ACCUMULATORS, mm.OUTPUT_STATE, mm.INPUT_STATE, mm.INTERNAL_RELAYS, mm.FINE_TIMER_BITS,
    mm.TCS_OUTPUT_BITS, mm.TCS_OVERFLOW_BITS,
)
_SLOW_REGIONS: tuple[mm.Region, ...] = (
    mm.PRESETS, mm.STEP_COUNTERS, mm.ERROR_BITS_REGION, mm.FORCE_SELECT, mm.FORCE_STATE,
)


def _addresses(region: mm.Region) -> range:
    return range(region.start, region.end + 1)


@functools.cache
def slc_ascii_plan() -> SlcAsciiPlan:
    """The default map of an SLC 100/150 (module docstring).

    Built once and shared by every SLC 100/150 link (a plan is never changed once built), so
    that 64 links hold one plan and one image layout (``gateway.image``), not 64.
    """
    plan: SlcAsciiPlan = mapping.Plan()
    fast = {address for region in _FAST_REGIONS for address in _addresses(region)}
    slow = {address for region in _SLOW_REGIONS for address in _addresses(region)}
    where: dict[int, tuple[int, int]] = {}  # byte address -> (block, offset)
    for scan, addresses in ((Scan.FAST, fast), (Scan.SLOW, slow)):
        for start, count, _ in plan_byte_blocks(addresses, scan):
            index = len(plan.blocks)
            plan.blocks.append(mapping.Block((start, count), count, scan, f"{count} byte(s) at 0x{start:04X}"))
            for k in range(count):
                where.setdefault(start + k, (index, k))

    def word(
        address: int, codec: Codec, write: SlcWordWrite | None = None, max_value: int = 0xFFFF
    ) -> mapping.RegisterPoint[SlcWordWrite]:
        block, offset = where[address]
        if offset + 2 > plan.blocks[block].size:
            raise AssertionError(f"word at 0x{address:04X} split across blocks")
        return mapping.RegisterPoint(block, offset, codec, write, max_value)

    timers = len(mm.TIMER_NUMBERS)
    for n, number in enumerate(mm.TIMER_NUMBERS):
        accumulator, preset = mm.accumulator_address(number), mm.preset_address(number)
        plan.holding[n] = word(accumulator, U16_BE_MASKED, SlcWordWrite(accumulator), 9999)
        plan.holding[timers + n] = word(preset, U16_BE_MASKED, SlcWordWrite(preset), 9999)
        block, offset = where[mm.step_counter_address(number)]
        plan.input[n] = mapping.RegisterPoint(block, offset, U8)
    for region in (mm.ERROR_BITS_REGION, mm.FORCE_SELECT, mm.FORCE_STATE):
        for address in _addresses(region)[::2]:
            plan.input[address // 2] = word(address, U16_BE)
    for user in mm.all_user_bits():
        byte, bit = mm.user_bit_to_byte(user)
        block, offset = where[byte]
        plan.discrete[user] = mapping.BitPoint(block, offset, bit)
        if 701 <= user <= 868:
            writable = SlcBitWrite(byte, bit) if mm.is_writable_user_bit(user) else None
            plan.coils[user] = mapping.BitPoint(block, offset, bit, writable)
    return plan


@functools.cache
def point_labels() -> dict[tuple[Table, int], PointLabel]:
    """What each point of :func:`slc_ascii_plan` is: ``901.PRE``, ``@0x86``, user bit ``701`` (the CLI's items)."""
    plan = slc_ascii_plan()
    labels: dict[tuple[Table, int], PointLabel] = {}
    for n, number in enumerate(mm.TIMER_NUMBERS):
        labels[Table.HOLDING, n] = PointLabel(f"{number}.ACC", "uint16", f"accumulator of {number} (0-9999)")
        labels[Table.HOLDING, 32 + n] = PointLabel(f"{number}.PRE", "uint16",
                                                   f"preset of {number} (0-9999, protect bit masked)")
        labels[Table.INPUT, n] = PointLabel(f"{number}.STEP", "uint16", f"sequencer step counter of {number}")
    for address in plan.input:
        if (Table.INPUT, address) not in labels:
            byte = 2 * address
            region = mm.region_of(byte)
            what = region.name if region is not None else "memory"
            labels[Table.INPUT, address] = PointLabel(f"@0x{byte:02X}", "uint16",
                                                      f"{what}: bytes {byte:02X}H (high), {byte + 1:02X}H (low)")
    for table, bits in ((Table.COIL, plan.coils), (Table.DISCRETE, plan.discrete)):
        for user in bits:
            byte, bit = mm.user_bit_to_byte(user)
            region = mm.region_of(byte)
            what = region.name if region is not None else "memory"
            labels[table, user] = PointLabel(str(user), "bool", f"{what}: bit {bit} of {byte:02X}H")
    return labels


def byte_read(block: mapping.Block) -> tuple[int, int]:
    """(first byte address, count) of an SLC 100/150 block."""
    request = block.request
    if not (isinstance(request, tuple) and len(request) == 2):
        raise TypeError(f"{block.label}: not an SLC 100/150 byte read")
    start, count = request
    return int(start), int(count)


def plan_lines(plan: mapping.Plan[Any, Any]) -> list[str]:
    """The read plan for ``check-config``: the 1-2 byte reads summarised as address ranges per scan class."""
    byte_reads: dict[str, list[tuple[int, int]]] = {}
    for block in plan.blocks:
        start, count = byte_read(block)
        byte_reads.setdefault(block.scan.value, []).append((start, count))
    lines: list[str] = []
    for scan, reads in byte_reads.items():
        runs: list[list[int]] = []
        for start, count in sorted(reads):
            if runs and runs[-1][1] == start:
                runs[-1][1] = start + count
            else:
                runs.append([start, start + count])
        text = ", ".join(f"0x{a:04X}-0x{b - 1:04X}" for a, b in runs)
        lines.append(f"{scan:4} {len(reads)} reads of 1-2 bytes covering {text}")
    return lines
