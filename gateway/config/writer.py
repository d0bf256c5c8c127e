"""The resolved-config writer: config models -> TOML text (what ``slc-gateway check-config`` prints).

Every key is written with its effective value, so the output loads back to the same configuration
(``parse_config(config.describe()) == config``), except credentials in port URLs, shown as ``***``.
This module knows tables and values, not sections: each model says what it writes.
"""

from __future__ import annotations

from collections.abc import Iterable

from pydantic import BaseModel

from gateway.logutil import redact_url

__all__ = ["table_lines", "toml_string", "toml_value"]


def toml_string(text: str) -> str:
    """``text`` as a TOML basic string, quotes included."""
    out = ['"']
    for char in text:
        if char in '"\\':
            out.append("\\" + char)
        elif char == "\n":
            out.append("\\n")
        elif char == "\t":
            out.append("\\t")
        elif ord(char) < 0x20 or ord(char) == 0x7F:
            out.append(f"\\u{ord(char):04X}")
        else:
            out.append(char)
    out.append('"')
    return "".join(out)


def toml_value(value: object) -> str:
    """A value as TOML; strings are redacted (``socket://user:password@...`` -> ``***``)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, str):
        return toml_string(redact_url(value))
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{toml_string(str(k))} = {toml_value(v)}" for k, v in value.items()) + " }"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(toml_value(item) for item in value) + "]"
    return toml_string(str(value))  # paths, networks, writable ranges: their str() is what loads back


def table_lines(header: str, model: BaseModel, *, skip: Iterable[str] = (), indent: str = "") -> list[str]:
    """``header`` and one ``key = value`` line per field of ``model`` (in field order), then a blank line.

    A field that is None is written as a comment (``# key not set``), except ``trace``, whose
    "off" is the empty string.
    """
    skipped = set(skip)
    lines = [indent + header]
    for key in type(model).model_fields:
        if key in skipped:
            continue
        value = getattr(model, key)
        if value is None and key == "trace":
            lines.append(f'{indent}trace = ""')
        elif value is None:
            lines.append(f"{indent}# {key} not set")
        else:
            lines.append(f"{indent}{key} = {toml_value(value)}")
    lines.append("")
    return lines
