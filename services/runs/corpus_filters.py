"""What the corpus adds to finding runs: conditions on a run's metrics (`distance_m>100`), tags
(`night-shift`) and events (`intervention`: has at least one), and sorting by a metric
(`metric.distance_m`, `-metric.distance_m`), as SQL over the catalog's corpus tables (the same on
Postgres and DuckDB).

A run without a metric matches no condition on it (`!=` included) and sorts after every run that
has it, in either direction.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Any

import sqlalchemy as sa
from sqlalchemy.orm import Session, aliased

from catalog.models import Event, Run, RunMetric, RunTag
from core.errors import BadParameterError

OPERATORS = (">=", "<=", "!=", ">", "<", "=")  # longest first: `>=` is not `>` then `=100`
METRIC_FORM = "NAME OP VALUE with OP one of > >= < <= = != (e.g. distance_m>100, sw_version=2.3)"
_NAME = r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,127}"  # a metric's name, as the rules file allows it
_CONDITION = re.compile(rf"\s*({_NAME})\s*({'|'.join(re.escape(op) for op in OPERATORS)})\s*(.*?)\s*", re.DOTALL)
SORT_PREFIX = "metric."


@dataclass(frozen=True)
class MetricCondition:
    name: str
    op: str
    text: str  # the value as written
    number: float | None  # the value as a number, when it is one

    @classmethod
    def parse(cls, expression: str) -> MetricCondition:
        """`distance_m>100` -> (distance_m, >, 100); a 422 naming the problem and the form otherwise."""
        found = _CONDITION.fullmatch(expression)
        if found is None:
            raise BadParameterError("metric", f"{expression!r} is not {METRIC_FORM}")
        name, op, text = found.groups()
        if not text:
            raise BadParameterError("metric", f"{expression!r} has no value after {op!r}: {METRIC_FORM}")
        if text[0] in "<>=!":  # `=>100`, `>>1`: an operator mistyped, not a text value
            raise BadParameterError("metric", f"{expression!r} has two operators: {METRIC_FORM}")
        number = _number(text)
        if op not in ("=", "!=") and number is None:
            raise BadParameterError(
                "metric", f"{expression!r}: {op} compares numbers and {text!r} is not one; {METRIC_FORM}"
            )
        return cls(name, op, text, number)

    def condition(self) -> sa.ColumnElement[bool]:
        """The run has the metric and its value meets the condition: `=` and `!=` compare the text
        of a text metric and the number of a number metric; the others compare numbers."""
        held = sa.and_(RunMetric.run_id == Run.id, RunMetric.name == self.name)
        return sa.exists().where(held, self._meets())

    def _meets(self) -> sa.ColumnElement[bool]:
        value, text = RunMetric.value, RunMetric.text_value
        if self.op in ("=", "!="):
            same_text = text == self.text if self.op == "=" else text != self.text
            on_text = sa.and_(text.is_not(None), same_text)
            numeric = sa.and_(text.is_(None), value.is_not(None))
            if self.number is None:  # a number metric never equals a word
                return on_text if self.op == "=" else sa.or_(on_text, numeric)
            same_number = value == self.number if self.op == "=" else value != self.number
            return sa.or_(on_text, sa.and_(numeric, same_number))
        compare = {">": value > self.number, ">=": value >= self.number, "<": value < self.number}
        compare["<="] = value <= self.number
        return sa.and_(value.is_not(None), compare[self.op])


def _number(text: str) -> float | None:
    try:
        number = float(text)
    except ValueError:
        return None
    return number if math.isfinite(number) else None


def tag_condition(tag: str) -> sa.ColumnElement[bool]:
    return sa.exists().where(RunTag.run_id == Run.id, RunTag.tag == tag)


def event_condition(kind: str) -> sa.ColumnElement[bool]:
    return sa.exists().where(Event.run_id == Run.id, Event.kind == kind)


# --- sorting by a metric --------------------------------------------------------------------------


def sort_metric(sort: str) -> str | None:
    """The metric a sort names (`metric.NAME` or `-metric.NAME`), None for the other sorts;
    a 422 for a malformed name."""
    column = sort.removeprefix("-")
    if not column.startswith(SORT_PREFIX):
        return None
    name = column.removeprefix(SORT_PREFIX)
    if not re.fullmatch(_NAME, name):
        raise BadParameterError("sort", f"{sort!r}: metric.NAME or -metric.NAME with the name of a metric")
    return name


def metric_sorted(
    session: Session,
    query: sa.Select[Any],
    name: str,
    descending: bool,
    after: tuple[float | None, str] | None,
    limit: int,
) -> list[tuple[Run, float | None]]:
    """Up to `limit` runs of `query` (a select of Run) with their value of metric `name`, in that
    order (runs without a value last, either way), then run id; from the cursor `after` on (the
    last row's value and run id). Read as two queries, the runs with a value in its order, then the
    others by id: one query ordering an outer join of every run to its metric would sort all of
    them, where these walk an index (run_metrics by name and value; the run ids) and stop at `limit`."""
    rows: list[tuple[Run, float | None]] = []
    if after is None or after[0] is not None:
        rows = _with_value(session, query, name, descending, after, limit)
    if len(rows) < limit:
        last_id = after[1] if after is not None and after[0] is None else None
        rows += [(run, None) for run in _without_value(session, query, name, descending, last_id, limit - len(rows))]
    return rows


def _with_value(
    session: Session,
    query: sa.Select[Any],
    name: str,
    descending: bool,
    after: tuple[float | None, str] | None,
    limit: int,
) -> list[tuple[Run, float | None]]:
    metric = aliased(RunMetric, name="sort_metric")
    value = metric.value
    joined = query.join(metric, sa.and_(metric.run_id == Run.id, metric.name == name)).where(value.is_not(None))
    if after is not None:
        last_value, last_id = after
        later_id = Run.id < last_id if descending else Run.id > last_id
        beyond = value < last_value if descending else value > last_value
        # The first condition bounds the index range; the second is the cursor's exact condition.
        reached = value <= last_value if descending else value >= last_value
        joined = joined.where(reached, sa.or_(beyond, sa.and_(value == last_value, later_id)))
    order = (value.desc(), Run.id.desc()) if descending else (value.asc(), Run.id.asc())
    found = session.execute(joined.add_columns(value).order_by(*order).limit(limit))
    return [(run, number) for run, number in found]


def _without_value(
    session: Session, query: sa.Select[Any], name: str, descending: bool, last_id: str | None, limit: int
) -> list[Run]:
    """The runs of `query` that have no value of metric `name` (no row, or a text metric), by id."""
    valued = sa.exists().where(RunMetric.run_id == Run.id, RunMetric.name == name, RunMetric.value.is_not(None))
    rest = query.where(~valued)
    if last_id is not None:
        rest = rest.where(Run.id < last_id if descending else Run.id > last_id)
    return list(session.scalars(rest.order_by(Run.id.desc() if descending else Run.id.asc()).limit(limit)))


def cursor_value(value: Any) -> float | None:
    """A metric sort's cursor value, checked (client input); ValueError if it is not one."""
    if value is None:
        return None
    if type(value) not in (int, float):
        raise ValueError(value)
    try:
        number = float(value)
    except OverflowError:  # an integer of hundreds of digits
        raise ValueError(value) from None
    if not math.isfinite(number):
        raise ValueError(value)
    return number
