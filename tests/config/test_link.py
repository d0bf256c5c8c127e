"""Each link kind uses every ``[[link]]`` key it accepts, in each of its modes.

A kind declares the keys it does not use, per mode (``LinkBase.mode_key`` / ``unused_keys``); such a
key given in the file is refused, naming the kind's protocol and mode.  Every other key is read when
the kind builds its units (checked here by watching the attribute reads of the link's model).
Also: the line keys of a half-duplex line (``retries`` among them), one default for ``retries``,
and the processor families by name.
"""

from __future__ import annotations

import inspect
import re
import tempfile
from pathlib import Path
from typing import Any, get_args

import pytest

from gateway.config import parse_config
from gateway.config.link import DEFAULT_RETRIES, LinkBase
from gateway.config.links import link_models, protocol_of
from gateway.errors import ConfigError
from gateway.kinds import link_kind
from gateway.kinds.df1.build import build_df1
from gateway.kinds.df1.config import LINE_KEYS, Df1LinkConfig, Processor
from gateway.kinds.df1.full.driver import Df1Driver
from gateway.kinds.df1.half.driver import Df1HalfDuplexLine
from gateway.kinds.df1.unit import PROCESSORS
from gateway.kinds.slc_ascii.driver import SlcAsciiDriver
from gateway.link_health import DEFAULT_DOWN_AFTER
from gateway.protocols.df1.pccc import ProcessorFamily

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


# --- keys a kind does not use in a mode ---------------------------------------------------------


def test_write_burst_on_a_half_duplex_link_is_refused_naming_the_kind_and_mode() -> None:
    text = half(extra="write_burst = 4\n")
    assert error_of(text) == (
        '<string>:8: link "s1" (link[0]).write_burst: not used by df1 links with duplex = "half" (the line master '
        "schedules writes; see docs/guide/df1-half-duplex.md)"
    )
    assert 'link "s1" (link[0]).poll_burst: not used by df1 links with duplex = "half"' in error_of(
        half(extra="poll_burst = 1\n")
    )
    assert parse_config(full(extra="write_burst = 4\npoll_burst = 3\n")).link[0].write_burst == 4


TARGET_KEYS = ("file", "persist", "check_dst")


@pytest.mark.parametrize("key", sorted(set(Df1LinkConfig.unused_keys["full"]) - set(TARGET_KEYS)))
def test_half_duplex_keys_on_a_full_duplex_link_are_refused(key: str) -> None:
    value = Df1LinkConfig.model_fields[key].default
    message = error_of(full(extra=f"{key} = {_toml(value)}\n"))
    assert f'<string>:6: link "d" (link[0]).{key}: not used by df1 links with duplex = "full" (a half-duplex ' in (
        message
    )
    # the same key, with the same value, on a station of a half-duplex line
    assert getattr(parse_config(half(extra=f"{key} = {_toml(value)}\n")).link[0], key) == value


def _toml(value: object) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return f'"{value}"'
    return repr(value)


@pytest.mark.parametrize("mode", ["full", "half"])
def test_a_targets_keys_on_a_polling_link_are_refused(mode: str) -> None:
    text = (full if mode == "full" else half)(extra='persist = "x.db"\ncheck_dst = true\n')
    message = error_of(text)
    assert f'persist: not used by df1 links with duplex = "{mode}" (a key of a link with role = "target"' in message
    assert f'check_dst: not used by df1 links with duplex = "{mode}"' in message


def test_every_unused_key_is_a_key_of_its_model_in_a_mode_it_has() -> None:
    for model in link_models():
        modes = (None, *model.modes())
        for mode, keys in model.unused_keys.items():
            assert mode in modes, (protocol_of(model), mode)
            for key in keys:
                assert key in model.model_fields and key not in ("name", "protocol", "port", "unit"), (mode, key)
                assert keys[key], (mode, key)  # says why


def _links() -> list[LinkBase]:
    """One link of each kind and mode, with every key it uses at a value that reaches its readers."""
    text = (
        '[[link]]\nname = "a"\nprotocol = "slc-ascii"\nport = "sim://slc150"\nunit = 1\n'
        + full().replace("unit = 1", "unit = 2")
        + half(unit=3, extra='receive_words = 2\nreceive_start = 100\nreceive_table = "holding"\n')
        + '[[link]]\nname = "t"\nprotocol = "df1"\nrole = "target"\nport = "sim://plc-msg"\nunit = 4\n'
        'persist = "' + str(Path(tempfile.gettempdir()) / "slc-gateway-keys-test.db") + '"\nstale_after = 30.0\n'
        '[[link.file]]\nfile = 7\ntype = "N"\nelements = 4\ninitial = 1\n'
    )
    return list(parse_config(text).link)


@pytest.mark.parametrize("index", [0, 1, 2, 3], ids=["slc-ascii", "df1-full", "df1-half", "df1-target"])
def test_every_key_a_kind_does_not_declare_unused_is_read_when_it_builds_its_units(
    index: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    link = _links()[index]
    model = type(link)
    kind = link_kind(link.protocol)
    reads: set[str] = set()

    def spy(self: Any, name: str) -> Any:
        if name in model.model_fields:
            reads.add(name)
        return object.__getattribute__(self, name)

    monkeypatch.setattr(model, "__getattribute__", spy)
    kind.build_units([link])
    kind.plan_of(link)
    monkeypatch.undo()
    unread = set(model.model_fields) - reads - set(link.unused()) - {"protocol"}  # protocol: the union's tag
    assert not unread, f"{link.protocol} ({link.link_mode}): keys accepted but never read: {sorted(unread)}"


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


# --- processor families ------------------------------------------------------------------------


def test_every_processor_has_its_family_by_name() -> None:
    assert set(PROCESSORS) == set(get_args(Processor))
    assert PROCESSORS["plc5"] is ProcessorFamily.PLC5
    assert PROCESSORS["slc500"] is ProcessorFamily.SLC500_FIXED
    for name, family in PROCESSORS.items():
        if name.startswith("slc5/"):
            assert family.name == "SLC5_" + name.removeprefix("slc5/"), name


def test_options_take_the_links_keys_of_the_same_name_and_the_given_ones_over_them() -> None:
    from gateway.kinds.contract import line_options, unit_options
    from gateway.kinds.df1.build import station_config

    link = parse_config(half(extra="poll_timeout = 0.25\nreply_wait = 0.05\ntimeout = 2.5\n"
                             "down_after_failures = 7\nstale_after = 9.5\n")).link[0]
    assert isinstance(link, Df1LinkConfig)
    station = station_config(link)
    assert (station.station, station.poll_timeout, station.reply_wait, station.reply_timeout) == (1, 0.25, 0.05, 2.5)
    options = unit_options(link)
    assert (options["unit_id"], options["name"], options.get("stale_after")) == (1, "s1", 9.5)
    assert line_options(link) == {"name": "s1", "trace": None, "down_after_failures": 7,
                                  "down_after_seconds": DEFAULT_DOWN_AFTER.seconds}
    # a key given explicitly wins over the link's key of the same name
    assert link.values_for(Df1LinkConfig, station=9)["station"] == 9
