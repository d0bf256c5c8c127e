"""The SLC 500 unit: Modbus reads and writes as PCCC commands, PCCC refusals as Modbus exceptions.

The unit runs over a driver that records each PCCC command it is given and answers it (or
refuses it, as a controller's reply with a non-zero STS would, through ``PcccReply.error``): no
line, no simulator, so each test states the exact command the manuals say a Modbus request becomes.

Expected values come from the manuals in ``../shared/docs`` and the guide:

* file type codes (SLC 500 PCCC command notes, Appendix A / §4.36): 84 status, 85 bit, 86 timer,
  89 integer, 8A float, 8B output logical by slot (element = slot, sub-element = word);
* holding registers: protected typed logical write (CMD 0F, FNC AA) of ``size`` bytes from the
  address, data low byte first; a float is 4 bytes IEEE 754, low byte first;
* coils: protected typed logical write with mask (CMD 0F, FNC AB, notes §4.36 / §7.3): "1" in the
  mask for each bit the command may change, data low byte first;
* size limit of one write (notes §4.36): 0-82 bytes on a 500 / 5/01 / 5/02, 0-228 on a 5/03 /
  5/04 / 5/05 channel 0 without the Internet field; "deduct 2 bytes from maximum valid range for
  every field that is in three byte format", a field being 3 bytes when its value is 255 or higher;
* docs/guide/reads-and-writes.md and docs/reference/modbus-map.md#exceptions: as few commands as
  the protocol allows (one typed write per run of words or floats of one file, one masked write per
  word of coils), a PCCC address problem answers 0x02, another refusal 0x04, a refusal part-way
  logs a WARNING naming the registers written; confirmed writes show in the image.
"""

from __future__ import annotations

import contextlib
import logging
import struct
from collections.abc import AsyncIterator, Sequence
from typing import Any

import pytest

from gateway.errors import ControllerRefused, ModbusExceptionReply, ProtocolError
from gateway.kinds.df1.full.driver import Df1Driver
from gateway.kinds.df1.plan import MapItem
from gateway.kinds.df1.unit import Df1Unit, pccc_exception
from gateway.line_driver import LineLease
from gateway.link_health import LineCounters
from gateway.modbus.mapping import Table
from gateway.protocols.df1.pccc import (
    PcccError,
    PcccReply,
    ProcessorFamily,
    ProtectedTypedLogicalMaskedWrite,
    ProtectedTypedLogicalRead,
    ProtectedTypedLogicalWrite,
)

ILLEGAL_ADDRESS = 0x02
DEVICE_FAILURE = 0x04

# SLC file type codes (notes Appendix A)
BIT, TIMER, INTEGER, FLOAT, OUTPUT = 0x85, 0x86, 0x89, 0x8A, 0x8B

MAP = [
    MapItem("holding", 0, "N7:10", 3),  # 0-2: N7:10-12
    MapItem("holding", 3, "T4:1.ACC", 2),  # 3-4: T4:1.ACC, T4:2.ACC (element 1/2, sub-element 2)
    MapItem("holding", 10, "F8:2", 2, "float32"),  # 10-13: F8:2, F8:3, high word first
    MapItem("holding", 20, "O:1.0", 1),  # slot 1 word 0
    MapItem("holding", 21, "O:2.0", 1),  # slot 2 word 0
    MapItem("holding", 30, "N7:20", 1),
    MapItem("holding", 31, "N7:22", 1),  # same file, not the next element
    MapItem("holding", 40, "N7:30", 1),
    MapItem("holding", 41, "N9:31", 1),  # next element number, another file
    MapItem("coil", 0, "B3/14", 4),  # 0-3: B3:0/14, B3:0/15, B3:1/0, B3:1/1
    MapItem("coil", 10, "B3:5/5", 1),
    MapItem("coil", 100, "B3:0/0", 16),
    MapItem("discrete", 0, "T4:1/DN", 1),
]


class RecordingDriver:
    """A PCCC driver without a line: records (command, label); answers reads with ``read_data``;
    the commands numbered in ``refuse`` (1 = the first) get a reply with that (STS, EXT STS)."""

    name = "slc"
    url = "fake://slc"
    available = True
    connected = True
    last_error = ""
    state_since: float | None = None

    def __init__(self, refuse: dict[int, tuple[int, int | None]] | None = None, read_data: bytes = b"") -> None:
        self.sent: list[tuple[Any, str]] = []
        self.refuse = refuse or {}
        self.read_data = read_data
        self.counters = LineCounters()
        self.last_sts = 0
        self.write_burst = 1
        self.poll_burst = 2

    async def execute(self, request: Any, name: str = "", line: LineLease | None = None) -> PcccReply:
        self.sent.append((request, name))
        n = len(self.sent)
        sts, ext_sts = self.refuse.get(n, (0, None))
        reply = PcccReply(dst=0, src=1, cmd=0x4F, sts=sts, tns=n, ext_sts=ext_sts, data=self.read_data)
        reply.raise_for_status(command=name)
        return reply

    @property
    def requests(self) -> list[Any]:
        return [request for request, _ in self.sent]

    @contextlib.asynccontextmanager
    async def write_session(self) -> AsyncIterator[LineLease]:
        yield LineLease()

    async def first_attempt(self) -> None:
        pass


def make_unit(driver: Any, items: Sequence[MapItem] = MAP, **options: Any) -> Df1Unit:
    return Df1Unit(driver=driver, items=list(items), max_read_bytes=236, unit_id=1, name="slc", **options)


def fill_image(unit: Df1Unit) -> None:
    """Every block read once (all zero bytes), now: the image serves every mapped point."""
    now = unit._loop_time()
    for index, block in enumerate(unit.plan.blocks):
        unit.store(index, bytes(block.size), now)


def word(value: int) -> bytes:
    return value.to_bytes(2, "little")


def words(*values: int) -> bytes:
    return b"".join(word(v) for v in values)


def halves(value: float) -> list[int]:
    """A float's two holding registers, high word first (``word_order = "high-first"``)."""
    raw = struct.unpack(">I", struct.pack(">f", value))[0]
    return [raw >> 16, raw & 0xFFFF]


def write(file_type: int, file: int, element: int, sub: int, data: bytes) -> ProtectedTypedLogicalWrite:
    return ProtectedTypedLogicalWrite(file_type, file, element, sub, data)


def masked(file_type: int, file: int, element: int, mask: int, data: int) -> ProtectedTypedLogicalMaskedWrite:
    return ProtectedTypedLogicalMaskedWrite(file_type, file, element, 0, mask, word(data))


# --- holding registers --------------------------------------------------------------------


async def test_one_register_is_a_typed_logical_write_of_its_word() -> None:
    driver = RecordingDriver()
    unit = make_unit(driver)
    await unit.write_registers(0, [0x1234])
    await unit.write_registers(4, [600])
    assert driver.requests == [
        write(INTEGER, 7, 10, 0, b"\x34\x12"),  # N7:10, low byte first
        write(TIMER, 4, 2, 2, word(600)),  # T4:2.ACC: element 2, sub-element 2 (ACC)
    ]
    labels = [label for _, label in driver.sent]
    assert "N7:10" in labels[0] and "T4:2.ACC" in labels[1]  # the driver's errors name the address


async def test_consecutive_words_of_a_file_go_in_one_write() -> None:
    driver = RecordingDriver()
    unit = make_unit(driver)
    await unit.write_registers(0, [1, 2, 0xBEEF])
    assert driver.requests == [write(INTEGER, 7, 10, 0, words(1, 2, 0xBEEF))]
    assert "N7:10" in driver.sent[0][1]


async def test_a_request_over_several_runs_is_one_write_per_run_in_order() -> None:
    """N7:10-12 are one run; T4:1.ACC and T4:2.ACC are words of two timer elements (3 words
    apart in the file): one write each."""
    driver = RecordingDriver()
    unit = make_unit(driver)
    await unit.write_registers(0, [1, 2, 3, 500, 600])
    assert driver.requests == [
        write(INTEGER, 7, 10, 0, words(1, 2, 3)),
        write(TIMER, 4, 1, 2, word(500)),
        write(TIMER, 4, 2, 2, word(600)),
    ]


@pytest.mark.parametrize(
    ("address", "expected"),
    [
        # output logical by slot: O:1.0 and O:2.0 are word 0 of two slots, not two words in a row
        (20, [write(OUTPUT, 0, 1, 0, word(1)), write(OUTPUT, 0, 2, 0, word(2))]),
        (30, [write(INTEGER, 7, 20, 0, word(1)), write(INTEGER, 7, 22, 0, word(2))]),  # a gap: N7:21
        (40, [write(INTEGER, 7, 30, 0, word(1)), write(INTEGER, 9, 31, 0, word(2))]),  # two files
    ],
)
async def test_words_that_are_not_next_to_each_other_are_separate_writes(address: int, expected: list[Any]) -> None:
    driver = RecordingDriver()
    unit = make_unit(driver)
    await unit.write_registers(address, [1, 2])
    assert driver.requests == expected


async def test_a_float_is_one_write_of_its_four_bytes() -> None:
    driver = RecordingDriver()
    unit = make_unit(driver)
    await unit.write_registers(10, halves(-2.5))
    assert driver.requests == [write(FLOAT, 8, 2, 0, struct.pack("<f", -2.5))]
    assert "F8:2" in driver.sent[0][1]


async def test_consecutive_floats_go_in_one_write() -> None:
    driver = RecordingDriver()
    unit = make_unit(driver)
    await unit.write_registers(10, halves(-2.5) + halves(1e6))
    assert driver.requests == [write(FLOAT, 8, 2, 0, struct.pack("<ff", -2.5, 1e6))]


async def test_written_registers_show_in_the_image() -> None:
    driver = RecordingDriver()
    unit = make_unit(driver)
    fill_image(unit)
    await unit.write_registers(0, [7, 8, 9, 500])
    await unit.write_registers(10, halves(-2.5) + halves(0.75))
    assert unit.read_registers(Table.HOLDING, 0, 4) == [7, 8, 9, 500]
    assert unit.read_registers(Table.HOLDING, 10, 4) == halves(-2.5) + halves(0.75)


# --- the size of one write ------------------------------------------------------------------


async def test_a_run_is_cut_at_228_bytes_on_a_5_04() -> None:
    """5/04 channel 0: 0-228 data bytes (notes §4.36); the unit's default without a Df1Driver."""
    items = [MapItem("holding", 0, "N7:0", 120)]
    driver = RecordingDriver()
    unit = make_unit(driver, items)
    values = list(range(1, 116))
    await unit.write_registers(0, values[:114])  # 228 bytes: one command
    await unit.write_registers(0, values)  # 230 bytes: 228, then 2
    assert driver.requests == [
        write(INTEGER, 7, 0, 0, words(*values[:114])),
        write(INTEGER, 7, 0, 0, words(*values[:114])),
        write(INTEGER, 7, 114, 0, word(115)),
    ]


async def test_a_three_byte_file_number_takes_two_bytes_off_the_limit() -> None:
    """File number 255 is a 3-byte field: 226 data bytes (notes §4.36, note 3)."""
    items = [MapItem("holding", 0, "N255:0", 120)]
    driver = RecordingDriver()
    unit = make_unit(driver, items)
    values = list(range(1, 115))
    await unit.write_registers(0, values)
    assert driver.requests == [write(INTEGER, 255, 0, 0, words(*values[:113])), write(INTEGER, 255, 113, 0, word(114))]


async def test_floats_are_cut_at_the_limit_too() -> None:
    items = [MapItem("holding", 0, "F8:0", 60, "float32")]
    driver = RecordingDriver()
    unit = make_unit(driver, items)
    values = [float(k) + 0.5 for k in range(58)]
    await unit.write_registers(0, [h for v in values for h in halves(v)])
    assert driver.requests == [
        write(FLOAT, 8, 0, 0, struct.pack("<57f", *values[:57])),  # 228 bytes
        write(FLOAT, 8, 57, 0, struct.pack("<f", values[57])),
    ]


@pytest.mark.parametrize("options", [{"family": ProcessorFamily.SLC5_01}, {"max_write_bytes": 82}])
async def test_a_5_01_takes_82_bytes_per_write(options: dict[str, Any]) -> None:
    items = [MapItem("holding", 0, "N7:0", 60)]
    driver = RecordingDriver()
    unit = make_unit(driver, items, **options)
    await unit.write_registers(0, list(range(42)))
    assert driver.requests == [write(INTEGER, 7, 0, 0, words(*range(41))), write(INTEGER, 7, 41, 0, word(41))]


@pytest.mark.parametrize(
    ("family", "spans"),
    [(ProcessorFamily.SLC5_02, [(0, 40), (41, 81), (82, 114)]), (ProcessorFamily.SLC5_05, [(0, 113), (114, 114)])],
)
def test_the_limit_is_the_full_duplex_drivers_processors(family: ProcessorFamily, spans: list[tuple[int, int]]) -> None:
    """On a ``Df1Driver`` the unit takes the size limit of the driver's ``processor``: 115 words
    of N7 are cut at 41 words (82 bytes) on a 5/02, at 114 (228 bytes) on a 5/05 (the holding
    registers each write command covers; nothing is sent, the driver is never started)."""
    driver = Df1Driver("socket://127.0.0.1:1", family=family)
    unit = Df1Unit(driver=driver, items=[MapItem("holding", 0, "N7:0", 120)], max_read_bytes=236, unit_id=1,
                   name="slc")
    steps = unit._register_steps(unit.check_register_write(0, list(range(115))))
    assert [(step.first, step.last) for step in steps] == spans


# --- coils ----------------------------------------------------------------------------------


@pytest.mark.parametrize(("on", "data"), [(True, 0x0020), (False, 0x0000)])
async def test_one_coil_is_a_masked_write_of_its_bit(on: bool, data: int) -> None:
    driver = RecordingDriver()
    unit = make_unit(driver)
    await unit.write_bits(10, [on])
    assert driver.requests == [masked(BIT, 3, 5, 0x0020, data)]  # B3:5/5: only bit 5 may change
    assert "B3:5" in driver.sent[0][1]


async def test_coils_of_one_word_are_one_masked_write_per_word() -> None:
    driver = RecordingDriver()
    unit = make_unit(driver)
    await unit.write_bits(0, [True, False, True, False])  # B3:0/14 on, /15 off, B3:1/0 on, /1 off
    assert driver.requests == [masked(BIT, 3, 0, 0xC000, 0x4000), masked(BIT, 3, 1, 0x0003, 0x0001)]
    assert "B3:0" in driver.sent[0][1] and "B3:1" in driver.sent[1][1]


async def test_sixteen_coils_of_a_word_are_one_masked_write() -> None:
    driver = RecordingDriver()
    unit = make_unit(driver)
    values = [k % 3 == 0 for k in range(16)]  # bits 0, 3, 6, 9, 12, 15
    await unit.write_bits(100, values)
    assert driver.requests == [masked(BIT, 3, 0, 0xFFFF, 0b1001001001001001)]


async def test_written_coils_show_in_the_image() -> None:
    driver = RecordingDriver()
    unit = make_unit(driver)
    fill_image(unit)
    await unit.write_bits(0, [True, False, True, True])
    await unit.write_bits(10, [True])
    assert unit.read_bits(Table.COIL, 0, 4) == [True, False, True, True]
    assert unit.read_bits(Table.COIL, 10, 1) == [True]


def test_a_coil_without_a_write_target_is_never_a_step() -> None:
    unit = make_unit(RecordingDriver())
    with pytest.raises(ModbusExceptionReply) as caught:
        unit._bit_steps([(7, unit.plan.discrete[0], True)])
    assert caught.value.code == ILLEGAL_ADDRESS and "coil 7 is not writable" in str(caught.value)


# --- refusals -------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("sts", "ext_sts", "code", "description"),
    [
        (0x50, None, ILLEGAL_ADDRESS, "Addressing problem"),
        (0xF0, 0x02, ILLEGAL_ADDRESS, "Less levels specified in address"),
        (0xF0, 0x03, ILLEGAL_ADDRESS, "More levels specified in address"),
        (0xF0, 0x06, ILLEGAL_ADDRESS, "Address doesn't point to something usable"),
        (0xF0, 0x07, ILLEGAL_ADDRESS, "File is wrong size"),
        (0xF0, 0x0A, ILLEGAL_ADDRESS, "Transaction size plus word address is too large"),
        (0xF0, 0x13, ILLEGAL_ADDRESS, "Address reference exists to deleted area"),
        (0xF0, 0x0B, DEVICE_FAILURE, "Access denied"),
        (0xF0, 0x1A, DEVICE_FAILURE, "File is open; another node owns it"),
        (0xF0, 0x01, DEVICE_FAILURE, "A field has an illegal value"),
        (0x10, None, DEVICE_FAILURE, "Illegal command or format"),
        (0x60, None, DEVICE_FAILURE, "command protection"),
        (0x70, None, DEVICE_FAILURE, "program mode"),
    ],
)
def test_pccc_refusals_answer_0x02_for_address_problems_else_0x04(
    sts: int, ext_sts: int | None, code: int, description: str
) -> None:
    error = PcccReply(dst=0, src=1, cmd=0x4F, sts=sts, tns=1, ext_sts=ext_sts).error(command="write N7:10")
    assert isinstance(error, PcccError)
    reply = pccc_exception(error)
    assert reply.code == code
    assert description in str(reply) and "N7:10" in str(reply)
    unit = make_unit(RecordingDriver())
    assert unit.refusal_exception(error).code == code  # a refused block's reads answer the same


def test_another_refusal_answers_0x04_with_its_reason() -> None:
    unit = make_unit(RecordingDriver())
    reply = unit.refusal_exception(ControllerRefused("the controller said no", reason="no"))
    assert reply.code == DEVICE_FAILURE and "the controller said no" in str(reply)


@pytest.mark.parametrize(("sts", "ext_sts", "code"), [(0x50, None, ILLEGAL_ADDRESS), (0xF0, 0x0B, DEVICE_FAILURE)])
async def test_a_refused_write_answers_the_exception_naming_the_address(sts: int, ext_sts: int | None,
                                                                        code: int) -> None:
    driver = RecordingDriver(refuse={1: (sts, ext_sts), 2: (sts, ext_sts)})
    unit = make_unit(driver)
    with pytest.raises(ModbusExceptionReply) as caught:
        await unit.write_registers(0, [1, 2])
    assert caught.value.code == code and "N7:10" in str(caught.value)
    with pytest.raises(ModbusExceptionReply) as caught:
        await unit.write_bits(10, [True])
    assert caught.value.code == code and "B3:5" in str(caught.value)


async def test_a_register_write_refused_part_way_logs_what_was_written(caplog: pytest.LogCaptureFixture) -> None:
    driver = RecordingDriver(refuse={2: (0x10, None)})
    unit = make_unit(driver)
    fill_image(unit)
    with caplog.at_level(logging.WARNING, logger="gateway.unit"), pytest.raises(ModbusExceptionReply) as caught:
        await unit.write_registers(0, [1, 2, 3, 500, 600])
    assert caught.value.code == DEVICE_FAILURE and "T4:1.ACC" in str(caught.value)
    assert len(driver.sent) == 2  # nothing after the refusal
    assert "holding 0-2 written, holding 3 and after not" in caplog.text
    assert unit.read_registers(Table.HOLDING, 0, 4) == [1, 2, 3, 0]


async def test_a_coil_write_refused_part_way_logs_what_was_written(caplog: pytest.LogCaptureFixture) -> None:
    driver = RecordingDriver(refuse={2: (0x50, None)})
    unit = make_unit(driver)
    fill_image(unit)
    with caplog.at_level(logging.WARNING, logger="gateway.unit"), pytest.raises(ModbusExceptionReply) as caught:
        await unit.write_bits(0, [True, True, True, True])
    assert caught.value.code == ILLEGAL_ADDRESS and "B3:1" in str(caught.value)
    assert "coil 0-1 written, coil 2-3 and after not" in caplog.text
    assert unit.read_bits(Table.COIL, 0, 4) == [True, True, False, False]


# --- reads ----------------------------------------------------------------------------------


async def test_a_block_is_one_typed_logical_read_of_its_bytes() -> None:
    unit = make_unit(RecordingDriver(), [MapItem("holding", 0, "N7:10", 3)])
    (block,) = unit.plan.blocks
    driver = RecordingDriver(read_data=words(1, 2, 3))
    unit.driver = driver
    assert await unit.read_block(block) == words(1, 2, 3)
    assert driver.requests == [ProtectedTypedLogicalRead(INTEGER, 7, 10, 0, 6)]  # N7:10-12: 6 bytes
    assert "N7:10" in driver.sent[0][1]
    unit.driver = RecordingDriver(read_data=words(1, 2))
    with pytest.raises(ProtocolError, match="N7:10"):
        await unit.read_block(block)
    unit.driver = RecordingDriver(refuse={1: (0x50, None)})
    with pytest.raises(PcccError, match="N7:10"):
        await unit.read_block(block)
