"""Reading the config file: bytes -> text -> TOML -> validated :class:`GatewayConfig`, or one ConfigError."""

from __future__ import annotations

import hashlib
import re
import stat
import tomllib
from pathlib import Path

from gateway.config.reporting import validate
from gateway.config.schema import GatewayConfig
from gateway.errors import ConfigError

__all__ = ["MAX_CONFIG_BYTES", "load_config", "load_config_file", "parse_config"]

MAX_CONFIG_BYTES = 1 << 20
"""A config file larger than this is refused (it is not a config file)."""


def parse_config(text: str, source: str = "<string>", *, base_dir: str | Path | None = None) -> GatewayConfig:
    """Parse and validate TOML ``text``; ``source`` names it in error messages.

    Relative paths in the config (TLS files, traces) are relative to ``base_dir`` (default: the
    current directory). Raises :class:`ConfigError`, never anything else, for any bad text.
    """
    base = Path(base_dir) if base_dir is not None else Path.cwd()
    if "\0" in text:
        raise ConfigError(f"{source}: contains NUL characters: not a text file")
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        message = str(exc)
        where = re.search(r"\s*\(at line (\d+), column (\d+)\)$", message)
        if where is not None:
            message = message[: where.start()]
            raise ConfigError(f"{source}:{where[1]}:{where[2]}: not valid TOML: {message}") from None
        raise ConfigError(f"{source}: not valid TOML: {message}") from None
    except RecursionError:
        raise ConfigError(f"{source}: not valid TOML: nested too deeply") from None
    return validate(data, text, source, base)


def load_config(path: str | Path) -> GatewayConfig:
    """Read, parse and validate the config file at ``path``. Raises :class:`ConfigError`."""
    return load_config_file(path)[0]


def load_config_file(path: str | Path) -> tuple[GatewayConfig, str]:
    """:func:`load_config`, and the SHA-256 of the file's bytes as read (hex): which file a running
    gateway serves, whatever its name and time stamps say."""
    path = Path(path)
    source = str(path)
    try:
        if not stat.S_ISREG(path.stat().st_mode):
            raise ConfigError(f"{source}: not a regular file")
        with path.open("rb") as file:
            data = file.read(MAX_CONFIG_BYTES + 1)
    except OSError as exc:
        raise ConfigError(f"{source}: cannot read the config file: {exc.strerror or exc}") from None
    except ValueError as exc:  # a NUL in the path
        raise ConfigError(f"{source}: cannot read the config file: {exc}") from None
    if len(data) > MAX_CONFIG_BYTES:
        raise ConfigError(f"{source}: larger than {MAX_CONFIG_BYTES} bytes: not a config file")
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        raise ConfigError(
            f"{source}:{line}: not UTF-8 text (byte 0x{data[exc.start]:02X} at offset {exc.start}): "
            "is this a binary file?"
        ) from None
    return parse_config(text, source, base_dir=path.absolute().parent), hashlib.sha256(data).hexdigest()
