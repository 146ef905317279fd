"""The rules file: TOML `[[event]]`, `[[metric]]` and `[[trigger]]` (triggers.py) tables, parsed and
checked whole.

`parse_rules` either gives a `RuleSet` or raises `InvalidRulesError` naming every problem it found
(line, field, message): an unknown key, a missing or mistyped value, a condition without its
threshold, a regex re2 refuses, two rules of one name. Regexes are compiled with re2 (google-re2):
its matching is linear in the text whatever the pattern, so `(a+)+$` is accepted and harmless, and
what re2 cannot do in linear time (backreferences, lookaround) is a problem of the file.
"""

from __future__ import annotations

import re
import tomllib
from dataclasses import dataclass, field
from typing import Any

import re2

from core.errors import InvalidRulesError
from services.rules import tables
from services.rules.globs import compile_glob, entity_problem, is_glob, matches
from services.rules.tables import SHOWN_VALUE, Problems, Table, shown, table_name, tables_of
from services.rules.toml_lines import TomlLines, syntax_error_line
from services.rules.triggers import TriggerRule, trigger_rule

MAX_RULES_BYTES = 1024 * 1024
MAX_RULES = tables.MAX_RULES  # event, metric and trigger rules each
MAX_PROBLEMS = tables.MAX_PROBLEMS
MAX_REGEX_LENGTH = 1000
MAX_KEY_PARTS = 16  # of a dotted key or table name (`a.b.c`): TOML readers spend time and memory on
# each part times the parts before it, so a key of thousands of parts costs gigabytes
_REGEX_MEMORY = 8 << 20  # re2's budget for one compiled pattern: a larger one is refused
_ENTITY_CACHE = 100_000  # entity paths remembered by a rule set; more and it starts over

CONDITIONS = ("falls_below", "rises_above", "below", "above", "text")
NUMERIC = ("falls_below", "rises_above", "below", "above")
SEVERITIES = ("info", "warn", "error")
LEVELS = ("TRACE", "DEBUG", "INFO", "WARN", "ERROR", "CRITICAL")
METRIC_KINDS = ("path_length", "event_count", "duration_s", "mean", "min", "max", "last", "property")
SCALAR_METRICS = ("mean", "min", "max", "last")
LOG_TIME = "log_time"
# A rule's name is an event's kind or a metric's name: it appears in filters (`metric=NAME>3`) and
# in the catalog protocol's column names, so it is kept plain.
_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,127}")
_EVENT_KEYS = ("name", "entity", "when", "threshold", "for_s", "level", "match", "timeline", "severity")
_METRIC_KEYS = ("name", "kind", "entity", "event", "property")
# A run of more than MAX_KEY_PARTS dotted key parts, anywhere (re2: linear time over the whole file).
_KEY_PART = r"""(?:[A-Za-z0-9_-]+|"[^"\n]*"|'[^'\n]*')"""
_DEEP_KEY = re2.compile(rf"{_KEY_PART}(?:[ \t]*\.[ \t]*{_KEY_PART}){{{MAX_KEY_PARTS}}}")
_METRIC_NEEDS = {
    "path_length": ("entity",),
    "event_count": ("event",),
    "duration_s": ("event",),
    "mean": ("entity",),
    "min": ("entity",),
    "max": ("entity",),
    "last": ("entity",),
    "property": ("property",),
}


@dataclass(frozen=True)
class EventRule:
    """An `[[event]]` table: the condition that makes events of kind `name` on `entity` (a glob:
    each matching entity on its own)."""

    name: str
    entity: str
    when: str  # falls_below | rises_above | below | above | text
    severity: str = "info"
    threshold: float | None = None  # the numeric conditions'
    for_s: float = 0.0  # below / above: how long the condition must hold (ticks on a sequence timeline)
    level: str | None = None  # text: the lowest TextLog level (None: any)
    match: str | None = None  # text: a regex the text must contain a match of (None: any text)
    timeline: str = LOG_TIME
    line: int | None = None
    pattern: Any = field(default=None, compare=False, repr=False)  # `match` compiled (re2)
    glob: Any = field(default=None, compare=False, repr=False)  # `entity` compiled, when a glob


@dataclass(frozen=True)
class MetricRule:
    """A `[[metric]]` table: one value per run."""

    name: str
    kind: str  # path_length | event_count | duration_s | mean | min | max | last | property
    entity: str | None = None  # path_length and the Scalars kinds: one entity path
    event: str | None = None  # event_count, duration_s: an event kind (a rule's, or robots')
    property: str | None = None  # property: PROPERTY.FIELD, e.g. fleet.sw_version
    line: int | None = None


@dataclass(frozen=True)
class EntityRules:
    """What the rules read of one entity path."""

    events: tuple[EventRule, ...] = ()
    path_length: bool = False  # its Transform3D translations
    scalar_stats: bool = False  # its Scalars, for mean / min / max / last

    def __bool__(self) -> bool:
        return bool(self.events) or self.path_length or self.scalar_stats


NO_RULES = EntityRules()


@dataclass(frozen=True)
class RuleSet:
    """A checked rules file."""

    events: tuple[EventRule, ...] = ()
    metrics: tuple[MetricRule, ...] = ()
    triggers: tuple[TriggerRule, ...] = ()
    text: str = ""
    _by_entity: dict[str, EntityRules] = field(default_factory=dict, compare=False, repr=False)

    @classmethod
    def empty(cls) -> RuleSet:
        return cls()

    def names_entity(self, path: str) -> bool:
        """Whether a rule reads this entity (one dict lookup once the path was seen)."""
        return bool(self.rules_for(path))

    def rules_for(self, path: str) -> EntityRules:
        """The rules that read `path`: each glob matched once per path, then remembered."""
        found = self._by_entity.get(path)
        if found is None:
            if len(self._by_entity) >= _ENTITY_CACHE:
                self._by_entity.clear()
            found = self._by_entity[path] = self._match(path)
        return found

    def _match(self, path: str) -> EntityRules:
        events = tuple(r for r in self.events if r.entity == path or (r.glob is not None and matches(r.glob, path)))
        kinds = {m.kind for m in self.metrics if m.entity == path}
        found = EntityRules(events, "path_length" in kinds, bool(kinds & set(SCALAR_METRICS)))
        return found if found else NO_RULES


# --- parsing -------------------------------------------------------------------------------------


def parse_rules(text: str) -> RuleSet:
    """The rules of a TOML rules file; InvalidRulesError listing every problem (nothing is half-read)."""
    problems = Problems(TomlLines.of(text))
    document = _document(text, problems)
    for key in document:
        if key not in ("event", "metric", "trigger") and problems.room():
            problems.add(
                problems.lines.top_level(key),
                key,
                "unknown key: a rules file holds [[event]], [[metric]] and [[trigger]]",
            )
    events = [_event_rule(t, i, problems) for i, t in enumerate(tables_of(document, "event", problems))]
    metrics = [_metric_rule(t, i, problems) for i, t in enumerate(tables_of(document, "metric", problems))]
    event_names = {r.name for r in events if r is not None}
    triggers = [
        trigger_rule(t, i, problems, event_names) for i, t in enumerate(tables_of(document, "trigger", problems))
    ]
    _check_unique("event", [table_name(t) for t in tables_of(document, "event", None)], problems)
    _check_unique("metric", [table_name(t) for t in tables_of(document, "metric", None)], problems)
    if problems.found:
        raise InvalidRulesError(problems.listed())
    return RuleSet(
        tuple(r for r in events if r is not None),
        tuple(r for r in metrics if r is not None),
        tuple(r for r in triggers if r is not None),
        text,
    )


def _document(text: str, problems: Problems) -> dict[str, Any]:
    """The TOML of `text`, read only when its size and shape are ones a reader copes with."""
    size = len(text.encode(errors="surrogatepass"))
    if size > MAX_RULES_BYTES:
        problems.add(None, "file", f"{size} bytes: a rules file holds at most {MAX_RULES_BYTES}")
        raise InvalidRulesError(problems.found)
    deep = _DEEP_KEY.search(text)
    if deep is not None:
        line = text.count("\n", 0, deep.start()) + 1
        problems.add(line, "toml", f"a dotted key of more than {MAX_KEY_PARTS} parts: a rules file needs at most 3")
        raise InvalidRulesError(problems.found)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        problems.add(syntax_error_line(str(exc)), "toml", f"not valid TOML: {exc}")
        raise InvalidRulesError(problems.found) from exc
    except RecursionError:  # arrays or inline tables in arrays, thousands deep
        problems.add(None, "toml", "arrays or inline tables nested too deeply: a rules file has none nested")
        raise InvalidRulesError(problems.found) from None


def _name(table: Table) -> str | None:
    name = table.text("name", required=True)
    if name is not None and not _NAME.fullmatch(name):
        table.problem(
            "name", f"{shown(name)}: letters, digits, '_', '.', '-' (up to 128, not starting with '.' or '-')"
        )
        return None
    return name


def _entity(table: Table, *, glob: bool) -> tuple[str | None, Any]:
    entity = table.text("entity", required=True)
    if entity is None:
        return None, None
    problem = entity_problem(entity)
    if problem is None and is_glob(entity) and not glob:
        problem = f"{shown(entity)}: a metric reads one entity, not a glob"
    if problem is not None:
        table.problem("entity", problem)
        return None, None
    return entity, compile_glob(entity) if is_glob(entity) else None


def _event_rule(values: dict[str, Any], index: int, problems: Problems) -> EventRule | None:
    table = Table("event", index, values, _EVENT_KEYS, problems)
    name = _name(table)
    entity, glob = _entity(table, glob=True)
    when = table.text("when", required=True, choices=CONDITIONS)
    severity = table.text("severity", choices=SEVERITIES) or "info"
    timeline = table.text("timeline") or LOG_TIME
    for_s = table.number("for_s", minimum=0) or 0.0
    threshold, level, match, pattern = None, None, None, None
    if when in NUMERIC:
        table.not_for(("level", "match"), f"by when = {when!r} (only by when = 'text')")
        threshold = table.number("threshold")
        if threshold is None and "threshold" not in values:
            table.problem("threshold", f"missing: when = {when!r} compares the value with a threshold")
    elif when == "text":
        table.not_for(("threshold", "for_s"), "by when = 'text' (only by the numeric conditions)")
        level = _level(table)
        match, pattern = _regex(table)
    if table.failed or name is None or entity is None or when is None:
        return None
    return EventRule(name, entity, when, severity, threshold, for_s, level, match, timeline, table.line, pattern, glob)


def _level(table: Table) -> str | None:
    level = table.text("level")
    if level is not None and level.upper() not in LEVELS:
        table.problem("level", f"{shown(level)} is none of {', '.join(LEVELS)}")
        return None
    return level.upper() if level is not None else None


def _regex(table: Table) -> tuple[str | None, Any]:
    match = table.text("match")
    if match is None:
        return None, None
    if len(match) > MAX_REGEX_LENGTH:
        table.problem("match", f"a regex of {len(match)} characters: at most {MAX_REGEX_LENGTH}")
        return None, None
    options = re2.Options()
    options.log_errors = False
    options.max_mem = _REGEX_MEMORY
    try:
        return match, re2.compile(match, options)
    except re2.error as exc:
        reason = exc.args[0].decode(errors="replace") if exc.args and isinstance(exc.args[0], bytes) else str(exc)
        table.problem("match", f"{shown(match)} is not a regex re2 runs in linear time: {reason[:SHOWN_VALUE]}")
        return None, None


def _metric_rule(values: dict[str, Any], index: int, problems: Problems) -> MetricRule | None:
    table = Table("metric", index, values, _METRIC_KEYS, problems)
    name = _name(table)
    kind = table.text("kind", required=True, choices=METRIC_KINDS)
    if kind is None:
        return None
    needs = _METRIC_NEEDS[kind]
    table.not_for(tuple(k for k in ("entity", "event", "property") if k not in needs), f"by kind = {kind!r}")
    entity = _entity(table, glob=False)[0] if "entity" in needs else None
    event = table.text("event", required=True) if "event" in needs else None
    prop = table.text("property", required=True) if "property" in needs else None
    if prop is not None and "." not in prop.strip("."):
        table.problem("property", f"{shown(prop)}: write PROPERTY.FIELD, e.g. fleet.sw_version")
    if table.failed or name is None:
        return None
    return MetricRule(name, kind, entity, event, prop, table.line)


def _check_unique(kind: str, names: list[str | None], problems: Problems) -> None:
    """Two `kind` tables of one name (`names`: each table's, None where it has none)."""
    first: dict[str, int] = {}
    for index, name in enumerate(names):
        if name is None:
            continue
        if name in first and problems.room():
            earlier = problems.lines.key(kind, first[name], "name")
            problems.add(
                problems.lines.key(kind, index, "name"),
                f"{kind}[{index + 1}].name",
                f"{shown(name)} names {kind}[{first[name] + 1}] too" + (f" (line {earlier})" if earlier else ""),
            )
        elif name not in first:
            first[name] = index
