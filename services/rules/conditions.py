"""What an event rule finds in one entity's samples: ranges for the numeric conditions, instants for
text, and robots' own events (a TextLog under `/events/**`).

The numeric conditions are state machines fed samples in time order, chunk after chunk: a range
opens at the first sample where the condition holds (for `falls_below` / `rises_above`, only at a
crossing: a sample after one where it did not) and closes at the first sample where it no longer
holds, or at the entity's last sample when the run ends. Only the samples where the state changes
are walked in Python: a long run of samples that keep the state costs a numpy comparison.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from services.rules.spec import LEVELS, EventRule

ROBOT_EVENTS = "/events/"  # a TextLog under it is a robot's event, its kind the path below
MAX_KIND_LENGTH = 256  # the catalog's `events.kind`
MAX_LABEL_LENGTH = 4096
_RANK = {level: rank for rank, level in enumerate(LEVELS)}
_UNKNOWN_LEVEL = _RANK["INFO"]  # a TextLog without a level, or with one of its own, counts as INFO
_PHRASES = {"below": "below", "above": "above", "falls_below": "fell below", "rises_above": "rose above"}
_NS_PER_S = 1_000_000_000


@dataclass(frozen=True)
class Found:
    """A range (inclusive; start = end: an instant) on a timeline, and its label."""

    start: int
    end: int
    label: str


class NumericCondition:
    """One numeric rule (below | above | falls_below | rises_above) on one entity, on its timeline."""

    def __init__(self, rule: EventRule, entity: str, timeline_type: str) -> None:
        assert rule.threshold is not None
        self.rule, self.timeline_type = rule, timeline_type
        self.threshold = rule.threshold
        self.crossing = rule.when in ("falls_below", "rises_above")
        self.below = rule.when in ("below", "falls_below")
        # `for_s` counts ticks on a sequence timeline, seconds (as ns) on the others; a crossing's
        # range is kept however short.
        scale = 1 if timeline_type == "sequence" else _NS_PER_S
        self.min_length = 0.0 if self.crossing else rule.for_s * scale
        self.label = label_of(f"{entity} {_PHRASES[rule.when]} {self.threshold:g}")
        self._holds: bool | None = None  # at the last sample (None: no sample yet)
        self._start: int | None = None  # of the open range
        self._last: int | None = None  # time of the last sample

    def feed(self, times: np.ndarray, values: np.ndarray) -> list[Found]:
        """The ranges closed by these samples (time order; no NaN)."""
        if len(times) == 0:
            return []
        holds = values < self.threshold if self.below else values > self.threshold
        before = np.concatenate(([holds[0] if self._holds is None else self._holds], holds[:-1]))
        changes = np.flatnonzero(holds != before)
        found = []
        if self._holds is None and holds[0] and not self.crossing:
            self._start = int(times[0])  # holds from the entity's first sample
        for i in changes:
            if holds[i]:
                self._start = int(times[i])
            elif self._start is not None:
                found += self._close(int(times[i]))
        self._holds, self._last = bool(holds[-1]), int(times[-1])
        return found

    def finish(self) -> list[Found]:
        """The range still open at the end of the run, closed at the entity's last sample."""
        if self._start is None or self._last is None:
            return []
        return self._close(self._last)

    def _close(self, end: int) -> list[Found]:
        start, self._start = self._start, None
        assert start is not None
        return [Found(start, end, self.label)] if end - start >= self.min_length else []


def text_matches(
    rule: EventRule, times: np.ndarray, texts: list[str | None], levels: list[str | None]
) -> Iterator[Found]:
    """Each row (with a time) whose level is at least the rule's and whose text matches: an instant."""
    lowest = _RANK[rule.level] if rule.level is not None else None
    for t, text, level in zip(times.tolist(), texts, levels, strict=True):
        if text is None or (lowest is not None and level_rank(level) < lowest):
            continue
        if rule.pattern is None or rule.pattern.search(text) is not None:
            yield Found(t, t, label_of(text))


def level_rank(level: str | None) -> int:
    return _RANK.get(level.upper(), _UNKNOWN_LEVEL) if level else _UNKNOWN_LEVEL


def robot_kind(entity_path: str) -> str | None:
    """`/events/hard_brake` -> `hard_brake` (None: not a robot's event entity)."""
    if not entity_path.startswith(ROBOT_EVENTS) or len(entity_path) == len(ROBOT_EVENTS):
        return None
    return entity_path[len(ROBOT_EVENTS) :][:MAX_KIND_LENGTH]


def robot_severity(level: str | None) -> str:
    rank = level_rank(level)
    return "error" if rank >= _RANK["ERROR"] else "warn" if rank == _RANK["WARN"] else "info"


def label_of(text: str) -> str:
    return text[:MAX_LABEL_LENGTH]
