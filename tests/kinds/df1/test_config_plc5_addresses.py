"""Map addresses of a ``processor = "plc5"`` link are PLC-5 addresses (issue #12); SLC links keep SLC ones.

PLC-5 forms (1770-6.5.16 chapter 13; PLC-5 quick reference 1785 p. 2-6): ``N7:0``, ``B3/5``,
``T4:1.ACC``, ``F8:2``, octal ``I:010``, elements above 255 (``N7:300``).
"""

from __future__ import annotations

import pytest

from gateway.app import describe_map
from gateway.config import parse_config
from gateway.errors import ConfigError


def link_with(processor: str, *maps: str) -> str:
    text = (f'[[link]]\nname = "p"\nprotocol = "df1"\nport = "sim://slc504"\nunit = 3\n'
            f'processor = "{processor}"\n')
    for body in maps:
        start = "" if "start =" in body else "start = 0\n"
        count = "" if "count =" in body else "count = 1\n"
        text += f"\n[[link.map]]\n{start}{count}{body}\n"
    return text


def error_of(text: str) -> str:
    with pytest.raises(ConfigError) as info:
        parse_config(text)
    return str(info.value)


def line_of(text: str, needle: str) -> int:
    return next(n for n, line in enumerate(text.split("\n"), start=1) if needle in line)


PLC5_ONLY = [
    ('table = "coil"\naddress = "B3/5"', "B3/5"),
    ('table = "holding"\naddress = "N7:300"', "N7:300"),
    ('table = "discrete"\naddress = "I:010/3"', "I:010/3"),
    ('table = "input"\naddress = "I:017"', "I:017"),
]


@pytest.mark.parametrize(("body", "address"), PLC5_ONLY)
def test_plc5_link_accepts_plc5_addresses(body: str, address: str) -> None:
    config = parse_config(link_with("plc5", body))
    assert config.link[0].map[0].address == address
    assert describe_map(config)  # the PLC-5 plan is built from it (check-config shows it)


def test_octal_io_addresses_differ_by_processor() -> None:
    """``I:010`` is input word 8 (octal) on a PLC-5, slot 10 on an SLC 500: each parser reads its own."""
    body = 'table = "input"\naddress = "I:010"'
    plc5 = describe_map(parse_config(link_with("plc5", body)))
    slc = describe_map(parse_config(link_with("slc5/04", body)))
    assert plc5 != slc


def test_plc5_link_accepts_the_common_forms_in_one_map() -> None:
    text = link_with(
        "plc5",
        'table = "holding"\naddress = "N7:0"\ncount = 10',
        'table = "holding"\nstart = 100\naddress = "T4:1.ACC"',
        'table = "holding"\nstart = 200\naddress = "F8:2"\ntype = "float32"',
        'table = "coil"\naddress = "B3/5"\ncount = 16',
        'table = "discrete"\naddress = "T4:1/DN"',
    )
    config = parse_config(text)
    assert [entry.address for entry in config.link[0].map] == ["N7:0", "T4:1.ACC", "F8:2", "B3/5", "T4:1/DN"]


@pytest.mark.parametrize("body", ['table = "holding"\naddress = "N7:300"', 'table = "holding"\naddress = "D10:0"'])
def test_slc_link_keeps_the_slc_parser(body: str) -> None:
    parse_config(link_with("plc5", body))
    text = link_with("slc5/04", body)
    error = error_of(text)
    assert error.startswith(f"<string>:{line_of(text, 'address =')}: ")
    assert 'link "p" (link[0]).map[0].address: ' in error
    assert "not a valid SLC 500 address" in error


@pytest.mark.parametrize(
    ("body", "key", "message"),
    [
        ('table = "discrete"\naddress = "I:1.0"', "address", "not a valid PLC-5 address"),  # SLC form
        ('table = "input"\naddress = "I:018"', "address", "octal"),
        ('table = "holding"\naddress = "N7"', "address", "not a valid PLC-5 address"),
        ('table = "holding"\naddress = "N7:0/3"', "address", "is a bit address: a holding table needs a word"),
        ('table = "holding"\naddress = "B3/5"', "address", "is a bit address"),
        ('table = "holding"\naddress = "N7:0"\ntype = "float32"', "address", 'type "float32" needs a floating-point'),
        ('table = "input"\naddress = "F8:2"', "type", 'use type = "float32"'),
        ('table = "coil"\naddress = "T4:1.ACC"', "address", "needs a bit address"),
        ('table = "coil"\naddress = "F8:0"', "address", "floating-point element: a coil table needs bits"),
    ],
)
def test_plc5_address_problems_name_the_key(body: str, key: str, message: str) -> None:
    text = link_with("plc5", body)
    error = error_of(text)
    assert f'link "p" (link[0]).map[0].{key}: ' in error, error
    assert message in error, error
    needle = key + " =" if key + " =" in body else "[[link.map]]"
    assert error.startswith(f"<string>:{line_of(text, needle)}: "), error


def test_every_bad_address_of_a_map_is_reported() -> None:
    text = link_with("plc5", 'table = "holding"\naddress = "X9:0"', 'table = "holding"\nstart = 5\naddress = "N7:1"',
                     'table = "coil"\nstart = 9\naddress = "B3:1.0"')
    error = error_of(text)
    assert "2 errors" in error
    assert "map[0].address" in error and "map[2].address" in error and "map[1]" not in error


def test_an_invalid_processor_is_reported_without_address_noise() -> None:
    error = error_of(link_with("plc6", 'table = "coil"\naddress = "B3/5"'))
    assert "(link[0]).processor" in error
    assert "address" not in error
