"""SLC 100/150 program upload and download, sans-I/O: the block order and the restart rules.

Manual: "SLC Programmable Controller Communications Protocol", *Upload and Download*: ``#0100``
returns the next program block (with its number) and moves the controller's block pointer on;
``#1101 <block> <15 bytes>`` stores one block; blocks go "in sequential order", in program mode,
and "the user can reset the procedure by re-entering the Program mode".

The caller (the driver) owns the line; it runs each command the core asks for and feeds back
the answer or the error, and logs the restarts the core reports::

    transfer = Upload(ControllerType.SLC150)          # or Download(controller, program)
    while (command := transfer.next_command()) is not None:
        try:
            answer = run(command)                     # one transaction (retries are below this)
        except transfer.restart_on as error:
            restart = transfer.failed(error)          # a Restart, or raises when out of restarts
        else:
            restart = transfer.answered(answer)       # a Restart or None
    program = transfer.program                        # Upload: every block, in order

Rules:

* **Never silently partial.**  A block that is lost, answered out of order, or whose outcome
  the line left unknown restarts the transfer from block 0; at most ``max_restarts`` restarts,
  then the error names the block (download: the controller's program is incomplete, run it
  again).
* **Upload after a power cycle.**  A reply carrying block 0 where another was expected means
  the controller's pointer restarted (a power cycle): it is block 0 of a new pass and is kept,
  no mode change needed.  Any other surprise (an unexpected block, a lost reply: the pointer may
  have moved) re-enters program mode first, which resets the pointer.
* **Download** re-enters program mode before every restart (a power cycle resets the pointer;
  a block whose ``;R`` was lost may or may not be stored).
* A failure of the mode change itself, and any error not in ``restart_on`` (the link is down,
  the controller refuses the mode change), ends the transfer with that error.

States and transitions (the only ones; anything else is a bug and raises ``AssertionError``)::

    state       event     ->  state
    ---------   --------      ---------
    BLOCK       answered      BLOCK | DONE        (the expected block; the last one: DONE)
    BLOCK       answered      BLOCK | PROGRAM     (upload, unexpected block: restart)
    BLOCK       failed        PROGRAM             (restart; upload keeps no pointer guess)
    PROGRAM     answered      BLOCK               (program mode re-entered: block 0 next)
    PROGRAM     failed        (raises the error)
"""

from __future__ import annotations

import enum
from abc import ABC, abstractmethod
from typing import Final

from gateway.errors import ControllerRefused, GatewayError, InvalidRequest, LinkTimeout, ProtocolError, RemoteError
from gateway.frozen import frozen
from gateway.protocols.slc_ascii import commands as cmds
from gateway.protocols.slc_ascii.commands import BLOCK_SIZE, Command, ControllerType, Mode
from gateway.protocols.slc_ascii.framing import Ack, DataReply

__all__ = ["MAX_TRANSFER_RESTARTS", "Download", "Restart", "TransferState", "Upload"]

#: Restarts from block 0 (after a power cycle, a lost block) before a transfer gives up.
MAX_TRANSFER_RESTARTS: Final = 10

Answer = Ack | DataReply


class TransferState(enum.Enum):
    BLOCK = "block"  # the next block command is due
    PROGRAM = "program"  # re-entering program mode before block 0
    DONE = "done"


#: The allowed transitions (state -> states it may go to), checked on every change.
_TRANSITIONS: Final = {
    TransferState.BLOCK: frozenset({TransferState.BLOCK, TransferState.PROGRAM, TransferState.DONE}),
    TransferState.PROGRAM: frozenset({TransferState.BLOCK}),
    TransferState.DONE: frozenset[TransferState](),
}


@frozen
class Restart:
    """The transfer starts again from block 0 (for the driver's log)."""

    transfer: str  # "upload" or "download"
    block: int  # the block that was due
    reason: str
    restarts: int  # restarts so far, this one included


class _Transfer(ABC):
    """What upload and download share: the state, the restart count, the mode change."""

    name = ""
    #: the errors of one transaction that restart the transfer (others end it)
    restart_on: tuple[type[GatewayError], ...] = ()

    def __init__(self, controller: ControllerType, max_restarts: int) -> None:
        if not isinstance(controller, ControllerType):
            raise InvalidRequest(f"controller {controller!r} is not a ControllerType")
        self.controller = controller
        self.max_restarts = max_restarts
        self.restarts = 0
        self.state = TransferState.BLOCK
        #: the block due next (0-based)
        self.block = 0

    @property
    def done(self) -> bool:
        return self.state is TransferState.DONE

    def _go(self, state: TransferState) -> None:
        assert state in _TRANSITIONS[self.state], f"{self.name}: {self.state.name} -> {state.name}"
        self.state = state

    def _mode_command(self) -> Command:
        return cmds.set_mode(Mode.PROGRAM)

    def _restart(self, reason: str, error: GatewayError | None, *, reenter: bool = True) -> Restart:
        """Count a restart from block 0; raise when out of restarts."""
        failed = self.block
        self.restarts += 1
        if self.restarts > self.max_restarts:
            raise self._give_up(reason) from error
        self.block = 0
        self._go(TransferState.PROGRAM if reenter else TransferState.BLOCK)
        return Restart(self.name, failed, reason, self.restarts)

    @abstractmethod
    def _give_up(self, reason: str) -> GatewayError:
        """The error that ends the transfer after the last restart (``reason``: the last failure)."""

    @abstractmethod
    def next_command(self) -> Command | None:
        """The command to run next; None when the transfer is complete."""

    @abstractmethod
    def answered(self, answer: Answer) -> Restart | None:
        """The answer to the command of ``next_command``; a ``Restart`` when it starts over."""

    def failed(self, error: GatewayError) -> Restart:
        """The last command failed with ``error`` (one of ``restart_on``): restart or give up."""
        if self.state is TransferState.PROGRAM:
            raise error  # the mode change failed: nothing to restart from
        assert self.state is TransferState.BLOCK, self.state
        return self._restart(str(error), error)


class Upload(_Transfer):
    """Every program block of ``controller`` in order, restarting from block 0 when one is lost."""

    name = "upload"
    restart_on = (LinkTimeout, ProtocolError)

    def __init__(self, controller: ControllerType, *, max_restarts: int = MAX_TRANSFER_RESTARTS) -> None:
        super().__init__(controller, max_restarts)
        self._blocks = bytearray()

    @property
    def program(self) -> bytes:
        """The program uploaded (``block_count * 15`` bytes; the last 8 are fill)."""
        if not self.done:
            raise InvalidRequest(f"upload: {self.block} of {self.controller.block_count} blocks so far")
        return bytes(self._blocks)

    def next_command(self) -> Command | None:
        if self.state is TransferState.PROGRAM:
            return self._mode_command()
        if self.state is TransferState.BLOCK:
            return cmds.upload_block()
        return None

    def answered(self, answer: Answer) -> Restart | None:
        if self.state is TransferState.PROGRAM:
            self._go(TransferState.BLOCK)
            return None
        assert self.state is TransferState.BLOCK, self.state
        if not isinstance(answer, DataReply):
            raise ProtocolError("upload: expected a data reply, got an acknowledge")
        got = cmds.parse_upload_reply(answer.body_hex, controller=self.controller)
        if got.block == self.block:
            self._blocks += got.data
            self.block += 1
            self._go(TransferState.DONE if self.block == self.controller.block_count else TransferState.BLOCK)
            return None
        reason = f"expected block 0x{self.block:02X}, got 0x{got.block:02X}"
        if got.block == 0:
            # A power cycle restarted the controller's pointer: this is block 0 of a new pass.
            restart = self._restart(reason, None, reenter=False)
            self._blocks = bytearray(got.data)
            self.block = 1
            return restart
        self._blocks = bytearray()
        return self._restart(reason, None)

    def failed(self, error: GatewayError) -> Restart:
        restart = super().failed(error)
        self._blocks = bytearray()  # the controller's pointer may have moved
        return restart

    def _give_up(self, reason: str) -> GatewayError:
        return ProtocolError(f"upload: gave up after {self.max_restarts} restarts ({reason}); "
                             "check the line and try again")


class Download(_Transfer):
    """Download ``program`` (``block_count * 15`` bytes) block by block, in program mode."""

    name = "download"
    restart_on = (LinkTimeout, ControllerRefused, ProtocolError)

    def __init__(
        self, controller: ControllerType, program: bytes, *, max_restarts: int = MAX_TRANSFER_RESTARTS
    ) -> None:
        super().__init__(controller, max_restarts)
        size = controller.block_count * BLOCK_SIZE
        if len(program) != size:
            raise InvalidRequest(f"download: a {controller.name} program is {size} bytes, got {len(program)}")
        self._commands = [
            cmds.download_block(block, program[block * BLOCK_SIZE : (block + 1) * BLOCK_SIZE], controller=controller)
            for block in range(controller.block_count)
        ]

    def next_command(self) -> Command | None:
        if self.state is TransferState.PROGRAM:
            return self._mode_command()
        if self.state is TransferState.BLOCK:
            return self._commands[self.block]
        return None

    def answered(self, answer: Answer) -> Restart | None:
        if self.state is TransferState.BLOCK:
            self.block += 1
            self._go(TransferState.DONE if self.block == len(self._commands) else TransferState.BLOCK)
        else:
            assert self.state is TransferState.PROGRAM, self.state
            self._go(TransferState.BLOCK)
        return None

    def _give_up(self, reason: str) -> GatewayError:
        return RemoteError(
            f"download failed at block 0x{self.block:02X} of {len(self._commands)} after {self.max_restarts} "
            f"restarts: {reason}; the controller's program is incomplete (a download clears it): "
            "run the download again"
        )
