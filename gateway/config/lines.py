"""Line numbers of TOML keys, for error messages: a best-effort index built by scanning the text.

Why a scanner of our own: :mod:`tomllib` (the standard library's parser, which does the parsing)
reports no positions for the values it returns, and no TOML parser among the project's allowed
dependencies (pymodbus, pyserial, pydantic, prometheus-client, pytest, hypothesis) does. tomlkit,
the maintained round-trip TOML library, keeps comments and layout but gives a line and column only
in its parse errors, not per key of a parsed document, and would be a new dependency. So the
index below maps key paths to the line that first names them: ``[table]`` and
``[[array.of.tables]]`` headers (counting the tables of an array) and ``key = ...`` lines,
skipping the inside of multi-line strings. A key written in an inline table is found at the line
of the key that holds the table.
"""

from __future__ import annotations

import json
import re

from gateway.config._common import Loc

__all__ = ["LineIndex"]

_HEADER_RE = re.compile(r"\s*(\[\[?)\s*(.*?)\s*(\]\]?)\s*(?:#.*)?")
_KEY_PART = r'(?:[A-Za-z0-9_-]+|"(?:[^"\\]|\\.)*"|\'[^\']*\')'
_KEY_LINE_RE = re.compile(rf"\s*({_KEY_PART}(?:\s*\.\s*{_KEY_PART})*)\s*=")
_KEY_PART_RE = re.compile(_KEY_PART)


def _split_key(text: str) -> tuple[str, ...]:
    parts = []
    for match in _KEY_PART_RE.finditer(text):
        part = match.group()
        if part.startswith('"'):
            try:
                part = json.loads(part)
            except ValueError:
                part = part[1:-1]
        elif part.startswith("'"):
            part = part[1:-1]
        parts.append(part)
    return tuple(parts)


class LineIndex:
    """Best-effort map from key paths to line numbers, by scanning the TOML text line by line."""

    def __init__(self, text: str) -> None:
        self.lines: dict[Loc, int] = {}
        arrays: dict[Loc, int] = {}  # array-of-tables path -> index of its last table
        current: Loc = ()
        quote: str | None = None
        for number, line in enumerate(text.split("\n"), start=1):
            if quote is not None:  # inside a multi-line string
                if line.count(quote) % 2 == 1:
                    quote = None
                continue
            header = _HEADER_RE.fullmatch(line)
            if header is not None and len(header[1]) == len(header[3]):
                current = self._resolve(_split_key(header[2]), arrays, is_array=header[1] == "[[")
                self.lines.setdefault(current, number)
                continue
            key = _KEY_LINE_RE.match(line)
            if key is not None:
                self.lines.setdefault(current + _split_key(key[1]), number)
                value = line[key.end() :]
                for candidate in ('"""', "'''"):
                    if value.count(candidate) % 2 == 1:
                        quote = candidate
                        break

    @staticmethod
    def _resolve(keys: tuple[str, ...], arrays: dict[Loc, int], *, is_array: bool) -> Loc:
        path: Loc = ()
        for position, key in enumerate(keys):
            path += (key,)
            if is_array and position == len(keys) - 1:
                arrays[path] = arrays.get(path, -1) + 1
            if path in arrays:
                path += (arrays[path],)
        return path

    def find(self, loc: Loc) -> int | None:
        """The line of ``loc``, else of the nearest enclosing key or table that has one."""
        for length in range(len(loc), 0, -1):
            number = self.lines.get(loc[:length])
            if number is not None:
                return number
        return None
