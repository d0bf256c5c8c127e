"""The one error hierarchy of slc-gateway, and the one table from error to Modbus exception code.

Errors are *local* or *remote*, as in h11 (``LocalProtocolError`` / ``RemoteProtocolError``) and
httpcore: a local error means we broke a rule, so the request was rejected before anything was
sent and sending it again unchanged fails again; a remote error means the controller or the line
broke a rule or failed, after (or while) something was sent.

::

    GatewayError
    +-- ConfigError                the configuration file is wrong (names the key path)
    +-- LocalError                 we broke a rule: rejected before anything was sent
    |   +-- InvalidRequest         a request breaks a rule of the protocol or the memory map
    |                              (also a ValueError; DF1's AddressError is one)
    +-- RemoteError                the controller or the line broke a rule or failed
    |   +-- ProtocolError          bytes on the wire that break the protocol (bad format, unexpected reply)
    |   +-- LinkError              the link to a controller failed
    |   |   +-- LinkDown           the port is closed or lost; reconnecting in the background
    |   |   +-- LinkTimeout        the controller did not answer in time (after retries)
    |   |       +-- WriteOutcomeUnknown  a write was sent (once) but nothing proved it applied or not
    |   +-- ControllerRefused      the controller answered with a refusal (;E, PCCC STS)
    |   +-- ControllerFault        the controller reported a fault (;T)
    +-- ModbusExceptionReply       the Modbus answer, already chosen (carries its own code)
        +-- StaleRead              0x0B for data not read yet or stale; the reader may wait for it

Each layer translates the errors of the layer below with ``raise ... from``.

Modbus exception codes (:data:`MODBUS_CODES`; :func:`modbus_code` walks the error's MRO, so the
most specific entry wins and a new subclass inherits its parent's code):

=======================  =====  ===============================================================
error                    code   why
=======================  =====  ===============================================================
GatewayError             0x04   anything else the gateway raised on purpose: server device failure
LocalError               0x03   the request breaks a rule: illegal data value
InvalidRequest           0x03   (e.g. a value out of range for the controller)
RemoteError              0x0B   the target did not do what was asked: gateway target failed
ProtocolError            0x0B   the reply was garbage: no answer
LinkError                0x0B   no answer: the link is down or the controller silent
LinkTimeout              0x0B
LinkDown                 0x0B
WriteOutcomeUnknown      0x0B   the write may have been applied (once): SCADA must read back
ControllerRefused        0x04   the controller answered and refused: server device failure
ControllerFault          0x04   the controller reported a fault
ModbusExceptionReply     its own ``code``
=======================  =====  ===============================================================

A protocol's unit may translate its refusals more finely before this table sees them (a PCCC
refusal naming a bad address answers 0x02: ``gateway.kinds.df1.unit.pccc_exception``).
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from typing import Final

__all__ = [
    "MODBUS_CODES",
    "ConfigError",
    "ControllerFault",
    "ControllerRefused",
    "GatewayError",
    "InvalidRequest",
    "LinkDown",
    "LinkError",
    "LinkTimeout",
    "LocalError",
    "ModbusExceptionReply",
    "ProtocolError",
    "RemoteError",
    "StaleRead",
    "WriteOutcomeUnknown",
    "format_seconds",
    "modbus_code",
    "modbus_exception",
]


class GatewayError(Exception):
    """Root of every error raised on purpose by slc-gateway."""


class ConfigError(GatewayError):
    """The configuration is invalid. The message names the key path (and line where known)."""


class LocalError(GatewayError):
    """We broke a rule: the request was rejected before anything was sent (h11's LocalProtocolError)."""


class RemoteError(GatewayError):
    """The controller or the line broke a rule or failed (h11's RemoteProtocolError)."""


class InvalidRequest(LocalError, ValueError):
    """A request broke a rule of the protocol or the memory map; nothing was sent."""


class ProtocolError(RemoteError):
    """Bytes that do not follow the protocol (bad CRC, bad format, unexpected reply)."""


class LinkError(RemoteError):
    """The link to a controller failed."""


class LinkDown(LinkError):
    """The port is closed or lost; the driver reconnects in the background."""


class LinkTimeout(LinkError):
    """No valid reply within the timeout, after every retry."""


class WriteOutcomeUnknown(LinkTimeout):
    """A write was sent (once, never again) but neither a reply nor a read-back proved whether it applied.

    Raised by every driver for the same situation (SLC 100/150: no reply after the resend rules
    ran out; DF1: a lost reply and no read-back that settles it).  A ``LinkTimeout``, so code
    that only cares whether the controller answered need not know it; answered Modbus 0x0B.

    ``shown``: what a read-back sent after the write gave, when it answered with another value
    than the one written (DF1 full duplex only: there the read-back runs after the write, so data
    equal to the value before the write proves the write was not applied; ``Unit`` retries it).
    """

    def __init__(self, message: str = "", *, shown: bytes | None = None) -> None:
        super().__init__(message)
        self.shown = shown


class ControllerRefused(RemoteError):
    """The controller answered with a refusal. ``reason`` is the manual's description."""

    def __init__(self, message: str, *, command: str = "", reason: str = "", code: int | None = None):
        super().__init__(message)
        self.command = command
        self.reason = reason
        self.code = code


class ControllerFault(RemoteError):
    """The controller reported a fault (SLC 100/150 ``;T``); ``errors`` are the manual's error numbers."""

    def __init__(self, message: str, *, errors: tuple[int, ...] = ()):
        super().__init__(message)
        self.errors = errors


class ModbusExceptionReply(GatewayError):
    """Answer the Modbus request with exception ``code`` (0x01..0x0B)."""

    ILLEGAL_FUNCTION = 0x01
    ILLEGAL_DATA_ADDRESS = 0x02
    ILLEGAL_DATA_VALUE = 0x03
    SERVER_DEVICE_FAILURE = 0x04
    SERVER_DEVICE_BUSY = 0x06
    GATEWAY_PATH_UNAVAILABLE = 0x0A
    GATEWAY_TARGET_FAILED = 0x0B

    def __init__(self, code: int, message: str = ""):
        super().__init__(message or f"Modbus exception 0x{code:02X}")
        self.code = code


class StaleRead(ModbusExceptionReply):
    """0x0B for data not read yet or stale, on a link that is up: the reader may wait for it.

    ``wait()`` asks for an immediate read of the data's blocks and returns an awaitable that is
    done when they were read (or failed, or the link was lost); a reader that may wait at most
    ``read_wait`` seconds for it and reads again after.  One that does not wait (the status page)
    answers the 0x0B at once; nothing is asked of the line until ``wait()`` is called.
    """

    def __init__(self, message: str, wait: Callable[[], Awaitable[None]], read_wait: float) -> None:
        super().__init__(ModbusExceptionReply.GATEWAY_TARGET_FAILED, message)
        self.wait = wait
        self.read_wait = read_wait
        #: what the link's ``offline`` policy serves once the wait is over and the data still not
        #: fresh (None: this exception)
        self.held: bytes | None = None


#: Error type -> Modbus exception code (the table of the module docstring).  Looked up along the
#: MRO of the error: the most specific class listed wins.
MODBUS_CODES: Final[dict[type, int]] = {
    GatewayError: ModbusExceptionReply.SERVER_DEVICE_FAILURE,
    LocalError: ModbusExceptionReply.ILLEGAL_DATA_VALUE,
    InvalidRequest: ModbusExceptionReply.ILLEGAL_DATA_VALUE,
    RemoteError: ModbusExceptionReply.GATEWAY_TARGET_FAILED,
    ProtocolError: ModbusExceptionReply.GATEWAY_TARGET_FAILED,
    LinkError: ModbusExceptionReply.GATEWAY_TARGET_FAILED,
    LinkTimeout: ModbusExceptionReply.GATEWAY_TARGET_FAILED,
    LinkDown: ModbusExceptionReply.GATEWAY_TARGET_FAILED,
    WriteOutcomeUnknown: ModbusExceptionReply.GATEWAY_TARGET_FAILED,
    ControllerRefused: ModbusExceptionReply.SERVER_DEVICE_FAILURE,
    ControllerFault: ModbusExceptionReply.SERVER_DEVICE_FAILURE,
}


def modbus_code(error: GatewayError) -> int:
    """The Modbus exception code that answers ``error`` (its own for a ``ModbusExceptionReply``)."""
    if isinstance(error, ModbusExceptionReply):
        return error.code
    for cls in type(error).__mro__:
        code = MODBUS_CODES.get(cls)
        if code is not None:
            return code
    raise AssertionError("unreachable: every GatewayError has an entry along its MRO")


def modbus_exception(error: GatewayError) -> ModbusExceptionReply:
    """``error`` as the Modbus answer: itself if already one, else a reply with its code and message."""
    if isinstance(error, ModbusExceptionReply):
        return error
    return ModbusExceptionReply(modbus_code(error), str(error))


def format_seconds(value: float) -> str:
    """A duration for people, to 10 ms: ``0.359375`` -> ``"0.36"``, ``3.05729`` -> ``"3.06"``, ``1.0`` -> ``"1"``."""
    return f"{value:.2f}".rstrip("0").rstrip(".") if value >= 0.005 else f"{value:.2g}"
