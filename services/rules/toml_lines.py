"""Line numbers for the problems of a rules file.

tomllib gives a line for syntax errors only (in its message), none for what a parsed file means.
So the lines are found by scanning the text: the n-th `[[event]]` header is the n-th `event` table
tomllib returns (array-of-tables headers, in order), and a key's line is the first line of that
table's section (up to the next `[` header) that starts with `key =`. This is simple and right for
the way rules files are written (one table per header, one key per line); a key written another way
(inside an inline table, on a line of a multi-line string) gets the table's line, or None.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from functools import cached_property

_ARRAY_HEADER = re.compile(r'^\s*\[\[\s*"?([A-Za-z0-9_-]+)"?\s*\]\]')
_ANY_HEADER = re.compile(r'^\s*\[\[?\s*"?([A-Za-z0-9_-]+)"?')
_SYNTAX_LINE = re.compile(r"at line (\d+)")


def _key_line(key: str) -> re.Pattern[str]:
    return re.compile(rf"""^\s*(?:{re.escape(key)}|"{re.escape(key)}"|'{re.escape(key)}')\s*[=.]""")


@dataclass(frozen=True)
class TomlLines:
    """Where the tables and keys of one rules file are (1-based line numbers)."""

    lines: tuple[str, ...]

    @classmethod
    def of(cls, text: str) -> TomlLines:
        return cls(tuple(text.splitlines()))

    @cached_property
    def _headers(self) -> dict[str, list[int]]:
        """The lines of each name's `[[name]]` headers, in order (found once: a file of a thousand
        tables asks for each)."""
        found: dict[str, list[int]] = {}
        for number, line in enumerate(self.lines, 1):
            match = _ARRAY_HEADER.match(line)
            if match:
                found.setdefault(match[1], []).append(number)
        return found

    def table(self, name: str, index: int) -> int | None:
        """The line of the `index`-th (0-based) `[[name]]` header."""
        lines = self._headers.get(name, [])
        return lines[index] if 0 <= index < len(lines) else None

    def key(self, name: str, index: int, key: str) -> int | None:
        """The line of `key` in the `index`-th `[[name]]` table (else the table's line)."""
        start = self.table(name, index)
        if start is None:
            return None
        pattern = _key_line(key)
        for number in range(start + 1, len(self.lines) + 1):
            line = self.lines[number - 1]
            if _ANY_HEADER.match(line):
                break
            if pattern.match(line):
                return number
        return start

    def top_level(self, key: str) -> int | None:
        """The line of a top-level key: `key = ...` before the first header, or a `[key]` or
        `[[key]]` header."""
        pattern = _key_line(key)
        in_top = True
        for number, line in enumerate(self.lines, 1):
            header = _ANY_HEADER.match(line)
            if header:
                in_top = False
                if header[1] == key:
                    return number
            elif in_top and pattern.match(line):
                return number
        return None


def syntax_error_line(message: str) -> int | None:
    """The line tomllib names in a syntax error's message ("... (at line 3, column 7)")."""
    match = _SYNTAX_LINE.search(message)
    return int(match[1]) if match else None
