"""Reading the tables of a rules file: each problem named by line and field, the number listed
capped; shared by the rules of each kind (spec.py, triggers.py)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from services.rules.toml_lines import TomlLines

MAX_RULES = 1000  # tables of each kind
MAX_PROBLEMS = 100  # listed of a refused file; the rest are counted
SHOWN_VALUE = 80  # characters of a value quoted back in a problem


def shown(value: object) -> str:
    """A value quoted back in a problem: its repr, cut at SHOWN_VALUE characters."""
    text = repr(value)
    return text if len(text) <= SHOWN_VALUE else f"{text[:SHOWN_VALUE]}... ({len(text)} characters)"


@dataclass
class Problems:
    lines: TomlLines
    found: list[dict[str, object]] = field(default_factory=list)
    more: int = 0  # problems past MAX_PROBLEMS, counted only

    def room(self) -> bool:
        """Whether another problem is listed: past MAX_PROBLEMS it is only counted (finding the
        line of each of thousands would cost more than the file is worth)."""
        if len(self.found) < MAX_PROBLEMS:
            return True
        self.more += 1
        return False

    def add(self, line: int | None, name: str, message: str) -> None:
        self.found.append({"line": line, "field": name, "message": message})

    def listed(self) -> list[dict[str, object]]:
        if not self.more:
            return self.found
        more = f"{self.more} more problem(s) not listed: at most {MAX_PROBLEMS} are"
        return [*self.found, {"line": None, "field": "file", "message": more}]


def table_name(table: dict[str, Any]) -> str | None:
    name = table.get("name")
    return name if isinstance(name, str) else None


def tables_of(document: dict[str, Any], name: str, problems: Problems | None) -> list[dict[str, Any]]:
    """The `[[name]]` tables of the document (`problems`: where to say they are not tables)."""
    value = document.get(name, [])
    if not isinstance(value, list) or not all(isinstance(t, dict) for t in value):
        if problems is not None and problems.room():
            problems.add(problems.lines.top_level(name), name, f"write each {name} as a [[{name}]] table")
        return []
    if len(value) > MAX_RULES:
        if problems is not None and problems.room():
            problems.add(problems.lines.table(name, MAX_RULES), name, f"{len(value)} tables: at most {MAX_RULES}")
        return []
    return value


class Table:
    """One `[[event]]`, `[[metric]]` or `[[trigger]]` table being read: its values, each problem at its
    key's line."""

    def __init__(self, kind: str, index: int, values: dict[str, Any], allowed: tuple[str, ...], problems: Problems):
        self.kind, self.index, self.values, self.problems = kind, index, values, problems
        self.line = problems.lines.table(kind, index)
        self.failed = False
        for key in values:
            if key not in allowed:
                self.problem(key, f"unknown key; [[{kind}]] has {', '.join(allowed)}")

    def problem(self, key: str, message: str) -> None:
        self.failed = True
        if not self.problems.room():
            return
        line = self.problems.lines.key(self.kind, self.index, key) if key in self.values else self.line
        self.problems.add(line, f"{self.kind}[{self.index + 1}].{key}", message)

    def text(self, key: str, *, required: bool = False, choices: tuple[str, ...] = ()) -> str | None:
        value = self.values.get(key)
        if value is None:
            if required:
                self.problem(key, "missing" + (f" (one of {', '.join(choices)})" if choices else ""))
            return None
        if not isinstance(value, str) or not value:
            self.problem(key, f"a non-empty string, not {shown(value)}")
            return None
        if choices and value not in choices:
            self.problem(key, f"{shown(value)} is none of {', '.join(choices)}")
            return None
        return value

    def number(self, key: str, *, minimum: float | None = None) -> float | None:
        value = self.values.get(key)
        if value is None:
            return None
        if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
            self.problem(key, f"a finite number, not {shown(value)}")
            return None
        if minimum is not None and value < minimum:
            self.problem(key, f"at least {minimum:g}, not {shown(value)}")
            return None
        return float(value)

    def not_for(self, keys: tuple[str, ...], what: str) -> None:
        for key in keys:
            if key in self.values:
                self.problem(key, f"not read {what}")
