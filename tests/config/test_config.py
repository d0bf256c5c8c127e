"""Tests of gateway.config: TOML text -> validated, frozen config objects, or one clear ConfigError."""

from __future__ import annotations

import inspect
import ipaddress
import re
import tomllib
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from gateway.config import (
    GatewayConfig,
    LoggingConfig,
    MetricsConfig,
    ModbusConfig,
    TlsConfig,
    WritableRange,
    link_models,
    load_config,
    parse_config,
    parse_listen,
    protocol_defaults,
    protocol_names,
)
from gateway.errors import ConfigError
from gateway.kinds.df1.config import DF1_DEFAULTS, Df1LinkConfig, MapEntry, classify_address
from gateway.kinds.df1.target.config import TargetFile
from gateway.kinds.slc_ascii.config import SLC_ASCII_DEFAULTS, SlcAsciiLinkConfig
from gateway.protocols.df1.address import parse_address

_PEM_CACHE: dict[str, bytes] = {}


def _pem() -> dict[str, bytes]:
    """A real self-signed certificate and key (made once with the openssl command)."""
    if not _PEM_CACHE:
        import shutil
        import subprocess
        import tempfile

        if shutil.which("openssl") is None:
            pytest.skip("the openssl command is needed to make test certificates")
        with tempfile.TemporaryDirectory() as work:
            subprocess.run(
                ["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "2", "-subj", "/CN=test",
                 "-keyout", f"{work}/key.pem", "-out", f"{work}/cert.pem"],
                check=True, capture_output=True,
            )
            _PEM_CACHE["cert"] = Path(work, "cert.pem").read_bytes()
            _PEM_CACHE["key"] = Path(work, "key.pem").read_bytes()
    return _PEM_CACHE


def write_tls(cert: Path, key: Path, ca: Path | None = None) -> None:
    """Real PEM files at these paths (the CA is the self-signed certificate itself)."""
    pem = _pem()
    cert.write_bytes(pem["cert"])
    key.write_bytes(pem["key"])
    if ca is not None:
        ca.write_bytes(pem["cert"])

HERE = Path(__file__).resolve().parent
EXAMPLE = HERE.parents[1] / "config" / "example-full.toml"

ASCII_LINK = """
[[link]]
name = "press-1"
protocol = "slc-ascii"
port = "sim://slc150"
unit = 1
"""

DF1_LINK = """
[[link]]
name = "line-2"
protocol = "df1"
port = "sim://slc504"
unit = 2

[[link.map]]
table = "holding"
start = 0
address = "N7:0"
count = 10
"""

VALID = ASCII_LINK + DF1_LINK


def error_of(text: str, **kwargs: object) -> str:
    """The message of the ConfigError that parsing ``text`` raises."""
    with pytest.raises(ConfigError) as info:
        parse_config(text, **kwargs)  # type: ignore[arg-type]
    return str(info.value)


def line_of(text: str, needle: str, occurrence: int = 1) -> int:
    """The 1-based number of the line holding the ``occurrence``-th ``needle``."""
    seen = 0
    for number, line in enumerate(text.split("\n"), start=1):
        if needle in line:
            seen += 1
            if seen == occurrence:
                return number
    raise AssertionError(f"{needle!r} not in text")


def df1_with_maps(*maps: str, extra: str = "") -> str:
    """A df1 link with the given [[link.map]] bodies (key lines)."""
    text = f'[[link]]\nname = "d"\nprotocol = "df1"\nport = "sim://slc504"\nunit = 3\n{extra}\n'
    for body in maps:
        text += f"\n[[link.map]]\n{body}\n"
    return text


# ----------------------------------------------------------------------------------------------
# The good files


def test_example_file_loads_and_shows_the_defaults() -> None:
    config = load_config(EXAMPLE)
    ascii_link, df1_link = config.link
    assert (ascii_link.name, ascii_link.protocol, ascii_link.unit) == ("press-1", "slc-ascii", 1)
    assert (df1_link.name, df1_link.protocol, df1_link.unit) == ("line-2", "df1", 2)
    assert config.metrics == MetricsConfig()
    assert config.modbus.tls is None

    # Every value the example writes out is the default: a file giving only what is required
    # (and the same map entries) must resolve to the same configuration.
    minimal = """
[metrics]

[[link]]
name = "press-1"
protocol = "slc-ascii"
port = "sim://slc150"
unit = 1

[[link]]
name = "line-2"
protocol = "df1"
port = "sim://slc504"
unit = 2

[[link.map]]
table = "holding"
start = 0
address = "N7:0"
count = 32

[[link.map]]
table = "holding"
start = 100
address = "F8:0"
count = 10
type = "float32"
scan = "slow"

[[link.map]]
table = "coil"
start = 0
address = "B3:0/0"
count = 64
"""
    assert parse_config(minimal, base_dir=EXAMPLE.parent) == config


def test_example_file_mentions_every_key() -> None:
    text = EXAMPLE.read_text(encoding="utf-8")
    for model in (ModbusConfig, TlsConfig, MetricsConfig, LoggingConfig, *link_models(), MapEntry, TargetFile):
        for key in model.model_fields:
            if key in ("tls", "map"):  # sections, not keys
                continue
            assert re.search(rf"^#?\s*{key} = ", text, re.MULTILINE), f"{model.__name__}.{key} missing"
    assert "\n# [modbus.tls]\n" in text
    assert "\n[[link.map]]\n" in text


def test_defaults_of_the_sections() -> None:
    config = parse_config(VALID)
    assert config.modbus == ModbusConfig(
        listen="0.0.0.0:5020", max_connections=64, idle_timeout=300.0, allow=(), tls=None
    )
    assert config.modbus.address == ("0.0.0.0", 5020)
    assert config.metrics is None
    assert config.logging.level == "INFO"
    assert config.links == config.link


@pytest.mark.parametrize("protocol", ["slc-ascii", "df1"])
def test_serial_defaults_follow_the_protocol(protocol: str) -> None:
    link = parse_config(VALID).link[0 if protocol == "slc-ascii" else 1]
    assert link.protocol == protocol
    for key, value in protocol_defaults()[protocol].items():
        assert getattr(link, key) == value
    assert (link.stopbits, link.retries, link.stale_after, link.read_only) == (1, 3, 5.0, False)
    assert (link.writable, link.fast_interval, link.slow_interval, link.trace) == ((), 0.0, 10.0, None)


def test_df1_defaults_and_map_defaults() -> None:
    link = parse_config(VALID).link[1]
    assert (link.station, link.source, link.checksum, link.processor) == (1, 0, "crc", "slc5/04")
    assert (link.max_read_bytes, link.max_write_bytes) == (0, 0)
    (entry,) = link.map
    assert entry == MapEntry(table="holding", start=0, address="N7:0", count=10)
    assert (entry.type, entry.word_order, entry.scan) == ("int16", "high-first", "fast")
    assert (entry.width, entry.size, entry.last) == (1, 10, 9)


def test_explicit_serial_settings_win_over_the_protocol_defaults() -> None:
    text = VALID.replace("unit = 2\n", 'unit = 2\nbaudrate = 9600\nparity = "E"\nbytesize = 7\ntimeout = 2\n')
    link = parse_config(text).link[1]
    assert (link.baudrate, link.parity, link.bytesize, link.timeout) == (9600, "E", 7, 2.0)


def test_bits_tables_default_to_bool_and_float32_takes_two_registers() -> None:
    text = df1_with_maps(
        'table = "discrete"\nstart = 0\naddress = "I:1.0"\ncount = 16',
        'table = "input"\nstart = 0\naddress = "F8:0"\ncount = 3\ntype = "float32"\nword_order = "low-first"',
    )
    first, second = parse_config(text).link[0].map
    assert first.type == "bool"
    assert (second.width, second.size, second.last, second.word_order) == (2, 6, 5, "low-first")


DF1_BCC = DF1_LINK.replace('port = "sim://slc504"', 'port = "rfc2217://10.0.0.5:4001"\nchecksum = "bcc"')


def test_a_full_configuration_round_trips_through_describe(tmp_path: Path) -> None:
    write_tls(tmp_path / "server.pem", tmp_path / "server.key", tmp_path / "ca.pem")
    (tmp_path / "traces").mkdir()
    text = f"""
[modbus]
listen = "[::]:1502"
allow = ["10.0.0.0/8", "192.168.1.20", "fd00::/8"]
idle_timeout = 0

[modbus.tls]
listen = "0.0.0.0:8020"
cert = "server.pem"
key = "server.key"
client_ca = "{tmp_path / "ca.pem"}"

[metrics]
listen = "127.0.0.1:9200"

[logging]
level = "debug"

[[link]]
name = "press.1_a"
protocol = "slc-ascii"
port = "/dev/ttyUSB0"
unit = 247
writable = ["holding:0-31", "coil:701-720", "holding:40"]
trace = "traces/press.log"

{DF1_BCC}
"""
    config = parse_config(text, "plant.toml", base_dir=tmp_path)
    assert config.modbus.tls is not None
    assert config.modbus.tls.cert == tmp_path / "server.pem"
    assert config.modbus.tls.client_ca == tmp_path / "ca.pem"
    assert config.modbus.tls.address == ("0.0.0.0", 8020)
    assert config.modbus.address == ("::", 1502)
    assert config.modbus.allow[1] == ipaddress.ip_network("192.168.1.20/32")
    assert config.logging.level == "DEBUG"
    link = config.link[0]
    assert link.trace == tmp_path / "traces" / "press.log"
    assert [str(r) for r in link.writable] == ["holding:0-31", "coil:701-720", "holding:40"]
    assert config.link[1].checksum == "bcc"
    assert config.link[1].port == "rfc2217://10.0.0.5:4001"

    described = config.describe()
    assert "processor" not in described.split("[[link]]")[1]  # no df1 keys on the slc-ascii link
    assert tomllib.loads(described)
    assert parse_config(described) == config


def test_a_half_duplex_station_polls_for_its_reply_before_the_timeout() -> None:
    """reply_wait (ACK to the first poll for the reply) must be shorter than timeout (ACK to the
    reply): else the request could only fail."""
    half = DF1_LINK.replace('"line-2"', '"station-3"\nduplex = "half"').replace("sim://slc504", "sim://df1line")
    for wait in ("1.0", "2.5"):
        message = error_of(half.replace("unit = 2", f"unit = 2\ntimeout = 1.0\nreply_wait = {wait}"))
        assert f"reply_wait {float(wait):g} s is not shorter than timeout 1 s" in message
        assert "make reply_wait shorter than timeout" in message
    assert parse_config(half.replace("unit = 2", "unit = 2\ntimeout = 1.0\nreply_wait = 0.9")).link[0].reply_wait == 0.9


def test_describe_lists_every_key() -> None:
    """Every key a link uses is written; a key its kind does not use in its mode (refused if given)
    is left out, so the output loads back."""
    half = DF1_LINK.replace('"line-2"', '"station-3"\nduplex = "half"').replace("unit = 2", "unit = 3")
    target = ('[[link]]\nname = "plc"\nprotocol = "df1"\nrole = "target"\nport = "sim://plc-msg"\nunit = 9\n'
              'persist = "plc.db"\nstale_after = 60.0\n[[link.file]]\nfile = 7\ntype = "N"\nelements = 10\n')
    config = parse_config(VALID + half.replace("sim://slc504", "sim://df1line") + target)
    described = config.describe()
    for key in ModbusConfig.model_fields:
        if key != "tls":
            assert f"\n{key} = " in described
    for key in {key for model in link_models() for key in model.model_fields}:
        if key not in ("map", "file"):
            assert f"\n{key} = " in described
    for key in TargetFile.model_fields:
        if key != "initial":  # not set: written as a comment
            assert f"\n  {key} = " in described
    for link in config.link:
        own = "\n".join(link.describe_lines())
        for key in link.unused():
            assert f"\n{key} = " not in own, (link.name, key)
    assert parse_config(described) == config
    for key in MapEntry.model_fields:
        assert f"  {key} = " in described
    assert "[modbus.tls] not configured" in described


def test_models_are_frozen_and_can_be_built_in_code() -> None:
    config = GatewayConfig(
        link=(SlcAsciiLinkConfig(name="a", protocol="slc-ascii", port="COM3", unit=1),),
    )
    assert config.link[0].baudrate == 9600
    with pytest.raises(ValidationError):
        config.link[0].unit = 2  # type: ignore[misc]
    assert hash(config.link[0].name) == hash("a")


def test_writable_and_allow_helpers() -> None:
    text = VALID.replace("unit = 1\n", 'unit = 1\nwritable = ["holding:0-31", "coil:40"]\n')
    text = '[modbus]\nallow = ["10.0.0.0/8", "::1"]\n' + text
    config = parse_config(text)
    link = config.link[0]
    assert link.is_writable("holding", 31)
    assert not link.is_writable("holding", 32)
    assert link.is_writable("coil", 40)
    assert not link.is_writable("input", 0)
    assert config.link[1].is_writable("holding", 1000)  # empty writable: the mapping decides
    read_only = parse_config(VALID.replace("unit = 2\n", "unit = 2\nread_only = true\n")).link[1]
    assert not read_only.is_writable("holding", 0)
    assert config.modbus.is_allowed("10.2.3.4")
    assert config.modbus.is_allowed("::ffff:10.2.3.4")
    assert config.modbus.is_allowed("::1")
    assert not config.modbus.is_allowed("192.168.0.1")
    assert not config.modbus.is_allowed("not-an-ip")
    assert WritableRange.parse(" holding : 3 - 5 ") == WritableRange(table="holding", first=3, last=5)
    assert ("holding", 4) in WritableRange.parse("holding:3-5")


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("0.0.0.0:5020", ("0.0.0.0", 5020)),
        ("localhost:0", ("localhost", 0)),
        ("plc-gw.example.com:65535", ("plc-gw.example.com", 65535)),
        ("[::]:502", ("::", 502)),
        ("[fe80::1%eth0]:502", ("fe80::1%eth0", 502)),
        (" 127.0.0.1:9108 ", ("127.0.0.1", 9108)),
    ],
)
def test_parse_listen(text: str, expected: tuple[str, int]) -> None:
    assert parse_listen(text) == expected


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("5020", "expected host:port"),
        (":5020", "host is missing"),
        ("::1:5020", "brackets"),
        ("[::1]5020", "expected [IPv6 address]:port"),
        ("[::1:5020", "missing ']'"),
        ("[1.2.3.4]:1", "not an IPv6 address"),
        ("host:65536", "0..65535"),
        ("host:-1", "0..65535"),
        ("host:", "0..65535"),
        ("bad host:1", "not an IPv4 address or a host name"),
        ("300.1.1.1:1", "not an IPv4 address or a host name"),
    ],
)
def test_parse_listen_rejects(text: str, message: str) -> None:
    with pytest.raises(ValueError, match=re.escape(message)):
        parse_listen(text)


@pytest.mark.parametrize(
    "port",
    [
        "/dev/ttyUSB0",
        "/dev/serial/by-id/usb-FTDI_FT232R-if00-port0",
        "/tmp/ttyV0",  # a socat pty's link: any absolute path
        "/home/plant/ports/press",
        "COM3",
        "com12",
        "\\\\.\\COM10",
        "socket://10.0.0.5:4001",
        "socket://[fd00::5]:4001",
        "rfc2217://serial-server.local:4001",
        "sim://slc150?garble=5&drop=7&power_cycle_every=50&seed=1&baud=9600&turnaround=0.002",
        "sim://slc100",
    ],
)
def test_good_ports(port: str) -> None:
    config = parse_config(ASCII_LINK.replace('"sim://slc150"', f"'{port}'"))
    assert config.link[0].port == port


# ----------------------------------------------------------------------------------------------
# The bad files: one test per rule, each checking the key path and the line


BAD = [
    # (id, text, key path, line needle (or None), part of the message)
    (
        "typo",
        ASCII_LINK + "timout = 1\n",
        'link "press-1" (link[0]).timout',
        "timout",
        'did you mean "timeout"',
    ),
    (
        "typo-section",
        "[modbuss]\n" + ASCII_LINK,
        "modbuss",
        "[modbuss]",
        'unknown key (did you mean "modbus"?)',
    ),
    (
        "wrong-type-str",
        ASCII_LINK.replace("unit = 1", 'unit = "1"'),
        "(link[0]).unit",
        "unit",
        'must be an integer (got "1")',
    ),
    (
        "wrong-type-bool",
        ASCII_LINK.replace("unit = 1", "unit = true"),
        "(link[0]).unit",
        "unit",
        "must be an integer (got true)",
    ),
    (
        "wrong-type-float",
        ASCII_LINK.replace("unit = 1", "unit = 1.0"),
        "(link[0]).unit",
        "unit",
        "must be an integer",
    ),
    (
        "bool-type",
        ASCII_LINK + "read_only = 1\n",
        "(link[0]).read_only",
        "read_only",
        "must be true or false (got 1)",
    ),
    ("section-type", "modbus = 5\n" + ASCII_LINK, "modbus", "modbus = 5", "must be a table (got 5)"),
    (
        "date",
        ASCII_LINK + "timeout = 1979-05-27\n",
        "(link[0]).timeout",
        "timeout",
        "must be a number (got 1979-05-27)",
    ),
    (
        "missing-key",
        ASCII_LINK.replace('port = "sim://slc150"\n', ""),
        'link "press-1" (link[0]).port',
        "[[link]]",
        "missing required key",
    ),
    ("no-link", '[logging]\nlevel = "INFO"\n', "link", None, "missing required key"),
    ("empty-link", "link = []\n", "link", "link = []", "at least one [[link]] is required"),
    ("link-not-array", '[link]\nname = "x"\n', "link", "[link]", "must be an array"),
    (
        "name-chars",
        ASCII_LINK.replace('"press-1"', '"press 1"'),
        'link "press 1" (link[0]).name',
        "name",
        "1 to 40 characters",
    ),
    (
        "name-long",
        ASCII_LINK.replace('"press-1"', '"' + "x" * 41 + '"'),
        "(link[0]).name",
        "name",
        "1 to 40 characters",
    ),
    (
        "protocol",
        ASCII_LINK.replace('"slc-ascii"', '"df2"'),
        "(link[0]).protocol",
        "protocol",
        'must be "slc-ascii" or "df1" (got "df2")',
    ),
    (
        "port-bad",
        ASCII_LINK.replace('"sim://slc150"', '"ttyUSB0"'),
        "(link[0]).port",
        "port",
        '"ttyUSB0" (did you mean "/dev/ttyUSB0"?): expected a serial port by its absolute path (/dev/ttyUSB0, '
        "/tmp/ttyV0) or COM3, socket://host:port, rfc2217://host:port or sim://slc150 | sim://slc100",
    ),
    (
        "port-relative",
        ASCII_LINK.replace('"sim://slc150"', '"tmp/ttyV0"'),
        "(link[0]).port",
        "port",
        '"tmp/ttyV0": expected a serial port by its absolute path',
    ),
    (
        "port-sim-model",
        ASCII_LINK.replace('"sim://slc150"', '"sim://slc999"'),
        "(link[0]).port",
        "port",
        "sim://slc150, sim://slc100, sim://slc504, sim://plc5, sim://df1line or sim://plc-msg",
    ),
    (
        "port-sim-query",
        ASCII_LINK.replace('"sim://slc150"', '"sim://slc150?garble"'),
        "(link[0]).port",
        "port",
        "option=value",
    ),
    (
        "port-socket",
        ASCII_LINK.replace('"sim://slc150"', '"socket://10.0.0.5"'),
        "(link[0]).port",
        "port",
        "socket://host:port",
    ),
    (
        "port-sim-protocol",
        ASCII_LINK.replace('"sim://slc150"', '"sim://slc504"'),
        "(link[0]).port",
        "port",
        "speaks df1, but this link's protocol is slc-ascii",
    ),
    (
        "unit-0",
        ASCII_LINK.replace("unit = 1", "unit = 0"),
        "(link[0]).unit",
        "unit",
        "must be greater than or equal to 1 (got 0)",
    ),
    (
        "unit-248",
        ASCII_LINK.replace("unit = 1", "unit = 248"),
        "(link[0]).unit",
        "unit",
        "less than or equal to 247",
    ),
    (
        "baudrate",
        ASCII_LINK + "baudrate = 9601\n",
        "(link[0]).baudrate",
        "baudrate",
        "not a standard baud rate",
    ),
    ("bytesize", ASCII_LINK + "bytesize = 6\n", "(link[0]).bytesize", "bytesize", "must be 7 or 8"),
    ("parity", ASCII_LINK + 'parity = "X"\n', "(link[0]).parity", "parity", 'must be "N", "E" or "O"'),
    ("stopbits", ASCII_LINK + "stopbits = 3\n", "(link[0]).stopbits", "stopbits", "must be 1 or 2"),
    (
        "stopbits-bool",
        ASCII_LINK + "stopbits = true\n",
        "(link[0]).stopbits",
        "stopbits",
        "must be an integer",
    ),
    ("timeout-0", ASCII_LINK + "timeout = 0\n", "(link[0]).timeout", "timeout", "greater than 0"),
    ("timeout-nan", ASCII_LINK + "timeout = nan\n", "(link[0]).timeout", "timeout", "finite number"),
    ("timeout-inf", ASCII_LINK + "timeout = inf\n", "(link[0]).timeout", "timeout", "finite number"),
    ("timeout-huge", ASCII_LINK + "timeout = 1e999\n", "(link[0]).timeout", "timeout", "finite number"),
    ("retries", ASCII_LINK + "retries = 11\n", "(link[0]).retries", "retries", "less than or equal to 10"),
    ("stale", ASCII_LINK + "stale_after = 0\n", "(link[0]).stale_after", "stale_after", "greater than 0"),
    (
        "interval",
        ASCII_LINK + "fast_interval = -1\n",
        "(link[0]).fast_interval",
        "fast_interval",
        "greater than or equal to 0",
    ),
    ("demand-hold-0", ASCII_LINK + "demand_hold = 0\n", "(link[0]).demand_hold", "demand_hold", "greater than 0"),
    (
        "background-negative",
        ASCII_LINK + "background_interval = -1\n",
        "(link[0]).background_interval",
        "background_interval",
        "greater than or equal to 0",
    ),
    ("read-wait-6", ASCII_LINK + "read_wait = 6\n", "(link[0]).read_wait", "read_wait", "less than or equal to 5"),
    ("read-wait-nan", ASCII_LINK + "read_wait = nan\n", "(link[0]).read_wait", "read_wait", "finite number"),
    (
        "df1-key-on-ascii",
        ASCII_LINK + "station = 3\n",
        'link "press-1" (link[0]).station',
        "station",
        "only for df1 links",
    ),
    (
        "df1-checksum-on-ascii",
        ASCII_LINK + 'checksum = "bcc"\n',
        "(link[0]).checksum",
        "checksum",
        "only for df1 links",
    ),
    (
        "map-on-ascii",
        ASCII_LINK + '[[link.map]]\ntable = "holding"\nstart = 0\naddress = "N7:0"\ncount = 1\n',
        'link "press-1" (link[0]).map',
        "[[link]]",
        "slc-ascii links use the fixed default map",
    ),
    (
        "df1-without-map",
        DF1_LINK.split("[[link.map]]")[0],
        'link "line-2" (link[0]).map',
        "[[link]]",
        "at least one [[link.map]]",
    ),
    (
        "station",
        DF1_LINK.replace("unit = 2", "unit = 2\nstation = 255"),
        "(link[0]).station",
        "station",
        "less than or equal to 254",
    ),
    (
        "checksum",
        DF1_LINK.replace("unit = 2", 'unit = 2\nchecksum = "xor"'),
        "(link[0]).checksum",
        "checksum",
        'must be "bcc" or "crc"',
    ),
    (
        "processor",
        DF1_LINK.replace("unit = 2", 'unit = 2\nprocessor = "slc5/06"'),
        "(link[0]).processor",
        "processor",
        '"plc5"',
    ),
    (
        "max-read",
        DF1_LINK.replace("unit = 2", "unit = 2\nmax_read_bytes = 245"),  # a PLC-5 reply holds 244 (pccc/limits.py)
        "(link[0]).max_read_bytes",
        "max_read_bytes",
        "244",
    ),
    (
        "map-table",
        DF1_LINK.replace('"holding"', '"holdings"'),
        'link "line-2" (link[0]).map[0].table',
        "table",
        '"coil" or "discrete"',
    ),
    ("map-start", DF1_LINK.replace("start = 0", "start = 65536"), "(link[0]).map[0].start", "start", "65535"),
    (
        "map-count-0",
        DF1_LINK.replace("count = 10", "count = 0"),
        "(link[0]).map[0].count",
        "count",
        "greater than or equal to 1",
    ),
    (
        "map-count-big",
        DF1_LINK.replace("count = 10", "count = 2001"),
        "(link[0]).map[0].count",
        "count",
        "less than or equal to 2000",
    ),
    (
        "map-missing",
        DF1_LINK.replace("count = 10\n", ""),
        "(link[0]).map[0].count",
        "[[link.map]]",
        "missing required key",
    ),
    ("map-typo", DF1_LINK + 'scna = "slow"\n', "(link[0]).map[0].scna", "scna", 'did you mean "scan"'),
    (
        "map-end",
        DF1_LINK.replace("start = 0", "start = 65530"),
        "(link[0]).map[0].count",
        "count",
        "65530 + count 10 x 1 - 1 = 65539",
    ),
    (
        "bad-address",
        DF1_LINK.replace('"N7:0"', '"hello"'),
        "(link[0]).map[0].address",
        "address",
        "not a valid SLC 500 address",
    ),
    (
        "writable-table",
        ASCII_LINK + 'writable = ["input:4"]\n',
        "(link[0]).writable[0]",
        "writable",
        "holding or coil",
    ),
    (
        "writable-range",
        ASCII_LINK + 'writable = ["holding:0-70000"]\n',
        "(link[0]).writable[0]",
        "writable",
        "0..65535",
    ),
    (
        "writable-backwards",
        ASCII_LINK + 'writable = ["coil:9-2"]\n',
        "(link[0]).writable[0]",
        "writable",
        "backwards",
    ),
    (
        "writable-syntax",
        ASCII_LINK + 'writable = ["ok", "holding"]\n',
        "(link[0]).writable[1]",
        "writable",
        "table:first-last",
    ),
    (
        "writable-type",
        ASCII_LINK + "writable = [5]\n",
        "(link[0]).writable[0]",
        "writable",
        "must be a string",
    ),
    (
        "writable-not-array",
        ASCII_LINK + 'writable = "holding:1"\n',
        "(link[0]).writable",
        "writable",
        "must be an array",
    ),
    (
        "writable-read-only",
        ASCII_LINK + 'read_only = true\nwritable = ["holding:1"]\n',
        "(link[0]).writable",
        "writable",
        "read_only",
    ),
    ("listen", '[modbus]\nlisten = "5020"\n' + ASCII_LINK, "modbus.listen", "listen", "expected host:port"),
    ("listen-ipv6", '[metrics]\nlisten = "::1:9108"\n' + ASCII_LINK, "metrics.listen", "listen", "brackets"),
    (
        "max-connections",
        "[modbus]\nmax_connections = 0\n" + ASCII_LINK,
        "modbus.max_connections",
        "max_connections",
        "greater than or equal to 1",
    ),
    (
        "idle",
        "[modbus]\nidle_timeout = -1.0\n" + ASCII_LINK,
        "modbus.idle_timeout",
        "idle_timeout",
        "greater than or equal to 0",
    ),
    (
        "allow-host-bits",
        '[modbus]\nallow = ["10.1.1.1/24"]\n' + ASCII_LINK,
        "modbus.allow[0]",
        "allow",
        "has host bits set",
    ),
    (
        "allow-garbage",
        '[modbus]\nallow = ["10.0.0.0/8", "nope"]\n' + ASCII_LINK,
        "modbus.allow[1]",
        "allow",
        "not a CIDR network",
    ),
    (
        "level",
        '[logging]\nlevel = "TRACE"\n' + ASCII_LINK,
        "logging.level",
        "level",
        '"WARNING" or "ERROR" (got "TRACE")',
    ),
    (
        "trace-dir",
        ASCII_LINK + 'trace = "no/such/dir/trace.log"\n',
        "(link[0]).trace",
        "trace",
        "directory not found",
    ),
    ("trace-type", ASCII_LINK + "trace = 1\n", "(link[0]).trace", "trace", "must be a string"),
    (
        "tls-no-cert",
        '[modbus.tls]\nkey = "k"\n' + ASCII_LINK,
        "modbus.tls.cert",
        "[modbus.tls]",
        "missing required key",
    ),
    (
        "tls-cert-missing",
        '[modbus.tls]\ncert = "nope.pem"\nkey = "k"\n' + ASCII_LINK,
        "modbus.tls.cert",
        "cert",
        "file not found",
    ),
]


@pytest.mark.parametrize(
    ("text", "path", "needle", "message"), [case[1:] for case in BAD], ids=[c[0] for c in BAD]
)
def test_bad_file(text: str, path: str, needle: str | None, message: str) -> None:
    error = error_of(text, base_dir=HERE)
    assert path in error
    assert message in error
    if needle is not None:
        assert f"<string>:{line_of(text, needle)}: " in error
    else:
        assert re.match(r"<string>: ", error)
    assert "Traceback" not in error


def test_a_single_error_is_one_line() -> None:
    text = ASCII_LINK + "retries = -1\n"
    assert error_of(text) == (
        f'<string>:{line_of(text, "retries")}: link "press-1" (link[0]).retries: '
        "must be greater than or equal to 0 (got -1)"
    )


def test_every_error_is_listed_under_a_summary_in_line_order() -> None:
    text = (
        '[logging]\nlevel = "LOUD"\n'
        + ASCII_LINK.replace("unit = 1", "unit = 0")
        + DF1_LINK.replace("count = 10", "count = 0").replace('port = "sim://slc504"', 'port = "x"')
    )
    lines = error_of(text, source="plant.toml").split("\n")
    assert lines[0] == "plant.toml: 4 errors in the configuration:"
    assert len(lines) == 5
    paths = ["logging.level", "(link[0]).unit", '"line-2" (link[1]).port', "(link[1]).map[0].count"]
    needles = [("level", 1), ("unit", 1), ("port", 2), ("count", 1)]
    for line, path, (needle, occurrence) in zip(lines[1:], paths, needles, strict=True):
        assert line.startswith(f"  plant.toml:{line_of(text, needle, occurrence)}: ")
        assert path in line


def test_line_numbers_find_the_right_link_and_map_entry() -> None:
    text = (
        VALID
        + DF1_LINK.replace('"line-2"', '"line-3"').replace("unit = 2", "unit = 3")
        + '\n[[link.map]]\ntable = "input"\nstart = 0\naddress = "N7:0/0"\ncount = 10\n'
    )
    error = error_of(text)
    assert error.startswith(f'<string>:{line_of(text, "N7:0/0")}: link "line-3" (link[2]).map[1].address: ')
    assert "bit address" in error


def test_key_path_without_a_usable_name() -> None:
    text = ASCII_LINK.replace('name = "press-1"\n', "name = 7\n")
    assert error_of(text).startswith(f"<string>:{line_of(text, 'name = 7')}: link[0].name: must be a string")


def test_inline_tables_still_name_the_key() -> None:
    text = 'link = [{name = "a", protocol = "slc-ascii", port = "COM1", unit = 1, retries = 99}]\n'
    assert error_of(text) == (
        '<string>:1: link "a" (link[0]).retries: must be less than or equal to 10 (got 99)'
    )


# ----------------------------------------------------------------------------------------------
# Cross-checks


def test_duplicate_link_names() -> None:
    text = VALID.replace('"line-2"', '"press-1"')
    error = error_of(text)
    assert error.startswith(f'<string>:{line_of(text, "name", 2)}: link "press-1" (link[1]).name: ')
    assert 'duplicate link name "press-1": link[0] has it' in error


def test_duplicate_unit_ids() -> None:
    text = VALID.replace("unit = 2", "unit = 1")
    error = error_of(text)
    assert error.startswith(f'<string>:{line_of(text, "unit", 2)}: link "line-2" (link[1]).unit: ')
    assert 'duplicate unit id 1: link "press-1" (link[0]) has it' in error


def test_overlapping_map_entries_name_both_entries_and_the_addresses() -> None:
    text = df1_with_maps(
        'table = "holding"\nstart = 0\naddress = "N7:0"\ncount = 16',
        'table = "input"\nstart = 0\naddress = "N7:0"\ncount = 16',  # other table: fine
        'table = "holding"\nstart = 10\naddress = "F8:0"\ncount = 5\ntype = "float32"',
    )
    error = error_of(text)
    assert error == (
        f'<string>:{line_of(text, "[[link.map]]", 3)}: link "d" (link[0]).map[2]: '
        "holding 10-19 overlaps map[0] (holding 0-15) at holding 10-15"
    )


def test_touching_map_entries_do_not_overlap() -> None:
    text = df1_with_maps(
        'table = "coil"\nstart = 0\naddress = "B3:0"\ncount = 16',
        'table = "coil"\nstart = 16\naddress = "B3:1/0"\ncount = 1',
        'table = "coil"\nstart = 17\naddress = "B3:1/1"\ncount = 1',
    )
    assert [entry.last for entry in parse_config(text).link[0].map] == [15, 16, 17]


def test_overlap_of_a_single_address() -> None:
    text = df1_with_maps(
        'table = "coil"\nstart = 0\naddress = "B3:0"\ncount = 16',
        'table = "coil"\nstart = 15\naddress = "B3:1/0"\ncount = 1',
    )
    assert error_of(text).endswith("coil 15-15 overlaps map[0] (coil 0-15) at coil 15")


@pytest.mark.parametrize(
    ("body", "key", "message"),
    [
        ('table = "coil"\ntype = "float32"\naddress = "F8:0"', "type", 'the type must be "bool"'),
        (
            'table = "holding"\ntype = "float32"\naddress = "N7:0"',
            "address",
            'type "float32" needs a floating-point',
        ),
        ('table = "input"\naddress = "F8:0"', "type", 'use type = "float32"'),
        (
            'table = "holding"\ntype = "bool"\naddress = "B3:0/0"',
            "type",
            'type "bool" is for coil and discrete',
        ),
        (
            'table = "holding"\naddress = "N7:0/3"',
            "address",
            "is a bit address: a holding table needs a word",
        ),
        ('table = "input"\naddress = "B3/17"', "address", "is a bit address"),
        ('table = "input"\naddress = "T4:0.DN"', "address", "is a bit address"),
        ('table = "coil"\naddress = "T4:0.ACC"', "address", "needs a bit address (e.g. B3:0/0 or N7:0/0)"),
        ('table = "discrete"\naddress = "T4:0"', "address", "or an element of a bit file"),
        ('table = "coil"\naddress = "F8:0"', "address", "floating-point element: a coil table needs bits"),
    ],
)
def test_map_entry_type_table_and_address_rules(body: str, key: str, message: str) -> None:
    text = df1_with_maps(f"start = 0\ncount = 1\n{body}")
    error = error_of(text)
    assert f'link "d" (link[0]).map[0].{key}: ' in error
    assert message in error
    needle = key + " =" if key + " =" in body else "[[link.map]]"
    assert error.startswith(f"<string>:{line_of(text, needle)}: ")


@pytest.mark.parametrize(
    ("body", "table", "address", "value_type"),
    [
        ('table = "coil"\naddress = "N7:0/0"', "coil", "N7:0/0", "bool"),
        ('table = "coil"\naddress = "B3:0"', "coil", "B3:0", "bool"),
        ('table = "discrete"\naddress = "I:1.0/3"', "discrete", "I:1.0/3", "bool"),
        ('table = "discrete"\naddress = "T4:2.DN"', "discrete", "T4:2.DN", "bool"),
        ('table = "holding"\naddress = "T4:0.ACC"', "holding", "T4:0.ACC", "int16"),
        ('table = "input"\naddress = "S:3"', "input", "S:3", "int16"),
        ('table = "holding"\ntype = "uint16"\naddress = "N10:5"', "holding", "N10:5", "uint16"),
        ('table = "input"\ntype = "float32"\naddress = "F8:0"', "input", "F8:0", "float32"),
    ],
)
def test_map_entry_good_combinations(body: str, table: str, address: str, value_type: str) -> None:
    config = parse_config(df1_with_maps(f"start = 0\ncount = 1\n{body}"))
    [link] = config.link
    [entry] = link.map
    assert (entry.table, entry.address, entry.type, entry.start, entry.count) == (table, address, value_type, 0, 1)
    assert entry.width == (2 if value_type == "float32" else 1)


def test_float32_end_counts_two_registers() -> None:
    text = df1_with_maps('table = "holding"\nstart = 65534\ncount = 1\naddress = "F8:0"\ntype = "float32"')
    parse_config(text)  # 65534..65535: fits
    assert "= 65536" in error_of(text.replace("65534", "65535"))


@pytest.mark.parametrize(
    ("sections", "path", "collides_with"),
    [
        ('[metrics]\nlisten = "0.0.0.0:5020"\n', "metrics.listen", "modbus.listen"),
        ('[metrics]\nlisten = "127.0.0.1:5020"\n', "metrics.listen", "modbus.listen"),
        ('[modbus]\nlisten = "[::]:9108"\n[metrics]\n', "metrics.listen", "modbus.listen"),
        (
            '[modbus.tls]\nlisten = "10.0.0.1:5020"\ncert = "c"\nkey = "k"\n',
            "modbus.tls.listen",
            "modbus.listen",
        ),
        (
            '[modbus.tls]\ncert = "c"\nkey = "k"\n[metrics]\nlisten = "0.0.0.0:802"\n',
            "metrics.listen",
            "modbus.tls.listen",
        ),
    ],
)
def test_listeners_need_their_own_ports(tmp_path: Path, sections: str, path: str, collides_with: str) -> None:
    write_tls(tmp_path / "c", tmp_path / "k")
    error = error_of(sections + ASCII_LINK, base_dir=tmp_path)
    assert f"{path}: " in error
    assert f"collides with {collides_with} (" in error


def test_listeners_on_different_hosts_or_port_0_are_fine() -> None:
    text = '[modbus]\nlisten = "10.0.0.1:0"\n[metrics]\nlisten = "10.0.0.2:9108"\n'
    text += '[modbus.tls]\nlisten = "10.0.0.1:9108"\ncert = "c"\nkey = "k"\n'
    error = error_of(text + ASCII_LINK, base_dir=HERE)  # only the TLS files are missing
    assert "listen" not in error
    assert "file not found" in error


def test_tls_files_are_relative_to_the_config_file(tmp_path: Path) -> None:
    (tmp_path / "tls").mkdir()
    write_tls(tmp_path / "tls" / "server.pem", tmp_path / "tls" / "server.key")
    path = tmp_path / "gateway.toml"
    path.write_text(
        '[modbus.tls]\ncert = "tls/server.pem"\nkey = "tls/server.key"\nclient_ca = "tls/ca.pem"\n'
        + ASCII_LINK
    )
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert str(info.value) == (
        f"{path}:4: modbus.tls.client_ca: file not found: {tmp_path / 'tls' / 'ca.pem'}"
    )
    (tmp_path / "tls" / "ca.pem").write_text("not a certificate")
    with pytest.raises(ConfigError, match=r"client_ca ca.pem: not a usable PEM CA certificate"):
        load_config(path)
    write_tls(tmp_path / "tls" / "server.pem", tmp_path / "tls" / "server.key", tmp_path / "tls" / "ca.pem")
    tls = load_config(path).modbus.tls
    assert tls is not None
    assert (tls.cert, tls.key, tls.client_ca) == (
        tmp_path / "tls" / "server.pem",
        tmp_path / "tls" / "server.key",
        tmp_path / "tls" / "ca.pem",
    )
    assert tls.listen == "0.0.0.0:802"


def test_every_df1_only_key_is_refused_on_an_slc_ascii_link() -> None:
    values = {
        "station": "1",
        "source": "0",
        "checksum": '"crc"',
        "processor": '"slc5/04"',
        "max_read_bytes": "0",
        "max_write_bytes": "0",
        # half duplex
        "duplex": '"full"',
        "pre_transmit_delay": "0.0",
        "rts_send_delay": "0.0",
        "rts_off_delay": "0.0",
        "rts": '"toggle"',
        "dtr": "true",
        "echo": "false",
        "ack_timeout": "0.5",
        "message_retries": "3",
        "duplicate_detect": "true",
        "link_reset": "true",
        "poll_timeout": "0.5",
        "reply_wait": "0.0",
        "max_polls": "20",
        "poll_interval": "1.0",
        "demote_after": "3",
        "slow_poll_interval": "10.0",
        "receive_file": "7",
        "receive_words": "0",
        "receive_table": '"input"',
        "receive_start": "100",
        # target mode
        "role": '"target"',
        "persist": '"x.db"',
        "check_dst": "false",
    }
    assert set(values) | {"map", "file"} == set(Df1LinkConfig.model_fields) - set(SlcAsciiLinkConfig.model_fields)
    text = ASCII_LINK + "".join(f"{key} = {value}\n" for key, value in values.items())
    lines = error_of(text).split("\n")
    assert lines[0] == f"<string>: {len(values)} errors in the configuration:"
    for key in values:
        assert any(f"(link[0]).{key}: only for df1 links" in line for line in lines)


# ----------------------------------------------------------------------------------------------
# SLC 500 address syntax: decided by gateway.protocols.df1.address, the protocol's own parser


@pytest.mark.parametrize(
    "address", ["N7:0", "B3:0/5", "F8:10", "T4:0.ACC", "N256:0", "N7:x", "Z9:0", "N7:0/99", "ST9:0"]
)
def test_address_syntax_follows_the_address_module(address: str) -> None:
    text = df1_with_maps(f'table = "holding"\nstart = 0\ncount = 1\naddress = "{address}"')
    try:
        parse_address(address)
    except ValueError as exc:
        error = error_of(text)
        assert "(link[0]).map[0].address: not a valid SLC 500 address: " in error
        assert str(exc) in error
    else:
        try:
            parse_config(text)
        except ConfigError as exc:
            assert "not a valid SLC 500 address" not in str(exc)


@pytest.mark.parametrize(
    ("address", "letter", "is_bit"),
    [
        ("N7:0", "N", False),
        ("n7:0/3", "N", True),
        ("$B3/37", "B", True),
        ("T4:0.DN", "T", True),
        ("T4:0/DN", "T", True),
        ("T4:0.ACC", "T", False),
        ("I:5.3/6", "I", True),
        ("O:5.3", "O", False),
        ("S:3", "S", False),
        ("F8:0", "F", False),
        ("B3/17", "B", True),
    ],
)
def test_address_classification_comes_from_the_parser(address: str, letter: str, is_bit: bool) -> None:
    """The map rules read file letter and bit-ness from parse_address's result (no regex twin)."""
    assert classify_address(address) == (letter, is_bit)
    with pytest.raises(ValueError, match="hello"):
        classify_address("hello")


# ----------------------------------------------------------------------------------------------
# Files that are not config files


def test_toml_syntax_error_gives_line_and_column() -> None:
    text = ASCII_LINK + "retries = = 3\n"
    error = error_of(text, source="plant.toml")
    assert error.startswith(f"plant.toml:{line_of(text, 'retries')}:11: not valid TOML: ")


def test_duplicate_key_is_a_toml_error() -> None:
    text = ASCII_LINK + "unit = 2\n"
    assert error_of(text).startswith(f"<string>:{line_of(text, 'unit', 2)}:")


def test_missing_file(tmp_path: Path) -> None:
    path = tmp_path / "nope.toml"
    with pytest.raises(ConfigError, match=r"nope\.toml: cannot read the config file: No such file"):
        load_config(path)


def test_directory(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="not a regular file"):
        load_config(tmp_path)


def test_binary_file(tmp_path: Path) -> None:
    path = tmp_path / "gateway.toml"
    path.write_bytes(b"[modbus]\n" + bytes(range(256)))
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert str(info.value) == f"{path}:3: not UTF-8 text (byte 0x80 at offset 137): is this a binary file?"


def test_file_with_nul_bytes(tmp_path: Path) -> None:
    path = tmp_path / "zeros.toml"
    path.write_bytes(b"\0" * 100)
    with pytest.raises(ConfigError, match="NUL"):
        load_config(path)


def test_latin1_file(tmp_path: Path) -> None:
    path = tmp_path / "latin1.toml"
    path.write_bytes(ASCII_LINK.encode() + "# Pressen-Linie Süd\n".encode("latin-1"))
    with pytest.raises(ConfigError, match=rf"latin1\.toml:{line_of(ASCII_LINK, 'unit') + 1}: not UTF-8"):
        load_config(path)


def test_utf8_bom_and_crlf_are_accepted(tmp_path: Path) -> None:
    path = tmp_path / "windows.toml"
    path.write_bytes(b"\xef\xbb\xbf" + VALID.replace("\n", "\r\n").encode())
    assert load_config(str(path)) == parse_config(VALID)


def test_too_large_file(tmp_path: Path) -> None:
    path = tmp_path / "huge.toml"
    path.write_bytes(b"#" * (2 << 20))
    with pytest.raises(ConfigError, match="not a config file"):
        load_config(path)


def test_deep_nesting_is_a_config_error() -> None:
    with pytest.raises(ConfigError):
        parse_config("x = " + "[" * 100_000)


# ----------------------------------------------------------------------------------------------
# Fuzzing: parse_config returns a GatewayConfig or raises ConfigError, nothing else


def parse_or_config_error(text: str) -> None:
    try:
        config = parse_config(text, base_dir=HERE)
    except ConfigError as exc:
        assert str(exc)
    else:
        assert isinstance(config, GatewayConfig)
        assert parse_config(config.describe(), base_dir=HERE) == config


FUZZ_BASE = (
    '[modbus]\nlisten = "0.0.0.0:5020"\nallow = ["10.0.0.0/8"]\n[metrics]\n[logging]\nlevel = "INFO"\n'
    + ASCII_LINK
    + 'writable = ["holding:0-31", "coil:5"]\n'
    + DF1_LINK
    + '\n[[link.map]]\ntable = "coil"\nstart = 0\naddress = "B3:0/0"\ncount = 16\n'
    + '\n[[link.map]]\ntable = "input"\nstart = 0\naddress = "F8:0"\ncount = 2\ntype = "float32"\n'
)

VALUES = [
    "0",
    "1",
    "-1",
    "2",
    "247",
    "248",
    "65535",
    "65536",
    "1.5",
    "0.0",
    "nan",
    "-inf",
    "true",
    "false",
    '""',
    '"x"',
    '"press-1"',
    '"line-2"',
    '"df1"',
    '"slc-ascii"',
    '"sim://slc504"',
    '"holding"',
    '"coil"',
    '"float32"',
    '"bool"',
    '"N7:0"',
    '"F8:0"',
    '"B3:0/0"',
    '"T4:0.DN"',
    '"holding:0-9"',
    '"0.0.0.0:5020"',
    "[]",
    "[1]",
    '["a"]',
    "{}",
    "{ a = 1 }",
    "1979-05-27",
    "9" * 30,
    "'\\u0000'",
]


@st.composite
def mutated_config(draw: st.DrawFn) -> str:
    lines = FUZZ_BASE.split("\n")
    for _ in range(draw(st.integers(1, 4))):
        index = draw(st.integers(0, len(lines) - 1))
        operation = draw(st.sampled_from(["value", "delete", "duplicate", "swap", "chars", "line"]))
        if operation == "value" and "=" in lines[index]:
            key = lines[index].split("=", 1)[0]
            lines[index] = f"{key}= {draw(st.sampled_from(VALUES))}"
        elif operation == "delete":
            del lines[index]
        elif operation == "duplicate":
            lines.insert(draw(st.integers(0, len(lines))), lines[index])
        elif operation == "swap":
            other = draw(st.integers(0, len(lines) - 1))
            lines[index], lines[other] = lines[other], lines[index]
        elif operation == "chars":
            line = lines[index]
            at = draw(st.integers(0, len(line)))
            cut = draw(st.integers(0, 3))
            lines[index] = line[:at] + draw(st.text(max_size=3)) + line[at + cut :]
        else:
            lines[index] = draw(st.text(max_size=20))
        if not lines:
            lines = [""]
    return "\n".join(lines)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.text(max_size=200))
def test_fuzz_random_text(text: str) -> None:
    parse_or_config_error(text)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.text(alphabet='[]."=\n #abcdeklmnoprstu0123456789-_:/{},', max_size=200))
def test_fuzz_toml_like_text(text: str) -> None:
    parse_or_config_error(text)


@settings(max_examples=600, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(mutated_config())
def test_fuzz_mutations_of_a_valid_file(text: str) -> None:
    parse_or_config_error(text)


def test_fuzz_base_is_valid() -> None:
    config = parse_config(FUZZ_BASE)
    assert len(config.link[1].map) == 3


def test_tls_files_that_are_not_pem_are_refused_by_name(tmp_path: Path) -> None:
    (tmp_path / "cert.pem").write_text("garbage\n")
    (tmp_path / "key.pem").write_text("garbage\n")
    error = error_of('[modbus.tls]\ncert = "cert.pem"\nkey = "key.pem"\n' + ASCII_LINK, base_dir=tmp_path)
    assert "modbus.tls" in error and "cert.pem" in error and "not a usable PEM certificate" in error


# ----------------------------------------------------------------------------------------------
# Issue 14: the network edge


def _tls_text(tmp_path: Path, *, client_ca: bool = True, extra: str = "") -> str:
    write_tls(tmp_path / "server.pem", tmp_path / "server.key", tmp_path / "ca.pem")
    text = '\n[modbus.tls]\nlisten = "0.0.0.0:802"\ncert = "server.pem"\nkey = "server.key"\n'
    if client_ca:
        text += 'client_ca = "ca.pem"\n'
    return text + extra


def test_listen_empty_turns_the_plain_listener_off(tmp_path: Path) -> None:
    """Issue 14: listen = "" failed check-config, so TLS could not be the only way in."""
    config = parse_config('[modbus]\nlisten = ""\n' + _tls_text(tmp_path) + ASCII_LINK, base_dir=tmp_path)
    assert not config.modbus.plain_enabled
    assert config.warnings() == []
    assert parse_config(config.describe()) == config
    with pytest.raises(ConfigError, match=r'listen = "" turns the plain listener off: configure \[modbus.tls\]'):
        parse_config('[modbus]\nlisten = ""\n' + ASCII_LINK)


def test_tls_with_client_ca_and_a_plain_listener_warns(tmp_path: Path) -> None:
    config = parse_config('[modbus]\nlisten = "0.0.0.0:5020"\n' + _tls_text(tmp_path) + ASCII_LINK, base_dir=tmp_path)
    (warning,) = config.warnings()
    assert "plain listener" in warning and 'listen = ""' in warning
    no_ca = parse_config(_tls_text(tmp_path, client_ca=False) + ASCII_LINK, base_dir=tmp_path)
    assert no_ca.warnings() == []  # TLS without client certificates gates nothing: no false promise


def test_roles_and_new_modbus_keys(tmp_path: Path) -> None:
    extra = 'handshake_timeout = 2.5\nmax_handshakes = 8\ndefault_rights = "read-write"\n'
    extra += '[modbus.tls.roles]\noperator = "read-write"\nviewer = "read"\n'
    text = '[modbus]\nlisten = ""\nmax_connections_per_address = 4\nframe_timeout = 2.0\nloopback_reads = false\n'
    config = parse_config(text + _tls_text(tmp_path, extra=extra) + ASCII_LINK, base_dir=tmp_path)
    tls = config.modbus.tls
    assert tls is not None
    assert tls.roles == {"operator": "read-write", "viewer": "read"}
    assert (tls.handshake_timeout, tls.max_handshakes, tls.default_rights) == (2.5, 8, "read-write")
    modbus = config.modbus
    assert (modbus.max_connections_per_address, modbus.frame_timeout, modbus.loopback_reads) == (4, 2.0, False)
    assert modbus.per_address_cap == 4
    assert parse_config(ASCII_LINK).modbus.per_address_cap == 32  # 0: half of max_connections (64)
    assert parse_config("[modbus]\nmax_connections = 1\n" + ASCII_LINK).modbus.per_address_cap == 1
    described = config.describe()
    assert 'roles = { "operator" = "read-write", "viewer" = "read" }' in described
    assert parse_config(described) == config


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        ('[modbus.tls.roles]\nadmin = "write"\n', "modbus.tls.roles.admin"),
        ('default_rights = "all"\n', "modbus.tls.default_rights"),
        ("handshake_timeout = 0\n", "modbus.tls.handshake_timeout"),
        ("max_handshakes = 0\n", "modbus.tls.max_handshakes"),
    ],
)
def test_bad_tls_keys(tmp_path: Path, extra: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        parse_config(_tls_text(tmp_path, extra=extra) + ASCII_LINK, base_dir=tmp_path)


def test_roles_need_client_certificates(tmp_path: Path) -> None:
    extra = '[modbus.tls.roles]\noperator = "read-write"\n'
    with pytest.raises(ConfigError, match="roles come from client certificates: set client_ca"):
        parse_config(_tls_text(tmp_path, client_ca=False, extra=extra) + ASCII_LINK, base_dir=tmp_path)


def test_metrics_allow_and_cap() -> None:
    text = '[metrics]\nlisten = "0.0.0.0:9108"\nallow = ["10.1.0.0/16"]\nmax_connections = 4\n'
    config = parse_config(text + ASCII_LINK)
    assert config.metrics is not None
    assert config.metrics.allow == (ipaddress.ip_network("10.1.0.0/16"),)
    assert config.metrics.max_connections == 4
    assert config.warnings() == []
    (warning,) = parse_config('[metrics]\nlisten = "0.0.0.0:9108"\n' + ASCII_LINK).warnings()
    assert "[metrics] listens on 0.0.0.0:9108 with no allow list" in warning
    assert parse_config('[metrics]\nlisten = "127.0.0.1:9108"\n' + ASCII_LINK).warnings() == []


def test_shipped_gateway_toml_binds_metrics_to_loopback() -> None:
    shipped = HERE.parents[1] / "config"
    config = parse_config((shipped / "gateway.toml").read_text(), base_dir=shipped)
    assert config.metrics is not None
    assert ipaddress.ip_address(config.metrics.address[0]).is_loopback
    # its port is the usual USB adapter's, which this machine need not have
    ports = [link.port for link in config.link]
    assert [w for w in config.warnings() if not any(f"port {port} does not exist" in w for port in ports)] == []


def test_a_missing_serial_port_is_a_warning(tmp_path: Path) -> None:
    """A port path that does not exist loads (the link keeps trying to open it), with a warning;
    an existing path anywhere (a socat pty's link in /tmp) loads without one."""
    missing = tmp_path / "ttyV0"
    config = parse_config(ASCII_LINK.replace('"sim://slc150"', f'"{missing}"'))
    assert config.link[0].port == str(missing)
    assert config.warnings() == [
        f'link "press-1": port {missing} does not exist (yet): run keeps trying to open it until it appears; '
        "check the name (ls /dev/serial/by-id/ lists USB adapters)"
    ]
    missing.symlink_to("/dev/null")  # a symlink to a device, as socat's link=/tmp/ttyV0 makes
    assert parse_config(ASCII_LINK.replace('"sim://slc150"', f'"{missing}"')).warnings() == []


def test_describe_redacts_credentials_in_port_urls() -> None:
    """Issue 14: credentials in port URLs appeared in full in check-config output."""
    text = ASCII_LINK.replace("sim://slc150", "socket://plc:s3cret@10.0.0.5:4001")
    config = parse_config(text)
    assert config.link[0].port == "socket://plc:s3cret@10.0.0.5:4001"  # the link still uses them
    described = config.describe()
    assert "s3cret" not in described
    assert 'port = "socket://***@10.0.0.5:4001"' in described


def test_trace_limits_and_repeat_interval() -> None:
    config = parse_config("[logging]\ntrace_max_bytes = 65536\ntrace_backups = 0\nrepeat_interval = 5.0\n" + ASCII_LINK)
    assert (config.logging.trace_max_bytes, config.logging.trace_backups) == (65536, 0)
    assert config.logging.repeat_interval == 5.0
    with pytest.raises(ConfigError, match=r"logging\.trace_max_bytes"):
        parse_config("[logging]\ntrace_max_bytes = 10\n" + ASCII_LINK)


# ----------------------------------------------------------------------------------------------
# Issue 11: one link model per protocol, chosen by `protocol` (a discriminated union)


def test_each_link_is_validated_by_the_model_of_its_protocol() -> None:
    ascii_link, df1_link = parse_config(VALID).link
    assert type(ascii_link) is SlcAsciiLinkConfig
    assert type(df1_link) is Df1LinkConfig
    assert "station" not in SlcAsciiLinkConfig.model_fields  # refused by extra="forbid", not by a list
    assert protocol_names() == ("slc-ascii", "df1")
    assert tuple(protocol_defaults()) == protocol_names()
    for model in link_models():
        keys = model.serial_defaults.as_keys()
        assert {key: model.model_fields[key].default for key in keys} == keys


@pytest.mark.parametrize(
    ("value", "hint"),
    [('"df2"', ' (did you mean "df1"?)'), ('"slc_ascii"', ' (did you mean "slc-ascii"?)'), ('""', ""), ("5", "")],
)
def test_an_unknown_protocol_names_the_known_ones_and_never_falls_back(value: str, hint: str) -> None:
    text = ASCII_LINK.replace('"slc-ascii"', value)
    assert error_of(text) == (
        f'<string>:{line_of(text, "protocol")}: link "press-1" (link[0]).protocol: '
        f'unknown protocol: must be "slc-ascii" or "df1" (got {value}){hint}'
    )


def test_a_link_without_a_protocol() -> None:
    text = ASCII_LINK.replace('protocol = "slc-ascii"\n', "") + "station = 3\n"
    assert error_of(text) == (
        f'<string>:{line_of(text, "[[link]]")}: link "press-1" (link[0]).protocol: missing required key'
    )


def test_a_misspelt_key_of_the_other_protocol_is_named_as_such() -> None:
    text = ASCII_LINK + "statoin = 3\n"
    assert error_of(text).endswith(
        '(link[0]).statoin: unknown key (did you mean "station"? It is a key of df1 links; '
        "this link's protocol is slc-ascii)"
    )
    text = DF1_LINK.replace("unit = 2", "unit = 2\nstatoin = 3")
    assert error_of(text).endswith('(link[0]).statoin: unknown key (did you mean "station"?)')


def test_a_wrong_simulator_is_reported_with_the_other_problems_of_the_link() -> None:
    text = ASCII_LINK.replace("sim://slc150", "sim://slc504") + "retries = 99\n"
    lines = error_of(text).split("\n")
    assert lines[0] == "<string>: 2 errors in the configuration:"
    assert "(link[0]).port: sim://slc504 simulates a controller that speaks df1" in lines[1]
    assert "(link[0]).retries: must be less than or equal to 10" in lines[2]
    text = ASCII_LINK.replace("sim://slc150", "sim://slc999") + "retries = 99\n"
    lines = error_of(text).split("\n")
    assert lines[1].endswith("(link[0]).port: sim://slc999: no such simulator: expected sim://slc150, sim://slc100, "
                             "sim://slc504, sim://plc5, sim://df1line or sim://plc-msg")


def test_a_bad_port_names_the_simulators_of_the_links_protocol() -> None:
    error = error_of(DF1_LINK.replace('"sim://slc504"', '"ttyUSB0"'))
    assert error.endswith("rfc2217://host:port or sim://slc504 | sim://plc5 | sim://df1line | sim://plc-msg")
    error = error_of(ASCII_LINK.replace('"sim://slc150"', '"ttyUSB0"'))
    assert error.endswith("rfc2217://host:port or sim://slc150 | sim://slc100")


def test_drivers_and_tools_agree_with_the_serial_defaults_of_the_config() -> None:
    """config/slc_ascii.py and config/df1.py hold the serial defaults; the CLI tools read them there.
    The drivers keep a default of their own (for code that builds one without a config) until the
    link-kind registry passes the config's in: this keeps the two from drifting apart."""
    from gateway.kinds.df1.full.driver import DF1_SETTINGS, Df1Driver
    from gateway.kinds.slc_ascii.driver import SLC_ASCII_SETTINGS, SlcAsciiDriver

    assert SLC_ASCII_SETTINGS == SLC_ASCII_DEFAULTS.settings
    assert inspect.signature(SlcAsciiDriver).parameters["timeout"].default == SLC_ASCII_DEFAULTS.timeout
    assert DF1_SETTINGS == DF1_DEFAULTS.settings
    assert inspect.signature(Df1Driver).parameters["timeout"].default == DF1_DEFAULTS.timeout
