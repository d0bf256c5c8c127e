"""The one error hierarchy of slc-gateway.

::

    GatewayError
    +-- ConfigError            the configuration file is wrong (names the key path)
    +-- ProtocolError          bytes on the wire that break the protocol (local decoding)
    +-- LinkError              the link to a controller failed
    |   +-- LinkDown           the port is closed or lost; reconnecting in the background
    |   +-- LinkTimeout        the controller did not answer in time (after retries)
    +-- ControllerRefused      the controller answered with a refusal (;E, PCCC STS)
    +-- ControllerFault        the controller reported a fault (;T)
    +-- InvalidRequest         a request was rejected before anything was sent
    +-- ModbusExceptionReply   a Modbus request answered with an exception code

Each layer translates the errors of the layer below with ``raise ... from``.
"""

from __future__ import annotations

__all__ = [
    "ConfigError",
    "ControllerFault",
    "ControllerRefused",
    "GatewayError",
    "InvalidRequest",
    "LinkDown",
    "LinkError",
    "LinkTimeout",
    "ModbusExceptionReply",
    "ProtocolError",
    "format_seconds",
]


class GatewayError(Exception):
    """Root of every error raised on purpose by slc-gateway."""


class ConfigError(GatewayError):
    """The configuration is invalid. The message names the key path (and line where known)."""


class ProtocolError(GatewayError):
    """Bytes that do not follow the protocol (bad CRC, bad format, unexpected reply)."""


class InvalidRequest(GatewayError, ValueError):
    """A request broke a rule of the protocol or the memory map; nothing was sent."""


class LinkError(GatewayError):
    """The link to a controller failed."""


class LinkDown(LinkError):
    """The port is closed or lost; the driver reconnects in the background."""


class LinkTimeout(LinkError):
    """No valid reply within the timeout, after every retry."""


class ControllerRefused(GatewayError):
    """The controller answered with a refusal. ``reason`` is the manual's description."""

    def __init__(self, message: str, *, command: str = "", reason: str = "", code: int | None = None):
        super().__init__(message)
        self.command = command
        self.reason = reason
        self.code = code


class ControllerFault(GatewayError):
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


def format_seconds(value: float) -> str:
    """A duration for people, to 10 ms: ``0.359375`` -> ``"0.36"``, ``3.05729`` -> ``"3.06"``, ``1.0`` -> ``"1"``."""
    return f"{value:.2f}".rstrip("0").rstrip(".") if value >= 0.005 else f"{value:.2g}"
