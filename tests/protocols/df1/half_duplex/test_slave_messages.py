"""Messages slaves initiate on a half-duplex line (MSG, report by exception): stored and answered.

The core acknowledges a slave's own command (DLE ACK, 1770-6.5.16 ch. 3) and sends the PCCC reply
back as a master message ahead of the station's commands (``send_reply``); the answer is decided by
``gateway.protocols.df1.half_duplex.slave_messages``: writes to the gateway's own station go into the sending
station's register table (STS 00), writes outside it the refusal the PCCC target core gives that
command (``pccc.target.refusal``: SLC STS 50, PLC-5 STS F0 / EXT 06 or 09, p. 8-4), anything else
STS 10 "illegal command or format" (p. 8-3).  Byte scripts with a fake clock, whole and byte by byte, with
trailing garbage; then the driver against the multi-drop simulator.
"""

from __future__ import annotations

import asyncio
from dataclasses import replace

import pytest

from gateway.kinds.df1.half.driver import Df1HalfDuplexLine
from gateway.kinds.df1.sim.df1_multidrop import LineOptions, MultidropLine
from gateway.protocols.df1.framing import (
    ACK_SYMBOL,
    EOT_SYMBOL,
    Checksum,
    encode_frame,
    encode_master_message,
    encode_poll,
)
from gateway.protocols.df1.half_duplex.events import (
    FailReason,
    LineConfig,
    MessageDelivered,
    RequestFailed,
    SlaveInitiated,
    StationConfig,
)
from gateway.protocols.df1.half_duplex.master import HalfDuplexMaster
from gateway.protocols.df1.half_duplex.slave_messages import RegisterTable, SlaveMessageVerdict, answer_slave_message
from gateway.protocols.df1.pccc import (
    DataType,
    LogicalBinaryAddress,
    ProtectedTypedLogicalRead,
    ProtectedTypedLogicalWrite,
    TypedWrite,
    WordRangeWrite,
    encode_command,
)
from gateway.protocols.df1.pccc.target import PcccTarget
from gateway.protocols.df1.pccc.target_table import DataTable
from gateway.sim.serve import SimStream
from gateway.transport import ByteStream

from .test_master import events, feed

GATEWAY = 0x00
MODES = ["whole", "bytes"]  # as test_master: whole, byte by byte


def msg_word_range_write(station: int, tns: int, element: int, words: list[int], dst: int = GATEWAY) -> bytes:
    """What a PLC-5 MSG (word range write to N7:element of node ``dst``) puts on the line."""
    data = b"".join(w.to_bytes(2, "little") for w in words)
    return encode_command(WordRangeWrite(LogicalBinaryAddress.of(0, 7, element), data), dst=dst, src=station, tns=tns)


def msg_typed_logical_write(station: int, tns: int, element: int, words: list[int]) -> bytes:
    """What an SLC 5/0x MSG (485 write to N7:element) puts on the line: 0F AA, file type 89."""
    data = b"".join(w.to_bytes(2, "little") for w in words)
    return encode_command(ProtectedTypedLogicalWrite(0x89, 7, element, 0, data), dst=GATEWAY, src=station, tns=tns)


# ------------------------------------------------------------------------------ the answer


def test_word_range_write_to_us_is_stored_with_its_time() -> None:
    table = RegisterTable(file_number=7, size=10)
    packet = msg_word_range_write(3, 0x0102, 4, [11, 0x1010])
    verdict, reply = answer_slave_message(packet, own_station=GATEWAY, table=table, now=12.5)
    assert verdict is SlaveMessageVerdict.STORED
    assert reply == bytes.fromhex("03 00 4F 00 02 01")  # DST/SRC swapped, CMD | 40, same TNS, STS 0
    assert table.values()[4:6] == [11, 0x1010] and table.received_at(4) == 12.5
    assert table.age(5, 13.0) == pytest.approx(0.5) and table.age(0, 13.0) is None


def test_typed_logical_write_to_us_is_stored() -> None:
    table = RegisterTable(file_number=7, size=10)
    verdict, reply = answer_slave_message(msg_typed_logical_write(2, 9, 0, [1, 2, 3]), own_station=GATEWAY,
                                          table=table, now=1.0)
    assert verdict is SlaveMessageVerdict.STORED and reply == bytes.fromhex("02 00 4F 00 09 00")
    assert table.values()[:3] == [1, 2, 3]


@pytest.mark.parametrize(
    ("packet", "table", "verdict", "reply"),
    [
        # a read (0F A2): not something the gateway serves to slaves -> STS 10 (p. 8-3)
        (encode_command(ProtectedTypedLogicalRead(0x89, 7, 0, 0, 2), dst=GATEWAY, src=2, tns=5),
         RegisterTable(), SlaveMessageVerdict.UNSUPPORTED, "02 00 4F 10 05 00"),
        # a write for another station: the gateway does not route between slaves -> STS 10
        (msg_word_range_write(2, 6, 0, [1], dst=9), RegisterTable(), SlaveMessageVerdict.UNSUPPORTED,
         "02 09 4F 10 06 00"),
        # a station without a register table -> STS 10
        (msg_word_range_write(2, 7, 0, [1]), None, SlaveMessageVerdict.UNSUPPORTED, "02 00 4F 10 07 00"),
        # The STS of a write outside the table is the PCCC target's (pccc/target.py), by command family.
        # PLC-5 word range write, data past the end of the table -> STS F0, EXT STS 09 "data or file
        # is too large" (1770-6.5.16 p. 8-4; p. 8-9: "read or write past the end of a file")
        (msg_word_range_write(2, 8, 9, [1, 2]), RegisterTable(size=10), SlaveMessageVerdict.BAD_ADDRESS,
         "02 00 4F F0 08 00 09"),
        # its first element past the end -> EXT STS 06 "address doesn't point to something usable" (p. 8-4)
        (msg_word_range_write(2, 8, 10, [1]), RegisterTable(size=10), SlaveMessageVerdict.BAD_ADDRESS,
         "02 00 4F F0 08 00 06"),
        # another file -> the same
        (encode_command(WordRangeWrite(LogicalBinaryAddress.of(0, 9, 0), b"\x01\x00"), dst=GATEWAY, src=2, tns=1),
         RegisterTable(), SlaveMessageVerdict.BAD_ADDRESS, "02 00 4F F0 01 00 06"),
        # an SLC protected typed logical write (0F AA) outside the table, past its end or to another
        # file -> STS 50 "address problem", the SLC command's own code (notes §4.36 (d), §7.3)
        (msg_typed_logical_write(2, 4, 9, [1, 2]), RegisterTable(size=10), SlaveMessageVerdict.BAD_ADDRESS,
         "02 00 4F 50 04 00"),
        (msg_typed_logical_write(2, 5, 10, [1]), RegisterTable(size=10), SlaveMessageVerdict.BAD_ADDRESS,
         "02 00 4F 50 05 00"),
        (encode_command(ProtectedTypedLogicalWrite(0x89, 9, 0, 0, b"\x01\x00"), dst=GATEWAY, src=2, tns=6),
         RegisterTable(), SlaveMessageVerdict.BAD_ADDRESS, "02 00 4F 50 06 00"),
        # an unknown command -> STS 10; a reply or a runt -> no answer at all
        (bytes.fromhex("00 02 06 00 03 00 00"), RegisterTable(), SlaveMessageVerdict.UNSUPPORTED, "02 00 46 10 03 00"),
        (bytes.fromhex("00 02 4F 00 03 00"), RegisterTable(), SlaveMessageVerdict.NO_ANSWER, None),
        (bytes.fromhex("00 02 0F"), RegisterTable(), SlaveMessageVerdict.NO_ANSWER, None),
    ],
)
def test_everything_else_gets_the_manuals_error(
    packet: bytes, table: RegisterTable | None, verdict: SlaveMessageVerdict, reply: str | None
) -> None:
    got = answer_slave_message(packet, own_station=GATEWAY, table=table, now=0.0)
    assert got == (verdict, None if reply is None else bytes.fromhex(reply))
    if table is not None:
        assert table.values() == [0] * table.size  # nothing stored


@pytest.mark.parametrize(
    "packet",
    [
        msg_word_range_write(2, 1, 9, [1, 2]),
        msg_word_range_write(2, 2, 10, [1]),
        encode_command(WordRangeWrite(LogicalBinaryAddress.of(0, 9, 0), b"\x01\x00"), dst=GATEWAY, src=2, tns=3),
        msg_typed_logical_write(2, 4, 9, [1, 2]),
        msg_typed_logical_write(2, 5, 10, [1]),
        encode_command(ProtectedTypedLogicalWrite(0x89, 9, 0, 0, b"\x01\x00"), dst=GATEWAY, src=2, tns=6),
    ],
)
def test_a_write_outside_the_table_gets_the_full_duplex_targets_answer(packet: bytes) -> None:
    """The same write outside N7:0-9 gets the same reply from both paths that answer a PLC's message."""
    _verdict, half_duplex = answer_slave_message(packet, own_station=GATEWAY, table=RegisterTable(size=10), now=0.0)
    full_duplex = PcccTarget(DataTable.of("N7:10")).execute(packet, 0.0).reply
    assert half_duplex == full_duplex is not None


# ------------------------------------------------------------------------------ the core


def make(*stations: int, checksum: Checksum = Checksum.BCC) -> HalfDuplexMaster:
    master = HalfDuplexMaster(LineConfig(checksum, ack_timeout=0.5, message_resends=1),
                              [replace(StationConfig(s), poll_interval=100.0) for s in stations])
    master.start(0.0)
    return master


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("checksum", list(Checksum))
def test_core_acks_the_msg_then_sends_the_reply_as_a_master_message(mode: str, checksum: Checksum) -> None:
    master = make(2, 3, checksum=checksum)
    assert master.data_to_send() == encode_poll(2)
    msg = msg_word_range_write(2, 0x10, 0, [5])
    feed(master, encode_frame(msg, checksum) + b"\x00\x10", 0.01, mode)  # with trailing garbage
    assert master.data_to_send() == ACK_SYMBOL + encode_poll(2)
    assert events(master) == [SlaveInitiated(2, msg)]
    feed(master, EOT_SYMBOL, 0.02, mode)
    assert master.data_to_send() == encode_poll(3)
    reply = bytes.fromhex("02 00 4F 00 10 00")
    request = master.send_reply(2, reply, 0.025)  # while station 3's poll is out: queued
    assert master.data_to_send() == b""
    feed(master, EOT_SYMBOL, 0.03, mode)
    assert master.data_to_send() == encode_master_message(2, reply, checksum)
    feed(master, ACK_SYMBOL + b"\x55", 0.04, mode)
    assert events(master) == [MessageDelivered(request, 2)]
    assert master.data_to_send() == b""  # nothing polled for; next background poll at 100 s


def test_reply_goes_ahead_of_queued_commands_and_is_resent_identically() -> None:
    master = make(2)
    master.data_to_send()
    master.receive_data(EOT_SYMBOL, 0.0)
    command = bytes.fromhex("02 00 0F 00 10 00 A2")  # our own command, same TNS as the slave's MSG
    reply = bytes.fromhex("02 00 4F 00 10 00")
    master.submit(2, command, 0.0)
    sent = master.data_to_send()
    assert sent == encode_master_message(2, command, Checksum.BCC)
    request = master.send_reply(2, reply, 0.0)  # queued while our command waits for its ACK
    master.receive_data(ACK_SYMBOL, 0.1)
    assert master.data_to_send() == encode_master_message(2, reply, Checksum.BCC)  # before the reply poll
    master.handle_timeout(0.6)  # no ACK: the same bytes again
    assert master.data_to_send() == encode_master_message(2, reply, Checksum.BCC)
    master.handle_timeout(1.1)
    assert events(master) == [RequestFailed(request, 2, reason=FailReason.NO_ACK, may_have_executed=True)]




# ------------------------------------------------------------------------------ the driver


async def test_driver_stores_report_by_exception_and_answers_each_station() -> None:
    line = MultidropLine(LineOptions(checksum=Checksum.CRC, stations=(1, 2, 3)))

    async def opener(url: str, settings: object, **_: object) -> ByteStream:
        return SimStream(line)

    tables = {1: RegisterTable(size=8), 2: RegisterTable(size=8)}
    driver = Df1HalfDuplexLine(
        "sim://line", [StationConfig(n, poll_timeout=0.05, poll_interval=0.02) for n in (1, 2, 3)],
        name="line", checksum=Checksum.CRC, ack_timeout=0.05, opener=opener, register_tables=tables, first_tns=1,
        link_reset=False,  # a DLE NAK at start would empty the slaves' queues (Table 2.C)
    )
    line.slaves[1].initiate(msg_word_range_write(1, 0x0501, 2, [111, 112]))
    line.slaves[2].initiate(msg_typed_logical_write(2, 0x0601, 0, [222]))
    line.slaves[3].initiate(msg_word_range_write(3, 0x0701, 0, [333]))  # no table for station 3
    await driver.start()
    try:
        for _ in range(200):
            totals = [driver.stations[n].totals for n in (1, 2, 3)]
            if all(t.slave_messages == 1 for t in totals) and not driver._replies:
                break
            await asyncio.sleep(0.01)
    finally:
        await driver.close()
    assert tables[1].values()[2:4] == [111, 112] and tables[1].values()[:2] == [0, 0]
    assert tables[2].values()[0] == 222 and tables[1].values()[0] == 0  # never mixed between stations
    assert [driver.stations[n].totals.slave_writes for n in (1, 2, 3)] == [1, 1, 0]
    assert driver.stations[3].totals.slave_refused == 1
    # each slave received exactly one master message: the reply to its MSG (its controller ignores it)
    assert [line.slaves[n].counters.messages for n in (1, 2, 3)] == [1, 1, 1]
    assert all(not line.slaves[n].outgoing for n in (1, 2, 3))  # every MSG was acknowledged


# ------------------------------------------------------------------------------ which writes are stored


def store(packet: bytes, table: RegisterTable, now: float = 0.0) -> SlaveMessageVerdict:
    verdict, reply = answer_slave_message(packet, own_station=GATEWAY, table=table, now=now)
    assert reply is not None
    return verdict


def typed_write(address: LogicalBinaryAddress, data_type: int, element_size: int, data: bytes,
                packet_offset: int = 0) -> bytes:
    request = TypedWrite(address, data_type, element_size, data, packet_offset=packet_offset,
                         total=len(data) // element_size + packet_offset)
    return encode_command(request, dst=GATEWAY, src=2, tns=1)


@pytest.mark.parametrize(
    ("levels", "stored"),
    [
        ((0, 7, 3), True),  # section 0 (data table), file 7, element 3
        ((0, 7, 3, 0), True),  # the same with sub-element 0
        ((0, 7, 3, 1), False),  # a sub-element: not a word of the table
        ((1, 7, 3), False),  # another section
        ((0, 7), False),  # a whole file: no element
        ((0, 7, 3, 0, 0), False),  # five levels
    ],
)
def test_a_word_range_write_is_stored_only_when_it_addresses_data_table_words(
    levels: tuple[int, ...], stored: bool
) -> None:
    table = RegisterTable(file_number=7, size=10)
    packet = encode_command(WordRangeWrite(LogicalBinaryAddress.of(*levels), b"\x2a\x00\x2b\x01"),
                            dst=GATEWAY, src=2, tns=1)
    assert store(packet, table) is (SlaveMessageVerdict.STORED if stored else SlaveMessageVerdict.UNSUPPORTED)
    assert table.values()[3:5] == ([0x2A, 0x12B] if stored else [0, 0])


def test_a_later_packet_of_a_word_range_write_is_not_stored() -> None:
    table = RegisterTable(file_number=7, size=10)
    request = WordRangeWrite(LogicalBinaryAddress.of(0, 7, 3), b"\x2a\x00", packet_offset=1, total=2)
    assert store(encode_command(request, dst=GATEWAY, src=2, tns=1), table) is SlaveMessageVerdict.UNSUPPORTED
    assert table.writes == 0 and table.values() == [0] * 10


@pytest.mark.parametrize(
    ("file_type", "sub_element", "data", "stored"),
    [
        (0x89, 0, b"\x01\x00\x02\x00", True),  # integer file, whole words
        (0x85, 0, b"\x01\x00\x02\x00", False),  # a bit file
        (0x89, 1, b"\x01\x00\x02\x00", False),  # a sub-element
        (0x89, 0, b"\x01\x00\x02", False),  # half a word
    ],
)
def test_a_typed_logical_write_is_stored_only_for_whole_words_of_an_integer_file(
    file_type: int, sub_element: int, data: bytes, stored: bool
) -> None:
    table = RegisterTable(file_number=7, size=10)
    packet = encode_command(ProtectedTypedLogicalWrite(file_type, 7, 1, sub_element, data), dst=GATEWAY, src=2, tns=1)
    assert store(packet, table) is (SlaveMessageVerdict.STORED if stored else SlaveMessageVerdict.UNSUPPORTED)
    assert table.values()[1:3] == ([1, 2] if stored else [0, 0])


@pytest.mark.parametrize(
    ("levels", "data_type", "size", "offset", "stored"),
    [
        ((0, 7, 2), DataType.INTEGER, 2, 0, True),
        ((0, 7, 2, 0), DataType.INTEGER, 2, 0, True),  # four levels, sub-element 0
        ((0, 7, 2, 1), DataType.INTEGER, 2, 0, False),  # a sub-element: not a word of the table
        ((0, 7, 2, 0, 0), DataType.INTEGER, 2, 0, False),  # five levels
        ((0, 7, 2), DataType.INTEGER, 4, 0, False),  # 4-byte elements
        ((0, 7, 2), DataType.BCD, 2, 0, False),  # not integers
        ((1, 7, 2), DataType.INTEGER, 2, 0, False),  # another section
        ((0, 7), DataType.INTEGER, 2, 0, False),  # no element
        ((0, 7, 2), DataType.INTEGER, 2, 1, False),  # a later packet
    ],
)
def test_a_typed_write_is_stored_only_for_integers_of_the_data_table(
    levels: tuple[int, ...], data_type: int, size: int, offset: int, stored: bool
) -> None:
    table = RegisterTable(file_number=7, size=10)
    packet = typed_write(LogicalBinaryAddress.of(*levels), data_type, size, b"\x05\x00\x06\x00", offset)
    assert store(packet, table) is (SlaveMessageVerdict.STORED if stored else SlaveMessageVerdict.UNSUPPORTED)
    assert table.values()[2:4] == ([5, 6] if stored else [0, 0])


def test_words_are_little_endian_and_each_gets_its_time() -> None:
    table = RegisterTable(file_number=7, size=4)
    assert store(msg_word_range_write(2, 1, 0, [0x1234, 0xFFFF]), table, now=5.0) is SlaveMessageVerdict.STORED
    assert store(msg_word_range_write(2, 2, 1, [7]), table, now=6.5) is SlaveMessageVerdict.STORED
    assert list(table) == table.values() == [0x1234, 7, 0, 0]
    assert [table.value(i) for i in range(4)] == [0x1234, 7, 0, 0]
    assert [table.received_at(i) for i in range(4)] == [5.0, 6.5, None, None]
    assert table.age(0, 7.0) == 2.0 and table.age(1, 7.0) == 0.5 and table.age(2, 7.0) is None
    assert (table.writes, table.refused) == (2, 0)
    for tns in (3, 4):
        assert store(msg_word_range_write(2, tns, 3, [1, 2]), table) is SlaveMessageVerdict.BAD_ADDRESS
    assert (table.writes, table.refused) == (2, 2)  # each write counted once, stored or refused


@pytest.mark.parametrize(
    ("element", "count", "covered"),
    [(10, 1, True), (10, 5, True), (9, 1, False), (14, 1, True), (15, 1, False), (14, 2, False)],
)
def test_a_table_with_a_first_element_covers_its_window_only(element: int, count: int, covered: bool) -> None:
    """N7:10 .. N7:14 (first element 10, 5 words): a write must fall within it entirely."""
    table = RegisterTable(file_number=7, size=5, first_element=10)
    verdict = store(msg_word_range_write(2, 1, element, list(range(1, count + 1))), table, now=1.0)
    assert verdict is (SlaveMessageVerdict.STORED if covered else SlaveMessageVerdict.BAD_ADDRESS)
    assert (table.writes, table.refused) == ((1, 0) if covered else (0, 1))
    if covered:
        assert table.values()[element - 10 : element - 10 + count] == list(range(1, count + 1))
    else:
        assert table.values() == [0] * 5


@pytest.mark.parametrize(
    ("kwargs", "ok"),
    [
        ({"file_number": 0}, True), ({"file_number": 999}, True), ({"file_number": -1}, False),
        ({"file_number": 1000}, False), ({"size": 1}, True), ({"size": 10_000}, True), ({"size": 0}, False),
        ({"size": 10_001}, False), ({"first_element": 0}, True), ({"first_element": -1}, False),
    ],
)
def test_register_table_limits(kwargs: dict[str, int], ok: bool) -> None:
    if ok:
        table = RegisterTable(**kwargs)
        assert len(table.values()) == table.size == kwargs.get("size", 100)
    else:
        with pytest.raises(ValueError, match="out of range"):
            RegisterTable(**kwargs)


def test_register_table_defaults_are_n7_0_to_99() -> None:
    table = RegisterTable()
    assert (table.file_number, table.size, table.first_element) == (7, 100, 0)
