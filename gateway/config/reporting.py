"""Turning pydantic's validation errors into one :class:`~gateway.errors.ConfigError`.

Each problem becomes one line ``source:line: key path: what is wrong``, sorted by line: the key
path in TOML terms (``link "press-1" (link[0]).map[2].count``, indexes from 0), the line from
:class:`~gateway.config.lines.LineIndex`, unknown keys with a "did you mean", keys of another
protocol's links named as such, and an unknown protocol with the list of the known ones.
"""

from __future__ import annotations

import difflib
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any, get_args

from pydantic import BaseModel, ValidationError
from pydantic_core import ErrorDetails

from gateway.config._common import Loc, Problems, show
from gateway.config.lines import LineIndex
from gateway.config.link import LinkBase
from gateway.config.links import link_model, link_models, protocol_names, protocol_of
from gateway.config.schema import GatewayConfig
from gateway.config.writer import toml_string
from gateway.errors import ConfigError

__all__ = ["validate"]

_TYPE_MESSAGES = {
    "int_type": "must be an integer",
    "int_parsing": "must be an integer",
    "float_type": "must be a number",
    "float_parsing": "must be a number",
    "finite_number": "must be a finite number",
    "bool_type": "must be true or false",
    "bool_parsing": "must be true or false",
    "string_type": "must be a string",
    "tuple_type": "must be an array",
    "list_type": "must be an array",
    "dict_type": "must be a table",
    "model_type": "must be a table",
    "model_attributes_type": "must be a table",
    "is_instance_of": "must be a string",
}


def _choices(names: tuple[str, ...]) -> str:
    quoted = [f'"{name}"' for name in names]
    return ", ".join(quoted[:-1]) + " or " + quoted[-1] if len(quoted) > 1 else quoted[0]


def _protocol_message(value: object) -> str:
    """An unknown ``protocol``: the known ones, and the closest if the name looks like a typo."""
    known = protocol_names()
    message = f"unknown protocol: must be {_choices(known)} (got {show(value)})"
    if isinstance(value, str):
        close = difflib.get_close_matches(value.lower(), known, n=1, cutoff=0.6)
        if close and close[0] != value:
            message += f' (did you mean "{close[0]}"?)'
    return message


def _foreign_key(key: str, link: type[LinkBase]) -> str | None:
    """The message for ``key`` on a ``link`` whose protocol does not have it, if another has it."""
    note = link.foreign_key_notes.get(key)
    if note is not None:
        return note
    owners = [protocol_of(model) for model in link_models() if model is not link and key in model.model_fields]
    if not owners:
        return None
    return f"only for {' and '.join(owners)} links (this link's protocol is {protocol_of(link)})"


def _message(error: ErrorDetails, loc: Loc, link: type[LinkBase] | None) -> str:
    kind = error["type"]
    if kind == "missing":
        return "missing required key"
    if kind == "extra_forbidden":
        key = loc[-1] if loc else None
        if link is not None and len(loc) == 3 and isinstance(key, str):
            foreign = _foreign_key(key, link)
            if foreign is not None:
                return foreign
        return "unknown key" + _suggestion(loc, link)
    message = error["msg"]
    if kind in ("value_error", "assertion_error"):
        return message.removeprefix("Value error, ").removeprefix("Assertion failed, ")
    message = _TYPE_MESSAGES.get(kind) or message.replace("Input should be", "must be").replace("'", '"')
    return f"{message} (got {show(error['input'])})"


def _suggestion(loc: Loc, link: type[LinkBase] | None) -> str:
    if not loc or not isinstance(loc[-1], str):
        return ""
    model: type[BaseModel] | None = GatewayConfig
    rest = loc[:-1]
    if link is not None and len(loc) >= 3:
        model, rest = link, loc[2:-1]
    for part in rest:
        if isinstance(part, int) or model is None:
            continue
        field = model.model_fields.get(part)
        model = _model_in(field.annotation) if field is not None else None
    if model is None:
        return ""
    close = difflib.get_close_matches(loc[-1], list(model.model_fields), n=1, cutoff=0.6)
    if close:
        return f' (did you mean "{close[0]}"?)'
    if model is link and link is not None:  # a misspelt key of another protocol's links
        others = {key for other in link_models() for key in other.model_fields} - set(link.model_fields)
        close = difflib.get_close_matches(loc[-1], sorted(others), n=1, cutoff=0.6)
        if close:
            owners = " and ".join(protocol_of(model) for model in link_models() if close[0] in model.model_fields)
            protocol = protocol_of(link)
            return f' (did you mean "{close[0]}"? It is a key of {owners} links; this link\'s protocol is {protocol})'
    return ""


def _model_in(annotation: object) -> type[BaseModel] | None:
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for argument in get_args(annotation):
        found = _model_in(argument)
        if found is not None:
            return found
    return None


def _render_path(loc: Loc, link_names: Mapping[int, str]) -> str:
    if not loc:
        return "(top level)"
    parts: list[str] = []
    rest = loc
    if len(loc) >= 2 and loc[0] == "link" and isinstance(loc[1], int):
        name = link_names.get(loc[1])
        index = f"link[{loc[1]}]"
        parts.append(f"link {show(name, 42)} ({index})" if name is not None else index)
        rest = loc[2:]
    for part in rest:
        if isinstance(part, int):
            parts.append(f"[{part}]")
        else:
            key = part if re.fullmatch(r"[A-Za-z0-9_-]+", part) else toml_string(part)
            parts.append(("." if parts else "") + key)
    return "".join(parts)


def _untag(loc: Loc) -> tuple[Loc, type[LinkBase] | None]:
    """``("link", 0, <protocol>, "station")`` -> ``(("link", 0, "station"), <the protocol's link model>)``.

    Pydantic puts the tag of a discriminated union into the path; TOML has no such level.
    """
    if len(loc) >= 3 and loc[0] == "link" and isinstance(loc[1], int) and isinstance(loc[2], str):
        model = link_model(loc[2])
        if model is not None:
            return loc[:2] + loc[3:], model
    return loc, None


def _problems(error: ErrorDetails) -> list[tuple[Loc, str]]:
    """The problems of one pydantic error: ``(key path, message)`` pairs."""
    loc, link = _untag(tuple(error["loc"]))
    kind = error["type"]
    if kind == "union_tag_not_found":  # a link without a protocol
        return [((*loc, "protocol"), "missing required key")]
    if kind == "union_tag_invalid":
        raw: Any = error["input"]
        value = raw.get("protocol") if isinstance(raw, dict) else error.get("ctx", {}).get("tag")
        return [((*loc, "protocol"), _protocol_message(value))]
    cause = error.get("ctx", {}).get("error")
    if isinstance(cause, Problems):
        return [(loc + sub_loc, message) for sub_loc, message in cause.problems]
    return [(loc, _message(error, loc, link))]


def _config_error(source: str, problems: list[tuple[int | None, str]]) -> ConfigError:
    def line(number: int | None, text: str) -> str:
        return f"{source}:{number}: {text}" if number is not None else f"{source}: {text}"

    ordered = sorted(problems, key=lambda item: (item[0] is None, item[0] or 0))
    if len(ordered) == 1:
        return ConfigError(line(*ordered[0]))
    body = "\n".join("  " + line(number, text) for number, text in ordered)
    return ConfigError(f"{source}: {len(ordered)} errors in the configuration:\n{body}")


def validate(data: dict[str, Any], text: str, source: str, base_dir: Path) -> GatewayConfig:
    """``data`` (parsed from ``text``) as a GatewayConfig, or one ConfigError listing every problem."""
    try:
        return GatewayConfig.model_validate(data, context={"base_dir": base_dir})
    except ValidationError as exc:
        raw_links = data.get("link")
        link_names: dict[int, str] = {}
        if isinstance(raw_links, list):
            for index, raw in enumerate(raw_links):
                if isinstance(raw, dict) and isinstance(raw.get("name"), str):
                    link_names[index] = raw["name"]
        line_index = LineIndex(text)
        problems: list[tuple[int | None, str]] = []
        for error in exc.errors(include_url=False):
            for loc, message in _problems(error):
                problems.append((line_index.find(loc), f"{_render_path(loc, link_names)}: {message}"))
        raise _config_error(source, problems) from None
