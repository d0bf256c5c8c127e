"""The sans-I/O rules of the OPC UA face (gateway/opcua/quality.py), stated from docs/guide/opcua.md."""

from __future__ import annotations

import itertools

import pytest

from gateway.errors import ModbusExceptionReply
from gateway.freshness import LinkState, Offline
from gateway.opcua.passwords import hash_password, verify_password
from gateway.opcua.quality import Code, DemandBook, pass_period, point_quality, revise_interval, write_status


def expected(state: LinkState, known: bool, fresh: bool, read: bool, refused: bool,
             offline: Offline) -> tuple[str, bool]:
    """The guide's table, written out again."""
    if refused:
        return "BadDeviceFailure", False
    if state is LinkState.DOWN:
        return ("BadNoCommunication", False) if known or read else ("BadWaitingForInitialData", False)
    if not read:
        return "BadWaitingForInitialData", False
    if fresh:
        return "Good", True
    if offline is Offline.HOLD:
        return "UncertainLastUsableValue", True
    return "BadNoCommunication", False


@pytest.mark.parametrize(("state", "known", "fresh", "read", "refused", "offline"), list(itertools.product(
    LinkState, (False, True), (False, True), (False, True), (False, True), Offline)))
def test_every_combination_follows_the_guide(state: LinkState, known: bool, fresh: bool, read: bool, refused: bool,
                                             offline: Offline) -> None:
    reading = point_quality(state=state, known=known, fresh=fresh, read=read, refused=refused, offline=offline)
    assert (reading.code.value, reading.carries_value) == expected(state, known, fresh, read, refused, offline)


def test_the_issue_s_named_cases() -> None:
    up = {"known": True, "refused": False}
    assert point_quality(state=LinkState.UP, fresh=True, read=True, offline=Offline.EXCEPTION, **up).code is Code.GOOD
    assert point_quality(state=LinkState.UP, fresh=False, read=False, offline=Offline.HOLD,
                         **up).code is Code.WAITING
    assert point_quality(state=LinkState.DOWN, fresh=False, read=True, offline=Offline.HOLD,
                         **up).code is Code.NO_COMMUNICATION
    stale_hold = point_quality(state=LinkState.STALE, fresh=False, read=True, offline=Offline.HOLD, **up)
    assert (stale_hold.code, stale_hold.carries_value) == (Code.LAST_USABLE, True)
    stale = point_quality(state=LinkState.STALE, fresh=False, read=True, offline=Offline.EXCEPTION, **up)
    assert (stale.code, stale.carries_value) == (Code.NO_COMMUNICATION, False)


def _reply(code: int) -> ModbusExceptionReply:
    return ModbusExceptionReply(code, "x")


def test_write_status() -> None:
    assert write_status(None, elapsed=0.1, write_timeout=1.0, link_up=True) is Code.GOOD
    timed_out = _reply(ModbusExceptionReply.GATEWAY_TARGET_FAILED)
    assert write_status(timed_out, elapsed=1.0, write_timeout=1.0, link_up=True) is Code.TIMEOUT
    assert write_status(timed_out, elapsed=0.2, write_timeout=1.0, link_up=True) is Code.COMMUNICATION_ERROR
    assert write_status(timed_out, elapsed=1.0, write_timeout=1.0, link_up=False) is Code.COMMUNICATION_ERROR
    assert write_status(_reply(ModbusExceptionReply.ILLEGAL_DATA_ADDRESS), elapsed=0, write_timeout=1,
                        link_up=True) is Code.NOT_WRITABLE
    assert write_status(_reply(ModbusExceptionReply.ILLEGAL_DATA_VALUE), elapsed=0, write_timeout=1,
                        link_up=True) is Code.OUT_OF_RANGE
    assert write_status(_reply(ModbusExceptionReply.SERVER_DEVICE_BUSY), elapsed=0, write_timeout=1,
                        link_up=True) is Code.BUSY
    assert write_status(_reply(ModbusExceptionReply.SERVER_DEVICE_FAILURE), elapsed=0, write_timeout=1,
                        link_up=True) is Code.DEVICE_FAILURE


def test_revised_sampling_interval_is_never_faster_than_the_line() -> None:
    assert revise_interval(100, 1000, 0.5, None) == 500  # the class period
    assert revise_interval(100, 1000, 0.5, 2.0) == 2000  # what the line achieves
    assert revise_interval(5000, 1000, 0.5, 2.0) == 5000  # slower than asked: as asked
    assert revise_interval(-1, 1000, 0.0, None) == 1000  # -1: the publishing interval
    assert revise_interval(250, 1000, None, None) == 250  # not polled: as asked
    assert revise_interval(100, 1000, 0.0, None, passes=0.5) == 500  # the server looks every 0.5 s
    assert pass_period(0.1, 1000, 0.5) == 0.5  # half the publishing interval
    assert pass_period(0.1, 500, 0.5) == 0.25
    assert pass_period(0.1, 100, 0.5) == 0.1  # at least publish_interval
    assert pass_period(0.1, 10000, 0.5) == 0.5  # at most the check interval
    assert pass_period(0.1, 0, 0.5) == 0.1  # no subscription


def test_demand_book_notes_each_block_at_its_items_shortest_interval_and_forgets_the_gone() -> None:
    book = DemandBook({3: 0, 4: 0, 5: 1, 6: 1})  # point -> its block
    book.watch(3, 1.0, now=10.0)
    book.watch(5, 0.25, now=10.0)
    assert book.due(10.0) == [0, 1]  # at once
    assert book.due(10.2) == []
    assert book.due(10.25) == [1]
    assert book.due(11.0) == [0, 1]
    book.watch(4, 0.5, now=11.1)  # a faster item of the same block: the shortest interval wins, at once
    assert book.due(11.1) == [0]
    assert book.due(11.6) == [0, 1]
    book.settle({3, 5}, 11.7)  # 4's item is gone: its block is back at 3's interval
    assert book.due(12.1) == [0, 1]
    assert book.due(12.6) == [1]  # block 0 not before 13.1
    book.settle({5}, 12.7)  # 3's subscription is gone: block 0 stops demanding
    assert len(book) == 1
    assert book.due(14.0) == [1]
    book.settle({6}, 14.1)  # an item the book was not told of (made before a reload): at once, then every pass
    assert book.due(14.1) == [1]
    assert book.due(14.2) == [1]
    book.settle(set(), 15.0)
    assert len(book) == 0 and book.due(16.0) == []


def test_a_run_finds_its_changed_points_by_one_comparison() -> None:
    from gateway.modbus.mapping import Table
    from gateway.opcua.points import OpcPoint, point_runs

    def point(table: Table, address: int, kind: str) -> OpcPoint:
        return OpcPoint("l", f"p{address}", f"p{address}", table, address, kind, False, True, 0, "", "")

    words = [point(Table.HOLDING, 0, "int16"), point(Table.HOLDING, 1, "float32"), point(Table.HOLDING, 3, "int16"),
             point(Table.HOLDING, 4, "int32")]
    run, = point_runs(words, range(4))
    old = bytes(12)
    for changed_bytes, expected_members in (([], []), ([0], [0]), ([1], [0]), ([2], [1]), ([5], [1]), ([2, 5], [1]),
                                            ([6], [2]), ([11], [3]), ([0, 4, 8], [0, 1, 3]), (range(12), [0, 1, 2, 3])):
        new = bytearray(old)
        for at in changed_bytes:
            new[at] = 0xA5
        assert run.changed(old, bytes(new)) == expected_members, changed_bytes
    bits = [point(Table.COIL, n, "bool") for n in range(12)]
    run, = point_runs(bits, range(12))
    assert run.changed(b"\x00\x00", b"\x05\x08") == [0, 2, 11]
    assert run.changed(b"\x05\x08", b"\x05\x08") == []


def test_password_hashes() -> None:
    stored = hash_password("s3cret")
    assert stored.startswith("scrypt$") and "s3cret" not in stored
    assert verify_password("s3cret", stored)
    assert not verify_password("s3cret!", stored)
    assert hash_password("s3cret") != stored  # salted
    import hashlib

    pbkdf2 = "pbkdf2-sha256$1000$" + b"salt".hex() + "$" + hashlib.pbkdf2_hmac("sha256", b"pw", b"salt", 1000).hex()
    assert verify_password("pw", pbkdf2) and not verify_password("pw2", pbkdf2)
    assert not verify_password("pw", "scrypt$garbage")
