"""What a config reload keeps, restarts and cannot apply (``gateway.reload``), from config files alone."""

from __future__ import annotations

import hashlib
import time
from pathlib import Path

from pydantic import Field

from gateway.config import GatewayConfig, parse_config
from gateway.config._common import Model
from gateway.reload import ConfigSource, ConfigStatus, line_changes, restart_needed


def station(name: str, unit: int, number: int, port: str = "socket://Radio:4001", extra: str = "") -> str:
    return (f'[[link]]\nname = "{name}"\nprotocol = "df1"\nport = "{port}"\nunit = {unit}\nduplex = "half"\n'
            f"station = {number}\n{extra}"
            '[[link.map]]\ntable = "holding"\nstart = 0\naddress = "N7:0"\ncount = 4\n\n')


ASCII = '[[link]]\nname = "press"\nprotocol = "slc-ascii"\nport = "/dev/ttyUSB0"\nunit = 9\n\n'
# two stations of one half-duplex line (one device server, its host name in two spellings) and a press
FILE = station("pump1", 1, 1) + station("pump2", 2, 2, "socket://radio:4001") + ASCII


def test_a_change_to_one_station_restarts_its_whole_line_and_nothing_else() -> None:
    old = parse_config(FILE)
    new = parse_config(FILE.replace("station = 2\n", "station = 2\nstale_after = 9.0\n"))
    changes = line_changes(old.link, new.link)
    assert changes.kept == ("/dev/ttyUSB0",)
    assert changes.stopped == changes.started == ("socket://radio:4001/",)
    assert (changes.changed, changes.restarted, changes.added, changes.removed) == (("pump2",), ("pump1",), (), ())
    assert changes.summary() == "links: 1 changed (pump2), 1 restarted with their line (pump1), 1 line unchanged"


def test_links_added_and_removed_and_a_file_unchanged() -> None:
    old = parse_config(FILE)
    assert line_changes(old.link, parse_config(FILE).link).none
    new = parse_config(station("pump1", 1, 1) + station("pump2", 2, 2, "socket://radio:4001")
                       + station("pump3", 3, 3, "/dev/ttyS1"))
    changes = line_changes(old.link, new.link)
    assert changes.kept == ("socket://radio:4001/",)  # the same links in the same order: kept
    assert changes.stopped == ("/dev/ttyUSB0",) and changes.started == ("/dev/ttyS1",)
    assert (changes.added, changes.removed, changes.changed) == (("pump3",), ("press",), ())
    assert changes.summary() == "links: 1 added (pump3), 1 removed (press), 1 line unchanged"


def test_what_needs_a_restart_is_named_key_by_key() -> None:
    old = parse_config('[modbus]\nlisten = "0.0.0.0:5020"\n' + ASCII)
    new = parse_config('[modbus]\nlisten = "127.0.0.1:5021"\nallow = ["10.0.0.0/8"]\nmax_connections = 8\n'
                       '[metrics]\nlisten = "127.0.0.1:9108"\n[logging]\nlevel = "DEBUG"\n' + ASCII)
    # allow, max_connections and [logging] apply at once; a new listener and a new address do not
    assert restart_needed(old, new) == ['[modbus] listen ("0.0.0.0:5020" -> "127.0.0.1:5021")', "[metrics] added"]
    assert restart_needed(new, old) == ['[modbus] listen ("127.0.0.1:5021" -> "0.0.0.0:5020")', "[metrics] removed"]
    moved = parse_config('[modbus]\nlisten = "0.0.0.0:5020"\n[metrics]\nlisten = "127.0.0.1:9109"\n'
                         'allow = ["127.0.0.0/8"]\n' + ASCII)
    metrics = parse_config('[modbus]\nlisten = "0.0.0.0:5020"\n[metrics]\nlisten = "127.0.0.1:9108"\n' + ASCII)
    assert restart_needed(metrics, moved) == ['[metrics] listen ("127.0.0.1:9108" -> "127.0.0.1:9109")']


class _Sparkplug(Model):
    host: str = "127.0.0.1"


class _WithASection(GatewayConfig):
    """A config with a section this reload does not know (as one added later would be)."""

    sparkplug: _Sparkplug | None = Field(default=None, strict=False)


def test_a_section_reload_does_not_know_needs_a_restart() -> None:
    links = parse_config(ASCII).link
    without = _WithASection(link=links)
    with_it = _WithASection(link=links, sparkplug=_Sparkplug())
    assert restart_needed(without, with_it) == ["[sparkplug] added"]
    assert restart_needed(with_it, _WithASection(link=links, sparkplug=_Sparkplug(host="::1"))) == [
        "[sparkplug] changed"]
    assert restart_needed(with_it, with_it) == []


def test_a_config_source_loads_its_file_with_the_command_lines_changes(tmp_path: Path) -> None:
    """``ConfigSource.load``: the file's config with ``adjust`` applied, the SHA-256 of its bytes
    (``sha256sum`` shows the same digits), the Unix time it was read."""
    path = tmp_path / "gateway.toml"
    path.write_text(ASCII, encoding="utf-8")
    before = time.time()
    loaded = ConfigSource(path).load()
    assert loaded.config == parse_config(ASCII)  # no adjustment: the file as given
    assert loaded.sha256 == hashlib.sha256(ASCII.encode()).hexdigest()
    assert before <= loaded.loaded_at <= time.time()
    moved = ConfigSource(path, lambda config: config.model_copy(update={"link": []})).load()
    assert moved.config.link == [] and moved.sha256 == loaded.sha256


def test_the_config_status_is_what_the_reload_guide_shows() -> None:
    """``/api/status``'s ``config`` object (docs/guide/reload.md): the first 12 hex digits, the load
    time rounded to the millisecond, the counts, the last failure and what needs a restart."""
    status = ConfigStatus("4041052c30b1" + "9" * 52, 1764341234.51234, reloads=3, reload_failures=1)
    assert status.short_sha256 == "4041052c30b1"
    assert status.document() == {"sha256": "4041052c30b1", "loaded_at": 1764341234.512, "reloads": 3,
                                 "reload_failures": 1, "last_failure": None, "restart_needed": []}
    status.last_failure = "gateway.toml:3: bad"
    status.restart_needed = ("[modbus] listen (a -> b)",)
    document = status.document()
    assert document["last_failure"] == "gateway.toml:3: bad"
    assert document["restart_needed"] == ["[modbus] listen (a -> b)"]
    nothing = ConfigStatus(None, 0.0)  # a config that came from no file
    assert nothing.short_sha256 is None and nothing.document()["sha256"] is None
    assert (nothing.reloads, nothing.reload_failures, nothing.last_failure, nothing.restart_needed) == (0, 0, None, ())


def test_the_summary_counts_unchanged_lines_in_the_plural_but_one() -> None:
    old = parse_config(FILE)
    assert line_changes(old.link, old.link).summary() == "links: 2 lines unchanged"
    new = parse_config(FILE.replace("/dev/ttyUSB0", "/dev/ttyUSB1").replace("Radio:4001", "radio:4002")
                       .replace("radio:4001", "radio:4002").replace("station = 2\n", "station = 3\n"))
    assert line_changes(old.link, new.link).summary().endswith(", 0 lines unchanged")

