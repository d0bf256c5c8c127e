"""What an OPC UA client is told, decided without asyncua: sans-I/O, the caller passes ``now``.

* :func:`point_quality`: a variable's status code from the one verdict (``gateway.freshness``: the
  link's state, the block's freshness), whether its block was ever read, whether the controller
  refuses it, and the link's ``offline`` policy (docs/guide/opcua.md, "Quality and time").
* :func:`write_status`: a write's status code from the Modbus answer the write path gave.
* :class:`DemandBook`: the monitored items' demand: each block with a live monitored item on one of
  its points is noted as demand once per the shortest sampling interval of those items; a block
  whose monitored items are all gone (the subscription deleted, the session closed) stops
  demanding at once.
* :func:`revise_interval`: the sampling interval a monitored item is given: what the line achieves
  for its block, never less than the block's class period nor the server's pass period
  (:func:`pass_period`: half the subscription's publishing interval, from ``publish_interval``
  to 0.5 s).

Status codes are named as OPC UA Part 4 §7.34 and Part 8 name them (:class:`Code`); the server module
turns a name into asyncua's number.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from enum import StrEnum

from gateway.errors import ModbusExceptionReply
from gateway.freshness import LinkState, Offline
from gateway.frozen import frozen

__all__ = ["Code", "DemandBook", "Reading", "pass_period", "point_quality", "revise_interval", "write_status"]


class Code(StrEnum):
    """The status codes this server gives (their OPC UA names)."""

    GOOD = "Good"
    WAITING = "BadWaitingForInitialData"
    NO_COMMUNICATION = "BadNoCommunication"
    LAST_USABLE = "UncertainLastUsableValue"
    DEVICE_FAILURE = "BadDeviceFailure"
    NOT_WRITABLE = "BadNotWritable"
    OUT_OF_RANGE = "BadOutOfRange"
    TYPE_MISMATCH = "BadTypeMismatch"
    TIMEOUT = "BadTimeout"
    COMMUNICATION_ERROR = "BadCommunicationError"
    USER_DENIED = "BadUserAccessDenied"
    BUSY = "BadResourceUnavailable"


@frozen
class Reading:
    """A variable's status code, and whether its value goes with it (Good, or the last usable value)."""

    code: Code
    carries_value: bool


_GOOD = Reading(Code.GOOD, True)
_HELD = Reading(Code.LAST_USABLE, True)
_WAITING = Reading(Code.WAITING, False)
_NO_COMMUNICATION = Reading(Code.NO_COMMUNICATION, False)
_REFUSED = Reading(Code.DEVICE_FAILURE, False)


def point_quality(*, state: LinkState, known: bool, fresh: bool, read: bool, refused: bool,
                  offline: Offline) -> Reading:
    """A variable's quality now.

    ``state``: the link's verdict; ``known``: the link has had a verdict (a link that has not answered
    yet since start is not known down); ``fresh``: its block is fresh (``Freshness.block_fresh``);
    ``read``: its block was read at least once; ``refused``: the controller refuses the block.

    * the controller refuses the block: Bad_DeviceFailure;
    * the link is down: Bad_NoCommunication (before the link's first verdict and the block's first read:
      Bad_WaitingForInitialData);
    * the block was never read: Bad_WaitingForInitialData;
    * fresh: Good;
    * stale: ``hold``: Uncertain_LastUsableValue with the last value; ``exception`` and ``zero``:
      Bad_NoCommunication (a Bad status carries no value in OPC UA: there is no zero to give).
    """
    if refused:
        return _REFUSED
    if state is LinkState.DOWN:
        return _NO_COMMUNICATION if known or read else _WAITING
    if not read:
        return _WAITING
    if fresh:
        return _GOOD
    return _HELD if offline is Offline.HOLD else _NO_COMMUNICATION


def write_status(exc: ModbusExceptionReply | None, *, elapsed: float, write_timeout: float, link_up: bool) -> Code:
    """A write's status from the write path's answer (None: the controller confirmed it).

    0x0B at ``write_timeout`` is Bad_Timeout (outcome unknown or withdrawn: the audit log says which),
    0x0B before it Bad_CommunicationError (the link is down or went down under it); 0x02 (read only,
    not in ``writable``) Bad_NotWritable; 0x03 (a value the controller cannot hold) Bad_OutOfRange;
    0x06 (the write queue is full) Bad_ResourceUnavailable; 0x04 (the controller refused) Bad_DeviceFailure.
    """
    if exc is None:
        return Code.GOOD
    code = exc.code
    if code == ModbusExceptionReply.GATEWAY_TARGET_FAILED:
        if link_up and elapsed >= write_timeout * 0.999:
            return Code.TIMEOUT
        return Code.COMMUNICATION_ERROR
    return {
        ModbusExceptionReply.ILLEGAL_DATA_ADDRESS: Code.NOT_WRITABLE,
        ModbusExceptionReply.ILLEGAL_DATA_VALUE: Code.OUT_OF_RANGE,
        ModbusExceptionReply.SERVER_DEVICE_BUSY: Code.BUSY,
        ModbusExceptionReply.GATEWAY_PATH_UNAVAILABLE: Code.COMMUNICATION_ERROR,
    }.get(code, Code.DEVICE_FAILURE)


def revise_interval(requested: float, publishing: float, period: float | None, achieved: float | None,
                    passes: float = 0.0) -> float:
    """The sampling interval (ms) given to a monitored item of a block.

    ``requested``: what the client asked (ms; 0 or less: the subscription's ``publishing`` interval, as
    Part 4 §5.12.1.2 says for -1); ``period``: the block's class period (s; None: not polled, its peer
    pushes); ``achieved``: the refresh period the line achieves for it (s; None: not measured yet);
    ``passes``: the seconds between the server's publishing passes for this subscription.
    The item is sampled no faster than its block is read, nor than the server looks at it.
    """
    wanted = requested if requested > 0 else publishing
    floor = max(period or 0.0, achieved or 0.0, passes) * 1000.0
    return max(wanted, floor) if math.isfinite(floor) else wanted


def pass_period(publish_interval: float, publishing: float, longest: float) -> float:
    """Seconds between the publishing passes for subscriptions whose shortest publishing interval is
    ``publishing`` (ms; 0: none): half of it, at least ``publish_interval``, at most ``longest``.  Each
    pass judges every block stored since the last one: passes further apart cost less for the same values,
    and a subscription is sent values at most half its interval old, besides the read's age."""
    return max(publish_interval, min(publishing / 2000.0, longest))


class DemandBook:
    """Monitored items' demand, noted per block: sans-I/O (module docstring).

    The server numbers its points and tells the book each point's block (``blocks``); demand is
    noted for a block (one key, as a Modbus read of the block would), at the shortest sampling
    interval of the items on its points, so that 150 monitored points of one block cost one note,
    not 150.  A block none of whose points has a monitored item any more is forgotten at once."""

    def __init__(self, blocks: Mapping[int, int]) -> None:
        #: point -> its block
        self._blocks = blocks
        #: per point with a live item: its shortest sampling interval (s)
        self._interval: dict[int, float] = {}
        #: per block with a live item: the shortest interval of its points' items, and when it is next noted
        self._block_interval: dict[int, float] = {}
        self._next: dict[int, float] = {}

    def watch(self, point: int, interval: float, now: float) -> None:
        """A monitored item of ``point`` was created (``interval``: its revised sampling interval, s)."""
        current = self._interval.get(point)
        self._interval[point] = interval if current is None else min(current, interval)
        block = self._blocks.get(point)
        if block is None:
            return
        current = self._block_interval.get(block)
        self._block_interval[block] = interval if current is None else min(current, interval)
        self._next[block] = now  # demanded at once: its first value is wanted now

    def settle(self, alive: Iterable[int], now: float) -> None:
        """The points that have a monitored item now: the others are forgotten (nobody holds their items
        any more), and each block's interval is the shortest of its living points'.  A living point the
        book was not told of (an item created before a reload) is demanded at once, then every pass."""
        living = set(alive)
        intervals = self._interval
        for gone in [point for point in intervals if point not in living]:
            del intervals[gone]
        for point in living - intervals.keys():
            intervals[point] = 0.0
            block = self._blocks.get(point)
            if block is not None:
                self._next[block] = now
        shortest: dict[int, float] = {}
        for point, interval in intervals.items():
            block = self._blocks.get(point)
            if block is not None and interval < shortest.get(block, math.inf):
                shortest[block] = interval
        self._block_interval = shortest
        self._next = {block: self._next.get(block, now) for block in shortest}

    def due(self, now: float) -> list[int]:
        """The blocks whose demand is due at ``now`` (each then next due its interval later)."""
        found: list[int] = []
        upcoming = self._next
        for block, interval in self._block_interval.items():
            if upcoming[block] <= now:
                found.append(block)
                upcoming[block] = now + interval
        return sorted(found)

    def __len__(self) -> int:
        """The points with a monitored item the book knows of."""
        return len(self._interval)
