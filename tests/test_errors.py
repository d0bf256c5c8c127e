"""One error model (issue 11): local vs remote errors, one table from error type to Modbus code.

The table (``gateway.errors.MODBUS_CODES``) is checked three ways: every error class of the
gateway (found by importing every module) answers the code the unit's table says for it; the
table in the ``gateway.errors`` docstring is the table in the code; and ``Unit``'s write path
(``_translated``) answers with it, the original error kept as the cause.
"""

from __future__ import annotations

import importlib
import pkgutil
import uuid
from collections.abc import Iterator

import pytest

import gateway
from gateway import errors
from gateway.errors import (
    MODBUS_CODES,
    ConfigError,
    ControllerFault,
    ControllerRefused,
    GatewayError,
    InvalidRequest,
    LinkDown,
    LinkError,
    LinkTimeout,
    LocalError,
    ModbusExceptionReply,
    ProtocolError,
    RemoteError,
    WriteOutcomeUnknown,
    modbus_code,
    modbus_exception,
)
from gateway.kinds.slc_ascii.driver import SlcAsciiDriver
from gateway.sim import get_simulator
from gateway.unit_writes import translated as _translated

ILLEGAL_ADDRESS, ILLEGAL_VALUE, DEVICE_FAILURE, TARGET_FAILED = 0x02, 0x03, 0x04, 0x0B

#: The unit's table (gateway/unit.py docstring), class by class: value out of range 0x03;
#: controller refused 0x04; no answer, link down, outcome unknown 0x0B.  A new error class
#: anywhere in gateway/ must be added here (and to the table if its parent's code is wrong).
#: By class name, not module, so that moving a module does not touch this test.
EXPECTED = {
    "GatewayError": DEVICE_FAILURE,
    "ConfigError": DEVICE_FAILURE,
    "LocalError": ILLEGAL_VALUE,
    "InvalidRequest": ILLEGAL_VALUE,
    "AddressError": ILLEGAL_VALUE,
    "RemoteError": TARGET_FAILED,
    "ProtocolError": TARGET_FAILED,
    "PcccFormatError": TARGET_FAILED,
    "LinkError": TARGET_FAILED,
    "LinkDown": TARGET_FAILED,
    "_LineSettingsRefused": TARGET_FAILED,
    "LinkTimeout": TARGET_FAILED,
    "WriteOutcomeUnknown": TARGET_FAILED,
    "ControllerRefused": DEVICE_FAILURE,
    "PcccError": DEVICE_FAILURE,
    "ControllerFault": DEVICE_FAILURE,
}


def _all_modules() -> Iterator[str]:
    for info in pkgutil.walk_packages(gateway.__path__, "gateway."):
        if not info.name.endswith("__main__"):  # runs the CLI when imported
            yield info.name


def _subclasses(cls: type[GatewayError]) -> Iterator[type[GatewayError]]:
    for sub in cls.__subclasses__():
        yield sub
        yield from _subclasses(sub)


def _instance(cls: type[GatewayError]) -> GatewayError:
    """An instance without calling a subclass's own constructor (some need protocol fields)."""
    error = cls.__new__(cls)
    Exception.__init__(error, f"a {cls.__name__}")
    return error


def test_every_error_class_of_the_gateway_answers_the_code_of_the_units_table() -> None:
    for name in _all_modules():
        importlib.import_module(name)
    replies = set(_subclasses(ModbusExceptionReply)) | {ModbusExceptionReply}
    classes = {c for c in _subclasses(GatewayError) if c.__module__.startswith("gateway.") and c not in replies}
    every: list[type[GatewayError]] = [GatewayError, *classes]
    found = {c.__qualname__: c for c in every}  # by name: modules may move
    assert len(found) == len(classes) + 1, "two error classes of one name"
    assert sorted(found) == sorted(EXPECTED), "a new error class: give it its code in EXPECTED (and MODBUS_CODES)"
    for name, cls in found.items():
        assert modbus_code(_instance(cls)) == EXPECTED[name], name


def test_local_and_remote_errors() -> None:
    assert issubclass(InvalidRequest, LocalError) and issubclass(InvalidRequest, ValueError)
    for cls in (ProtocolError, LinkError, LinkDown, LinkTimeout, WriteOutcomeUnknown, ControllerRefused,
                ControllerFault):
        assert issubclass(cls, RemoteError) and not issubclass(cls, LocalError), cls
    assert not issubclass(ConfigError, LocalError | RemoteError)
    # a write whose outcome is unknown is a timeout to code that only asks "did it answer?"
    assert issubclass(WriteOutcomeUnknown, LinkTimeout)
    from gateway.kinds.df1.full.driver import WriteOutcomeUnknown as reexported

    assert reexported is WriteOutcomeUnknown


def test_the_most_specific_entry_wins_and_a_subclass_inherits_its_parents_code() -> None:
    class Odd(ControllerRefused, LinkTimeout):  # refusal listed first in the MRO
        pass

    class Later(LinkTimeout):
        pass

    assert modbus_code(Odd("x")) == DEVICE_FAILURE
    assert modbus_code(Later("x")) == TARGET_FAILED
    assert modbus_code(ModbusExceptionReply(ILLEGAL_ADDRESS)) == ILLEGAL_ADDRESS


def test_the_docstring_table_is_the_table() -> None:
    doc = errors.__doc__ or ""
    rows: dict[str, int] = {}
    for line in doc.splitlines():
        parts = line.split()
        if len(parts) >= 2 and parts[0] in errors.__all__ and parts[1].startswith("0x"):
            rows[parts[0]] = int(parts[1], 16)
    assert rows == {cls.__name__: code for cls, code in MODBUS_CODES.items()}


def test_modbus_exception_keeps_the_message_and_passes_a_reply_through() -> None:
    reply = modbus_exception(LinkDown("link a is down: closed"))
    assert reply.code == TARGET_FAILED and str(reply) == "link a is down: closed"
    already = ModbusExceptionReply(ILLEGAL_ADDRESS, "N7:99 does not exist")
    assert modbus_exception(already) is already


@pytest.mark.parametrize(
    ("error", "code"),
    [
        (InvalidRequest("9999 < 12000"), ILLEGAL_VALUE),
        (ControllerRefused("refused", command="write"), DEVICE_FAILURE),
        (ControllerFault("fault", errors=(3,)), DEVICE_FAILURE),
        (LinkDown("down"), TARGET_FAILED),
        (LinkTimeout("no answer"), TARGET_FAILED),
        (WriteOutcomeUnknown("outcome unknown"), TARGET_FAILED),
        (ProtocolError("garbage"), TARGET_FAILED),
        (ConfigError("?"), DEVICE_FAILURE),
        (ModbusExceptionReply(ILLEGAL_ADDRESS, "no such file"), ILLEGAL_ADDRESS),
    ],
    ids=lambda v: type(v).__name__ if isinstance(v, Exception) else f"0x{v:02X}",
)
async def test_a_failed_write_is_answered_by_the_table(error: GatewayError, code: int) -> None:
    async def write() -> None:
        raise error

    with pytest.raises(ModbusExceptionReply) as answer:
        await _translated(write())
    assert answer.value.code == code
    if isinstance(error, ModbusExceptionReply):
        assert answer.value is error
    else:
        assert answer.value.__cause__ is error and str(error) in str(answer.value)


@pytest.mark.looptime  # a 10 ms reply timeout on real time fails on a loaded machine (the read before it
# answered late, and the write began with a resync that timed out)
async def test_an_slc_write_whose_replies_are_all_lost_is_outcome_unknown_and_answers_0x0B() -> None:
    url = f"sim://slc150?ladder=0&instance={uuid.uuid4().hex}"
    sim = get_simulator(url)
    driver = SlcAsciiDriver(url, timeout=0.01, retries=2)
    async with driver:
        await driver.read(0x40, 2)
        sim.faults.drop = 1
        with pytest.raises(ModbusExceptionReply) as answer:
            await _translated(driver.write_word(0x40, 1234))
    assert answer.value.code == TARGET_FAILED
    assert isinstance(answer.value.__cause__, WriteOutcomeUnknown)
    assert "outcome unknown" in str(answer.value)
    assert sim.applied_writes == [("word", 0x40, 1234)]  # sent once, applied once
