"""The multi-drop half-duplex line simulator, driven by the sans-I/O master core with a fake clock."""

from __future__ import annotations

import asyncio
import itertools

import pytest

from gateway.kinds.df1.sim.df1_multidrop import LineOptions, MultidropLine
from gateway.protocols.df1.address import FileType
from gateway.protocols.df1.framing import EOT_SYMBOL, NEED_DATA, Checksum, encode_poll
from gateway.protocols.df1.half_duplex.events import (
    LineConfig,
    MasterEvent,
    ReplyReceived,
    RequestFailed,
    StationConfig,
    StationDemoted,
)
from gateway.protocols.df1.half_duplex.master import HalfDuplexMaster
from gateway.protocols.df1.pccc import (
    ProtectedTypedLogicalRead,
    ProtectedTypedLogicalWrite,
    decode_reply,
    encode_command,
)
from gateway.sim.serve import close_tcp, serve_tcp
from gateway.sim.variants import variant_matrix

N = FileType.INTEGER


class Harness:
    """Moves bytes between a master core and the line at fake times."""

    def __init__(self, line: MultidropLine, core: HalfDuplexMaster, *, bytewise: bool = False) -> None:
        self.line, self.core, self.now = line, core, 0.0
        self.events: list[MasterEvent] = []
        self.bytewise = bytewise
        self.tns = itertools.count(1)
        core.start(0.0)

    def pump(self) -> None:
        while True:
            data = self.core.data_to_send()
            if data and self.bytewise:
                outs = [o for b in data for o in self.line.receive(bytes((b,)), self.now)]
            else:
                outs = self.line.receive(data, self.now) if data else self.line.poll(self.now)
            for out in outs:
                self.core.receive_data(out.data, self.now)
            while (event := self.core.next_event()) is not NEED_DATA:
                self.events.append(event)
            if not data and not outs:
                return

    def run_until(self, done: int, limit: float = 120.0) -> None:
        """Until ``done`` request outcomes are in (or ``limit`` fake seconds)."""
        while self.now < limit:
            self.pump()
            if sum(isinstance(e, ReplyReceived | RequestFailed) for e in self.events) >= done:
                return
            times = [t for t in (self.core.next_deadline(), self.line.next_deadline()) if t is not None]
            if not times:
                return
            self.now = max(self.now, min(times))
            self.core.handle_timeout(self.now)
        raise AssertionError(f"not done by {limit} s: {self.events[-5:]}")

    def read(self, station: int, element: int) -> int:
        packet = encode_command(ProtectedTypedLogicalRead(N, 7, element, 0, 2), dst=station, src=0, tns=next(self.tns))
        return self.core.submit(station, packet, self.now)

    def write(self, station: int, element: int, value: int) -> int:
        request = ProtectedTypedLogicalWrite(N, 7, element, 0, value.to_bytes(2, "little"))
        return self.core.submit(station, encode_command(request, dst=station, src=0, tns=next(self.tns)), self.now)

    def outcome(self, request_id: int) -> ReplyReceived | RequestFailed:
        for event in self.events:
            if isinstance(event, ReplyReceived | RequestFailed) and event.request_id == request_id:
                return event
        raise AssertionError(f"no outcome for request {request_id}")


def core_for(stations: tuple[int, ...], checksum: Checksum, **line: object) -> HalfDuplexMaster:
    config = LineConfig(checksum, ack_timeout=0.2, message_resends=4, **line)  # type: ignore[arg-type]
    return HalfDuplexMaster(
        config,
        [StationConfig(s, poll_timeout=0.2, reply_timeout=5.0, demote_after=3, poll_interval=0.5) for s in stations],
    )


def seed_values(line: MultidropLine) -> None:
    for number, controller in line.controllers.items():
        for element in range(10):
            controller.set_word("N7", element, 1000 * number + element)


@pytest.mark.parametrize("checksum", [Checksum.BCC, Checksum.CRC])
def test_three_stations_answer_their_own_values(checksum: Checksum) -> None:
    line = MultidropLine(LineOptions(checksum=checksum, stations=(1, 2, 3)))
    seed_values(line)
    h = Harness(line, core_for((1, 2, 3), checksum))
    ids = {(s, e): h.read(s, e) for s in (1, 2, 3) for e in (0, 5)}
    h.run_until(len(ids))
    for (station, element), request_id in ids.items():
        event = h.outcome(request_id)
        assert isinstance(event, ReplyReceived) and event.station == station
        assert decode_reply(event.message).data == (1000 * station + element).to_bytes(2, "little")


def test_bytes_fed_one_at_a_time() -> None:
    line = MultidropLine(LineOptions(checksum=Checksum.CRC, stations=(1, 0x10)))
    seed_values(line)
    h = Harness(line, core_for((1, 0x10), Checksum.CRC), bytewise=True)
    ids = [h.read(0x10, 3), h.read(1, 2)]
    h.run_until(2)
    assert decode_reply(h.outcome(ids[0]).message).data == (16003).to_bytes(2, "little")  # type: ignore[union-attr]
    assert decode_reply(h.outcome(ids[1]).message).data == (1002).to_bytes(2, "little")  # type: ignore[union-attr]


@pytest.mark.parametrize("choices", list(variant_matrix(MultidropLine.VARIANTS)), ids=str)
@pytest.mark.parametrize("checksum", [Checksum.BCC, Checksum.CRC])
def test_faults_never_give_a_wrong_value(choices: dict[str, str], checksum: Checksum) -> None:
    """1 in 6 slave frames corrupted, 1 in 10 master frames unheard, one dead station, one slow one."""
    options = LineOptions(checksum=checksum, stations=(1, 2, 3, 4), dead=frozenset({4}), slow={3: 0.05},
                          busy_polls={2: 1}, corrupt=6, ignore=10, seed=7)
    line = MultidropLine(options, variants=choices)
    seed_values(line)
    h = Harness(line, core_for((1, 2, 3, 4), checksum))
    ids = {(s, e): h.read(s, e) for s in (1, 2, 3, 4) for e in range(4)}
    h.run_until(len(ids))
    answered = 0
    for (station, element), request_id in ids.items():
        event = h.outcome(request_id)
        assert event.station == station
        if isinstance(event, ReplyReceived):
            answered += 1
            assert decode_reply(event.message).data == (1000 * station + element).to_bytes(2, "little")
        else:
            assert station == 4 or choices["reply_retries"] != "unlimited"
    # a slave that gives its reply up (reply_retries 0 or 3) loses it to a corrupted frame: the driver
    # reads again with a new TNS; with unlimited resends every live station's read is answered
    assert answered == 12 if choices["reply_retries"] == "unlimited" else answered >= 6
    assert any(isinstance(e, StationDemoted) and e.station == 4 for e in h.events)
    assert line.counters.corrupted > 0 and line.counters.ignored > 0


def test_duplicate_detection_keeps_writes_exactly_once() -> None:
    """Lost master frames (ACKs too) with duplicate detection on: every write executed once."""
    line = MultidropLine(LineOptions(checksum=Checksum.BCC, stations=(1, 2), ignore=4, seed=3))
    h = Harness(line, core_for((1, 2), Checksum.BCC))
    ids = [h.write(1 + k % 2, 20 + k, 500 + k) for k in range(10)]
    h.run_until(len(ids))
    for k, request_id in enumerate(ids):
        station = 1 + k % 2
        assert isinstance(h.outcome(request_id), ReplyReceived)
        assert line.controllers[station].word("N7", 20 + k) == 500 + k
        assert line.controllers[3 - station].word("N7", 20 + k) == 20 + k  # the other station untouched
    for station in (1, 2):
        writes = line.controllers[station].applied_writes
        assert len(writes) == 5, writes


def test_collision_when_the_master_transmits_into_a_late_answer() -> None:
    """A station slower than the poll timeout answers while the master polls the next one."""
    options = LineOptions(checksum=Checksum.BCC, stations=(1, 2), slow={1: 0.25}, char_time=11 / 9600)
    line = MultidropLine(options)
    seed_values(line)
    h = Harness(line, core_for((1, 2), Checksum.BCC, char_time=11 / 9600))
    ids = [h.read(1, 1), h.read(2, 2)]
    h.run_until(2, limit=30.0)
    assert line.counters.collisions > 0
    for request_id in ids:
        event = h.outcome(request_id)
        if isinstance(event, ReplyReceived):
            assert decode_reply(event.message).data == (1000 * event.station + event.station).to_bytes(2, "little")


def test_radio_latency_and_echo() -> None:
    options = LineOptions(checksum=Checksum.CRC, stations=(5, 6), latency=0.03, turnaround=0.01,
                          char_time=11 / 19200, echo=True)
    line = MultidropLine(options)
    seed_values(line)
    h = Harness(line, core_for((5, 6), Checksum.CRC, char_time=11 / 19200, echo=True))
    ids = [h.read(5, 1), h.read(6, 2)]
    h.run_until(2)
    assert [decode_reply(h.outcome(i).message).data for i in ids] == [  # type: ignore[union-attr]
        (5001).to_bytes(2, "little"), (6002).to_bytes(2, "little")]
    assert h.core.collisions == 0 and line.counters.collisions == 0
    assert line.counters.busy_time > 0


def test_dead_station_never_answers() -> None:
    line = MultidropLine(LineOptions(checksum=Checksum.BCC, stations=(1, 2), dead=frozenset({2})))
    assert [o.data for o in line.receive(encode_poll(2), 0.0)] == []
    assert [o.data for o in line.receive(encode_poll(1), 0.0)] == [EOT_SYMBOL]
    assert 2 in line.controllers and 2 not in line.slaves


def test_options_from_strings() -> None:
    line = MultidropLine.from_options({"stations": "1,2,7", "dead": "7", "slow": "2:0.5", "busy_polls": "1:2",
                                       "checksum": "bcc", "corrupt": "6", "ignore": "10", "model": "plc5"})
    assert line.options.stations == (1, 2, 7) and line.options.dead == {7}
    assert line.options.slow == {2: 0.5} and line.options.busy_polls == {1: 2}
    with pytest.raises(ValueError, match="not on the line"):
        LineOptions.from_options({"stations": "1", "dead": "2"})
    with pytest.raises(ValueError, match="unknown multi-drop line option"):
        LineOptions.from_options({"stationz": "1"})
    with pytest.raises(ValueError, match="when_busy"):
        MultidropLine(variants={"when_busy": "maybe"})


async def test_served_over_tcp() -> None:
    """The line is a SimDevice: serve_tcp carries polls and answers."""
    line = MultidropLine(LineOptions(checksum=Checksum.BCC, stations=(1, 2)))
    server = await serve_tcp(line, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    try:
        writer.write(encode_poll(2))
        assert await asyncio.wait_for(reader.readexactly(2), 2.0) == EOT_SYMBOL
    finally:
        writer.close()
        await close_tcp(server)
