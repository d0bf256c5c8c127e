"""Half-duplex DF1 lines in the config: the new keys, grouping links into lines, checks across them."""

from __future__ import annotations

from typing import Any

import pytest
from pydantic import ValidationError

from gateway.kinds.df1.config import LINE_KEYS, Df1LinkConfig, group_lines, line_problems


def link(name: str, unit: int, **keys: Any) -> Df1LinkConfig:
    data = {"name": name, "protocol": "df1", "port": "/dev/ttyS1", "unit": unit, "duplex": "half",
            "map": [{"table": "holding", "start": 0, "address": "N7:0", "count": 4}], **keys}
    return Df1LinkConfig.model_validate(data)


def test_defaults_keep_full_duplex_and_today_s_behaviour() -> None:
    full = Df1LinkConfig.model_validate({"name": "a", "protocol": "df1", "port": "/dev/ttyS0", "unit": 1,
                                         "map": [{"table": "holding", "start": 0, "address": "N7:0", "count": 1}]})
    assert full.duplex == "full" and full.rts == "toggle" and full.receive_words == 0


def test_half_duplex_link_is_accepted() -> None:
    assert link("a", 1).duplex == "half"


def test_new_keys_are_typed_and_bounded() -> None:
    line = link("a", 1, pre_transmit_delay=0.02, rts="rs485", echo=True, poll_timeout=0.3, demote_after=5,
                receive_file=9, receive_words=20)
    assert (line.pre_transmit_delay, line.rts, line.echo, line.demote_after, line.receive_words) == (
        0.02, "rs485", True, 5, 20)
    with pytest.raises(ValidationError, match="rts"):
        link("a", 1, rts="auto")
    with pytest.raises(ValidationError, match="poll_timeout"):
        link("a", 1, poll_timeout=0)


def test_grouping_by_port_protocol_and_duplex() -> None:
    links = [
        link("a", 1, station=1),
        link("b", 2, station=2),
        link("c", 3, station=1, port="socket://Radio:4001"),
        link("d", 4, station=2, port="socket://radio:4001"),  # the same device server
        link("e", 5, station=3, port="/dev/ttyS2", duplex="full"),
    ]
    lines = group_lines(links)
    assert [(line.port, line.indexes, line.name) for line in lines] == [
        ("/dev/ttyS1", (0, 1), "a+b"), ("socket://Radio:4001", (2, 3), "c+d")]
    assert line_problems(links) == []


def test_line_keys_must_agree_and_messages_name_both_links() -> None:
    links = [link("pump1", 1, station=1), link("pump2", 2, station=2, baudrate=9600, checksum="bcc")]
    problems = line_problems(links)
    assert [loc for loc, _ in problems] == [("link", 1, "baudrate"), ("link", 1, "checksum")]
    message = problems[0][1]
    assert '"pump2"' in message and '"pump1"' in message and "link[0]" in message
    assert "9600" in message and "19200" in message


def test_station_numbers_unique_per_line_not_across_lines() -> None:
    links = [link("a", 1, station=4), link("b", 2, station=4), link("c", 3, station=4, port="/dev/ttyS2")]
    problems = line_problems(links)
    assert len(problems) == 1 and problems[0][0] == ("link", 1, "station")
    assert '"b"' in problems[0][1] and '"a"' in problems[0][1] and "both station 4" in problems[0][1]


def test_station_equal_to_source_and_full_duplex_on_a_line_port() -> None:
    links = [link("a", 1, station=0), link("b", 2, station=2, duplex="full")]
    problems = line_problems(links)
    assert [loc for loc, _ in problems] == [("link", 0, "station"), ("link", 1, "duplex")]
    assert "one port is one or the other" in problems[1][1]


@pytest.mark.parametrize("key", [k for k in LINE_KEYS if k not in ("trace",)])
def test_every_line_key_is_a_config_key(key: str) -> None:
    assert key in Df1LinkConfig.model_fields


def test_guide_half_duplex_example_passes() -> None:
    """The guide's half-duplex example is a valid config (``check-config`` loads it) and forms one
    line of two stations without conflicts."""
    from pathlib import Path

    from gateway.config import parse_config

    page = Path(__file__).resolve().parents[3] / "docs" / "guide" / "df1-half-duplex.md"
    section = page.read_text(encoding="utf-8")
    example = section[section.index("```toml\n") + 8 : section.index("\n```", section.index("```toml\n"))]
    config = parse_config(example)
    assert line_problems(config.links) == []
    (line,) = group_lines(config.links)
    assert [link.name for link in line.links] == ["well-1", "well-2"]
    assert line.links[1].processor == "plc5" and line.links[0].receive_words == 16
