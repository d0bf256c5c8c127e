"""``[[link]]`` keys: the line keys of a half-duplex line (``retries`` among them), one default
for ``retries``, and the ``down_after_*`` keys reaching every DF1 driver.
"""

from __future__ import annotations

import inspect
import re

import pytest

from gateway.config import parse_config
from gateway.config.link import DEFAULT_RETRIES, LinkBase
from gateway.errors import ConfigError
from gateway.kinds.df1.build import build_df1
from gateway.kinds.df1.config import LINE_KEYS
from gateway.kinds.df1.driver import Df1Driver
from gateway.kinds.df1.half_duplex_driver import Df1HalfDuplexLine
from gateway.kinds.slc_ascii.driver import SlcAsciiDriver
from gateway.link_health import DEFAULT_DOWN_AFTER

MAP = '\n[[link.map]]\ntable = "holding"\nstart = 0\naddress = "N7:0"\ncount = 4\n'


def half(name: str = "s1", unit: int = 1, station: int = 1, extra: str = "") -> str:
    return (f'[[link]]\nname = "{name}"\nprotocol = "df1"\nport = "sim://df1line"\nunit = {unit}\n'
            f'duplex = "half"\nstation = {station}\n{extra}' + MAP)


def full(extra: str = "") -> str:
    return f'[[link]]\nname = "d"\nprotocol = "df1"\nport = "sim://slc504"\nunit = 1\n{extra}' + MAP


def error_of(text: str) -> str:
    with pytest.raises(ConfigError) as info:
        parse_config(text)
    return str(info.value)


# --- line keys across the links of a half-duplex line -------------------------------------------


def test_retries_is_a_line_key() -> None:
    assert "retries" in LINE_KEYS
    text = half("s1", 1, 1, "retries = 2\n") + half("s2", 2, 2, "retries = 5\n")
    assert error_of(text) == (
        '<string>:22: link "s2" (link[1]).retries: link "s2" and link "s1" (link[0]) share the half-duplex line on '
        "sim://df1line but give retries = 5 and 2: one line has one retries; give both the same"
    )
    config = parse_config(half("s1", 1, 1, "retries = 2\n") + half("s2", 2, 2, "retries = 2\n"))
    assert build_df1(config.link).runners[0].retries == 2  # type: ignore[attr-defined]


def test_every_setting_the_line_master_takes_from_the_first_link_is_a_line_key() -> None:
    """``build_line`` gives the master the first link's values: each must be checked equal across the
    line (its arguments that are not per station are named after LINE_KEYS, or are derived from them)."""
    from gateway.kinds.df1 import build

    taken = set(re.findall(r"\bfirst\.(\w+)", inspect.getsource(build.build_line)))
    derived = {"port": "the line's grouping key", "line_settings": "baudrate, bytesize, parity, stopbits"}
    assert "retries" in taken and taken - set(derived) <= set(LINE_KEYS), taken - set(LINE_KEYS)
    assert {"baudrate", "bytesize", "parity", "stopbits"} <= set(LINE_KEYS)


# --- defaults in one place ---------------------------------------------------------------------


def test_the_drivers_default_retries_is_the_configs() -> None:
    from gateway import tools_common

    assert LinkBase.model_fields["retries"].default == DEFAULT_RETRIES
    for driver in (SlcAsciiDriver, Df1Driver, Df1HalfDuplexLine):
        assert inspect.signature(driver).parameters["retries"].default is DEFAULT_RETRIES, driver
    assert tools_common.DEFAULT_RETRIES is DEFAULT_RETRIES
    from gateway.protocols.df1.write_verdict import DEFAULT_RETRIES as core_default

    assert core_default == DEFAULT_RETRIES  # the sans-I/O cores' own default (what they get is passed)


def test_down_after_keys_reach_every_df1_driver() -> None:
    assert LinkBase.model_fields["down_after_failures"].default == DEFAULT_DOWN_AFTER.failures
    assert LinkBase.model_fields["down_after_seconds"].default == DEFAULT_DOWN_AFTER.seconds
    keys = "down_after_failures = 7\ndown_after_seconds = 12.5\n"
    config = parse_config(
        full(keys) + half("s1", 2, 1, keys) + half("s2", 3, 2, "down_after_failures = 2\n")
    )
    built = build_df1(config.link)
    drivers = [unit.driver for unit in built.units]
    assert [(d.down_after_failures, d.down_after_seconds) for d in drivers] == [(7, 12.5), (7, 12.5), (2, 5.0)]
    assert isinstance(built.runners[1], Df1Driver) and built.runners[1] is drivers[0]
