"""A half-duplex line driver on the multi-drop simulator over an in-memory stream, for the driver's tests."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from gateway.kinds.df1.half.driver import Df1HalfDuplexLine
from gateway.kinds.df1.sim.df1_multidrop import MultidropLine
from gateway.protocols.df1.address import FileType
from gateway.protocols.df1.half_duplex.events import StationConfig
from gateway.sim.serve import SimStream
from gateway.transport import ByteStream

N = FileType.INTEGER


def opener_for(line: MultidropLine) -> Any:
    async def opener(url: str, settings: object, **_: object) -> ByteStream:
        return SimStream(line)

    return opener


class PullableStream(SimStream):
    """A simulator stream whose cable a test can pull: ``lost(reason)`` is the transport's own callback."""

    lost: Callable[[str], None]

    def start_push(self, receive: Callable[[bytes], None], lost: Callable[[str], None]) -> bool:
        self.lost = lost
        return super().start_push(receive, lost)


def stations(*numbers: int, demote_after: int = 3, reply_timeout: float = 1.0,
             slow_poll_interval: float = 2.0) -> list[StationConfig]:
    return [
        StationConfig(n, poll_timeout=0.05, reply_timeout=reply_timeout, demote_after=demote_after, poll_interval=0.2,
                      slow_poll_interval=slow_poll_interval)
        for n in numbers
    ]


def make_driver(
    line: MultidropLine,
    numbers: tuple[int, ...],
    *,
    demote_after: int = 3,
    reply_timeout: float = 1.0,
    first_tns: int = 1,
    **kwargs: Any,
) -> Df1HalfDuplexLine:
    return Df1HalfDuplexLine(
        "sim://line", stations(*numbers, demote_after=demote_after, reply_timeout=reply_timeout), name="line",
        checksum=line.options.checksum, ack_timeout=0.05,
        message_retries=3, retries=3, opener=opener_for(line), first_tns=first_tns, **kwargs,
    )


def seed(line: MultidropLine) -> None:
    for number, controller in line.controllers.items():
        for element in range(10):
            controller.set_word("N7", element, 1000 * number + element)


def expected(station: int) -> bytes:
    return b"".join((1000 * station + k).to_bytes(2, "little") for k in range(5))
