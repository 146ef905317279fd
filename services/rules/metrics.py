"""Run metrics, accumulated chunk by chunk: a path's length, statistics of a Scalars entity, the
count and total time of events of a kind, and a recording property's field."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

_NS_PER_S = 1e9


@dataclass
class PathLength:
    """Distances between consecutive translations of one entity, fed in log_time order."""

    total: float = 0.0
    last: np.ndarray | None = None

    def feed(self, times: np.ndarray, points: np.ndarray) -> None:
        if len(points) == 0:
            return
        path = points if self.last is None else np.vstack([self.last[None, :], points])
        self.total += float(np.linalg.norm(np.diff(path, axis=0), axis=1).sum())
        self.last = points[-1]

    def value(self) -> float | None:
        return self.total if self.last is not None else None  # no translation: no metric


@dataclass
class ScalarStats:
    """Mean, min, max and last of one entity's Scalars (first instance; NaN skipped). `last`: the value
    at the greatest log_time (of equal times, the one that came later; without log_time, below any
    with one): the same whatever order the chunks came in."""

    count: int = 0
    total: float = 0.0
    low: float = math.inf
    high: float = -math.inf
    last_key: tuple[int, int, int] | None = None
    last: float = math.nan
    arrivals: int = 0

    def feed(self, values: np.ndarray, log_times: np.ndarray | None) -> None:
        """`values` without NaN; `log_times` the rows' log_time (None: the rows have none)."""
        if len(values) == 0:
            return
        self.count += len(values)
        self.total += float(values.sum())
        self.low = min(self.low, float(values.min()))
        self.high = max(self.high, float(values.max()))
        at = int(np.argmax(log_times[::-1])) if log_times is not None else 0
        newest = len(values) - 1 - at  # the last row of the greatest log_time
        key = (1, int(log_times[newest]), self.arrivals) if log_times is not None else (0, 0, self.arrivals)
        self.arrivals += 1
        if self.last_key is None or key >= self.last_key:
            self.last_key, self.last = key, float(values[newest])

    def value(self, kind: str) -> float | None:
        if self.count == 0:
            return None
        return {"mean": self.total / self.count, "min": self.low, "max": self.high, "last": self.last}[kind]


@dataclass
class KindTotals:
    """The events of one kind a run's evaluation found (those past the cap too)."""

    count: int = 0
    duration_ns: int = 0
    timed: int = 0  # events on a timestamp or duration timeline: those `duration_s` adds up

    def add(self, timeline_type: str, start: int, end: int) -> None:
        self.count += 1
        if timeline_type != "sequence":
            self.timed += 1
            self.duration_ns += end - start


@dataclass
class EventTotals:
    by_kind: dict[str, KindTotals] = field(default_factory=dict)

    def add(self, kind: str, timeline_type: str, start: int, end: int) -> None:
        self.by_kind.setdefault(kind, KindTotals()).add(timeline_type, start, end)

    def count(self, kind: str) -> float:
        """Events of `kind`: 0 when the run has none (a count, not missing data)."""
        totals = self.by_kind.get(kind)
        return float(totals.count if totals else 0)

    def duration_s(self, kind: str) -> float | None:
        """Their total time in seconds: 0 when the run has none; None when all are on sequence
        timelines (no time to add up)."""
        totals = self.by_kind.get(kind)
        if totals is None:
            return 0.0
        return totals.duration_ns / _NS_PER_S if totals.timed else None


def property_value(properties: dict[str, dict[str, Any]], name: str) -> tuple[float | None, str | None] | None:
    """`fleet.sw_version` of the run's properties: (number, None) for a number, (None, text) for
    anything else (a list or an object as JSON); None when the run has no such field."""
    prop, _, fld = name.partition(".")
    value = properties.get(prop, {}).get(fld)
    if value is None:
        return None
    if isinstance(value, int | float) and not isinstance(value, bool):
        return (float(value), None) if math.isfinite(value) else (None, str(value))
    if isinstance(value, str):
        return None, value
    if isinstance(value, bool):
        return None, "true" if value else "false"
    return None, json.dumps(value, sort_keys=True)
