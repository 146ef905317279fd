"""`[[trigger]]` tables: which events bring the full data of their moment home from the robot.

    [[trigger]]
    event = "hard_brake"                      # an [[event]] rule's name, or a list of them
    include = ["/camera/**", "/lidar/**"]     # the entities to bring home (paths or globs)
    before_s = 10                             # the window around the event, on its timeline
    after_s = 5
    max_bytes_per_robot_day = 500_000_000     # budget (none: only the agent's own cap)
    priority = "high"                         # high | normal

Checked here with the rest of the file (a trigger naming an event no rule of the file makes, a
window over MAX_WINDOW_S or an include that is no entity path or glob is refused); what fires them
and sends the windows is the agent's and the depot's."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from services.rules.globs import compile_glob, entity_problem, is_glob
from services.rules.tables import Problems, Table, shown

MAX_WINDOW_S = 3600.0  # before_s + after_s: a trigger brings moments home, not whole runs
MAX_LIST = 100  # events or includes of one trigger
DEFAULT_BEFORE_S = 10.0
DEFAULT_AFTER_S = 10.0
PRIORITIES = ("high", "normal")
_KEYS = ("event", "include", "before_s", "after_s", "max_bytes_per_robot_day", "priority")


@dataclass(frozen=True)
class TriggerRule:
    """A `[[trigger]]` table, checked."""

    events: tuple[str, ...]  # kinds of the file's [[event]] rules
    include: tuple[str, ...]  # entity paths or globs
    before_s: float = DEFAULT_BEFORE_S
    after_s: float = DEFAULT_AFTER_S
    max_bytes_per_robot_day: int | None = None
    priority: str = "normal"
    line: int | None = None
    globs: tuple[Any, ...] = field(default=(), compare=False, repr=False)  # `include`'s globs, compiled


def trigger_rule(values: dict[str, Any], index: int, problems: Problems, event_names: set[str]) -> TriggerRule | None:
    table = Table("trigger", index, values, _KEYS, problems)
    events = _texts(table, "event")
    unknown = [name for name in events if name not in event_names]
    if unknown:
        made = ", ".join(sorted(event_names)) or "none"
        table.problem("event", f"{shown(unknown[0])} is no [[event]] rule's name in this file (they are: {made})")
    include = _texts(table, "include")
    for pattern in include:
        problem = entity_problem(pattern)
        if problem is not None:
            table.problem("include", problem)
            break
    before_s = table.number("before_s", minimum=0)
    after_s = table.number("after_s", minimum=0)
    before_s = DEFAULT_BEFORE_S if before_s is None else before_s
    after_s = DEFAULT_AFTER_S if after_s is None else after_s
    if before_s + after_s > MAX_WINDOW_S:
        key = "after_s" if "after_s" in values else "before_s"
        table.problem(key, f"a window of {before_s + after_s:g} s: at most {MAX_WINDOW_S:g} s (before_s + after_s)")
    budget = _budget(table)
    priority = table.text("priority", choices=PRIORITIES) or "normal"
    if table.failed:
        return None
    globs = tuple(compile_glob(p) for p in include if is_glob(p))
    return TriggerRule(events, include, before_s, after_s, budget, priority, table.line, globs)


def _texts(table: Table, key: str) -> tuple[str, ...]:
    """A required string, or a non-empty list of them, as a tuple."""
    value = table.values.get(key)
    if value is None:
        table.problem(key, "missing")
        return ()
    items = [value] if isinstance(value, str) else value
    if not isinstance(items, list) or not items or not all(isinstance(v, str) and v for v in items):
        table.problem(key, f"a non-empty string or a list of them, not {shown(value)}")
        return ()
    if len(items) > MAX_LIST:
        table.problem(key, f"{len(items)} entries: at most {MAX_LIST}")
        return ()
    return tuple(dict.fromkeys(items))  # in order, each once


def _budget(table: Table) -> int | None:
    value = table.values.get("max_bytes_per_robot_day")
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
        table.problem("max_bytes_per_robot_day", f"a whole number of bytes above 0, not {shown(value)}")
        return None
    return value
