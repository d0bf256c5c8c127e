"""The config learns the link kinds from the registry (gateway.kinds), which it does not import."""

from __future__ import annotations

import subprocess
import sys
import textwrap

from gateway.config import parse_config, protocol_names

_LINK = """
[[link]]
name = "press"
protocol = "df1"
port = "sim://slc504"
unit = 1
map = [{ address = "N7:0", count = 1, table = "holding", start = 0 }]
"""


def test_the_registry_gives_the_config_its_kinds() -> None:
    assert protocol_names() == ("slc-ascii", "df1")
    assert parse_config(_LINK).links[0].name == "press"


def test_validating_before_the_registry_is_imported_says_what_to_do() -> None:
    code = textwrap.dedent(f"""
        import sys
        from gateway.config import parse_config
        assert "gateway.kinds" not in sys.modules, "gateway.config imports the registry"
        try:
            parse_config({_LINK!r})
        except RuntimeError as exc:
            print(exc)
    """)
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    assert done.stdout.strip() == (
        "no link kinds are known to the config: import gateway.kinds before validating a config")
