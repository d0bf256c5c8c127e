"""The SLC 100/150 program transfer core (sans-I/O), driven with scripted replies.

The controller is a script: each command the core asks for gets the next scripted answer or
error.  A power cycle mid-upload shows as block 0 where another was expected; a lost reply as a
``LinkTimeout`` from the transaction below.  Restarts are bounded and a download that cannot
finish names its block.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Iterable

import pytest

from gateway.errors import (
    ControllerRefused,
    GatewayError,
    InvalidRequest,
    LinkDown,
    LinkTimeout,
    ProtocolError,
    WriteOutcomeUnknown,
)
from gateway.protocols.slc_ascii import commands as cmds
from gateway.protocols.slc_ascii.commands import BLOCK_SIZE, Command, CommandCode, ControllerType, Mode
from gateway.protocols.slc_ascii.framing import Ack, DataReply
from gateway.protocols.slc_ascii.transfer import MAX_TRANSFER_RESTARTS, Download, Restart, TransferState, Upload

SLC100 = ControllerType.SLC100
BLOCKS = SLC100.block_count
PROGRAM = bytes((i * 37 + 11) & 0xFF for i in range(BLOCKS * BLOCK_SIZE - 8)) + bytes(8)
MODE_PROGRAM = cmds.set_mode(Mode.PROGRAM)
_ids = itertools.count(1)

Answer = Ack | DataReply
Reply = Answer | GatewayError
Controller = Callable[[Command], Reply]


def block_reply(block: int, program: bytes = PROGRAM) -> DataReply:
    data = program[block * BLOCK_SIZE : (block + 1) * BLOCK_SIZE]
    return DataReply(f"{block:02X}{data.hex().upper()}", next(_ids) & 0xFF)


def ack() -> Ack:
    return Ack(next(_ids) & 0xFF)


class ScriptedSlc:
    """A controller with a block pointer, program mode, and faults scheduled by command number."""

    def __init__(self, faults: dict[int, str] | None = None) -> None:
        self.pointer = 0
        self.faults = dict(faults or {})
        self.sent: list[Command] = []
        self.stored: dict[int, bytes] = {}

    def __call__(self, command: Command) -> Reply:
        n = len(self.sent)
        self.sent.append(command)
        fault = self.faults.get(n)
        if fault == "power cycle":
            self.pointer = 0
        if command == MODE_PROGRAM:
            self.pointer = 0
            return LinkTimeout("mode change lost") if fault == "lose" else ack()
        if command.code == CommandCode.UPLOAD:
            block = self.pointer
            self.pointer += 1
            return LinkTimeout("no valid answer") if fault == "lose" else block_reply(block)
        assert command.code == CommandCode.DOWNLOAD
        block = command.params[0]
        if fault == "lose":
            return WriteOutcomeUnknown("outcome unknown")
        if fault == "refuse" or block != self.pointer:
            return ControllerRefused("refused", command=command.name)
        self.stored[block] = command.params[1:]
        self.pointer += 1
        return ack()


def run(transfer: Upload | Download, controller: Controller) -> list[Restart]:
    """The driver's loop, without I/O."""
    restarts: list[Restart] = []
    for _ in range(100_000):
        command = transfer.next_command()
        if command is None:
            return restarts
        reply = controller(command)
        if isinstance(reply, GatewayError):
            if not isinstance(reply, transfer.restart_on):
                raise reply
            restarts.append(transfer.failed(reply))
        elif (restart := transfer.answered(reply)) is not None:
            restarts.append(restart)
    raise AssertionError("the transfer never ends")


def codes(sent: Iterable[Command]) -> list[str]:
    return ["P" if c == MODE_PROGRAM else f"{c.code:02X}" for c in sent]


# --- upload ---------------------------------------------------------------------------------


def test_a_clean_upload_is_every_block_in_order_one_command_each() -> None:
    slc = ScriptedSlc()
    upload = Upload(SLC100)
    assert run(upload, slc) == []
    assert upload.program == PROGRAM and upload.done
    assert codes(slc.sent) == ["00"] * BLOCKS
    assert upload.next_command() is None


def test_a_power_cycle_mid_upload_restarts_from_block_0_without_a_mode_change() -> None:
    slc = ScriptedSlc({50: "power cycle"})
    upload = Upload(SLC100)
    restarts = run(upload, slc)
    assert upload.program == PROGRAM
    assert restarts == [Restart("upload", 50, "expected block 0x32, got 0x00", 1)]
    # the block 0 of the new pass is kept: no command is sent twice for it, and no mode change
    assert codes(slc.sent) == ["00"] * (50 + BLOCKS)


def test_a_lost_upload_reply_reenters_program_mode_and_restarts() -> None:
    slc = ScriptedSlc({20: "lose"})
    upload = Upload(SLC100)
    restarts = run(upload, slc)
    assert upload.program == PROGRAM
    assert [(r.block, r.reason) for r in restarts] == [(20, "no valid answer")]
    assert codes(slc.sent) == ["00"] * 21 + ["P"] + ["00"] * BLOCKS


def test_an_unexpected_block_other_than_0_reenters_program_mode() -> None:
    upload = Upload(SLC100)
    assert upload.answered(block_reply(0)) is None
    restart = upload.answered(block_reply(5))
    assert restart is not None and restart.reason == "expected block 0x01, got 0x05"
    assert upload.state is TransferState.PROGRAM and upload.next_command() == MODE_PROGRAM
    assert upload.answered(ack()) is None
    assert upload.next_command() == cmds.upload_block() and upload.block == 0


def test_upload_restarts_are_bounded_and_the_error_says_what_to_do() -> None:
    upload = Upload(SLC100, max_restarts=3)
    last = LinkTimeout("no valid answer (4)")
    for n in range(3):
        assert upload.next_command() == cmds.upload_block()
        upload.failed(LinkTimeout(f"no valid answer ({n + 1})"))
        assert upload.next_command() == MODE_PROGRAM
        upload.answered(ack())
    gave_up = r"upload: gave up after 3 restarts \(no valid answer \(4\)\); check"
    with pytest.raises(ProtocolError, match=gave_up) as exc:
        upload.failed(last)
    assert exc.value.__cause__ is last
    with pytest.raises(InvalidRequest, match="0 of 123 blocks"):
        _ = upload.program


def test_upload_power_cycling_forever_gives_up_after_the_default_bound() -> None:
    slc = ScriptedSlc({n: "power cycle" for n in range(10, 100_000, 10)})
    with pytest.raises(ProtocolError, match=f"gave up after {MAX_TRANSFER_RESTARTS} restarts"):
        run(Upload(SLC100), slc)
    assert len(slc.sent) == 10 * (MAX_TRANSFER_RESTARTS + 1) + 1  # the 11th power cycle ends it


def test_a_failed_mode_change_ends_the_upload_with_its_error() -> None:
    slc = ScriptedSlc({3: "lose", 4: "lose"})  # block 3 lost, then the mode change too
    with pytest.raises(LinkTimeout, match="mode change lost"):
        run(Upload(SLC100), slc)


def test_an_acknowledge_to_an_upload_is_a_protocol_error() -> None:
    with pytest.raises(ProtocolError, match="expected a data reply"):
        Upload(SLC100).answered(ack())


# --- download -------------------------------------------------------------------------------


def test_a_clean_download_sends_every_block_once_in_order() -> None:
    slc = ScriptedSlc()
    download = Download(SLC100, PROGRAM)
    assert run(download, slc) == []
    assert download.done and download.next_command() is None
    assert [c.params[0] for c in slc.sent] == list(range(BLOCKS))
    assert b"".join(slc.stored[b] for b in range(BLOCKS)) == PROGRAM


@pytest.mark.parametrize("fault", ["lose", "refuse", "power cycle"])
def test_a_failed_block_restarts_the_download_from_block_0_after_program_mode(fault: str) -> None:
    slc = ScriptedSlc({40: fault})
    download = Download(SLC100, PROGRAM)
    restarts = run(download, slc)
    assert [r.block for r in restarts] == [40]
    assert codes(slc.sent) == ["01"] * 41 + ["P"] + ["01"] * BLOCKS
    assert b"".join(slc.stored[b] for b in range(BLOCKS)) == PROGRAM


def test_a_download_that_cannot_finish_names_the_block() -> None:
    slc = ScriptedSlc({n: "power cycle" for n in range(30, 100_000, 31)})  # every 30th block, after the mode
    with pytest.raises(GatewayError, match=rf"download failed at block 0x1D of {BLOCKS} after "
                       rf"{MAX_TRANSFER_RESTARTS} restarts: .*run the download again") as exc:
        run(Download(SLC100, PROGRAM), slc)
    assert isinstance(exc.value.__cause__, ControllerRefused)
    assert codes(slc.sent).count("P") == MAX_TRANSFER_RESTARTS


def test_a_lost_link_is_not_retried_by_the_core() -> None:
    # LinkDown is no restart reason: the driver lets it end the transfer (the link reconnects).
    assert not issubclass(LinkDown, Upload.restart_on) and not issubclass(LinkDown, Download.restart_on)
    slc = ScriptedSlc()

    def down_at_7(command: Command) -> Reply:
        return LinkDown("gone") if len(slc.sent) == 7 else slc(command)

    with pytest.raises(LinkDown):
        run(Download(SLC100, PROGRAM), down_at_7)


def test_a_program_of_the_wrong_size_is_refused_before_anything_is_sent() -> None:
    with pytest.raises(InvalidRequest, match=r"a SLC100 program is 1845 bytes, got 1844"):
        Download(SLC100, PROGRAM[:-1])
    with pytest.raises(InvalidRequest, match="fill and must be zero"):
        Download(SLC100, PROGRAM[:-1] + b"\x01")


def test_no_transition_out_of_done() -> None:
    download = Download(SLC100, PROGRAM)
    run(download, ScriptedSlc())
    with pytest.raises(AssertionError):
        download.answered(ack())


def test_a_block_number_beyond_the_controllers_last_is_a_protocol_error_not_a_restart() -> None:
    """No pass of an SLC 100 upload has a block past its last: such a reply is not a power cycle
    or a lost reply to recover from, it is not this controller's answer."""
    upload = Upload(SLC100)
    assert upload.answered(block_reply(0)) is None
    beyond = DataReply(f"{SLC100.last_block + 1:02X}" + "00" * BLOCK_SIZE, 1)
    with pytest.raises(ProtocolError, match="beyond the last"):
        upload.answered(beyond)
