"""``[sparkplug]``: validated like every other section (check-config), off when absent."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from gateway.config import parse_config
from gateway.config.sparkplug import SparkplugConfig
from gateway.errors import ConfigError

EXAMPLE = Path(__file__).resolve().parents[2] / "config" / "example-full.toml"
LINK = '\n[[link]]\nname = "{name}"\nprotocol = "slc-ascii"\nport = "sim://slc150"\nunit = 1\n'


def config(sparkplug: str, name: str = "press-1", base_dir: Path | None = None) -> object:
    return parse_config(sparkplug + LINK.format(name=name), base_dir=base_dir)


def section(**keys: object) -> str:
    values: dict[str, object] = {"broker": "mqtt://127.0.0.1:1883", "group_id": "plant1", "edge_node_id": "gw1",
                                 **keys}
    lines = [f"{k} = {v!r}".replace("'", '"') if isinstance(v, str) else f"{k} = {v}" for k, v in values.items()
             if v is not None]
    return "[sparkplug]\n" + "\n".join(lines) + "\n"


def test_absent_is_off() -> None:
    parsed = parse_config(LINK.format(name="press-1"))
    assert parsed.sparkplug is None
    assert "# [sparkplug] not configured" in parsed.describe()


def test_defaults_and_paths(tmp_path: Path) -> None:
    parsed = parse_config(section() + LINK.format(name="press-1"), base_dir=tmp_path)
    spb = parsed.sparkplug
    assert spb is not None
    assert spb.address == ("127.0.0.1", 1883) and not spb.tls and spb.ssl_context() is None
    assert spb.state_file == tmp_path / "sparkplug-bdseq.json"  # relative to the config file's directory
    assert (spb.keepalive, spb.primary_host_id, spb.check_interval) == (30, None, 0.5)
    assert SparkplugConfig.model_fields["state_file"].default == Path("sparkplug-bdseq.json")


def test_mqtts_default_port() -> None:
    spb = parse_config(section(broker="mqtts://broker.local") + LINK.format(name="a")).sparkplug
    assert spb is not None and spb.address == ("broker.local", 8883) and spb.tls


@pytest.mark.parametrize(("keys", "message"), [
    ({"broker": "tcp://127.0.0.1:1883"}, "the broker is mqtt://host:port or mqtts://host:port"),
    ({"broker": "mqtt://:1883"}, "no host"),
    ({"broker": "mqtt://h:99999"}, "the port must be 0..65535"),
    ({"broker": "mqtt://u:p@h:1883"}, "username and password are keys"),
    ({"group_id": "plant/1"}, "Sparkplug topic elements cannot hold / + #"),
    ({"edge_node_id": "gw#"}, "Sparkplug topic elements cannot hold / + #"),
    ({"primary_host_id": ""}, "must not be empty"),
    ({"password": "x"}, "a password needs a username"),
    ({"ca": "ca.pem"}, "file not found"),
    ({"keepalive": 2}, "greater than or equal to 5"),
    ({"reconnect_min": 5.0, "reconnect_max": 1.0}, "must be at least reconnect_min"),
    ({"colour": "red"}, "colour"),
])
def test_bad_sections_are_errors(keys: dict[str, object], message: str, tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=re.escape(message)):
        config(section(**keys), base_dir=tmp_path)


def test_cert_needs_key_and_mqtts(tmp_path: Path) -> None:
    (tmp_path / "client.pem").write_text("x")
    with pytest.raises(ConfigError, match="cert and key go together"):
        config(section(broker="mqtts://h", cert="client.pem"), base_dir=tmp_path)
    with pytest.raises(ConfigError, match=re.escape("ca / cert / key are for an mqtts:// broker")):
        config(section(cert="client.pem", key="client.pem"), base_dir=tmp_path)


def test_describe_hides_the_password() -> None:
    text = parse_config(section(username="gw", password="hunter2") + LINK.format(name="a")).describe()
    assert "[sparkplug]" in text and 'password = "***"' in text and "hunter2" not in text


def test_example_file_mentions_every_key() -> None:
    text = EXAMPLE.read_text(encoding="utf-8")
    assert "\n# [sparkplug]\n" in text
    for key in SparkplugConfig.model_fields:
        assert re.search(rf"^#\s*{key} = ", text, re.MULTILINE), key
    assert re.search(r"^deadband = 0.0$", text, re.MULTILINE)
