"""Quality checks of an episode, made from the rows an export reads (no second read): a camera frozen
(the same image for `frozen_s` seconds or more), timestamps that go back within a chunk or repeat,
an exported entity missing from the episode, an episode shorter than `min_frames`, a run still hot
(its data may still grow: the export reads it as it stands).

Each problem is a `Flag`: the check's name, the entity it is about (if any), and what was found.
`missing_entity`, `empty`, `shape` (its vectors do not have the first exported episode's widths) and
`missing_run` (its run deleted, or not readable now) stop the episode from being exported (nothing
fills its vectors or its video); the others are reported and the episode is exported, unless the
export is strict, which refuses if any episode has a flag.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from services.datasets.samples import EncodedImage, RawImage

NS = 1_000_000_000
FROZEN = "frozen_camera"
TIMESTAMPS = "timestamps"
MISSING = "missing_entity"
SHORT = "short"
HOT = "hot_run"
EMPTY = "empty"
SHAPE = "shape"
MISSING_RUN = "missing_run"
BLOCKING = frozenset({MISSING, EMPTY, SHAPE, MISSING_RUN})  # the episode is not exported
CHECKS = (FROZEN, TIMESTAMPS, MISSING, SHORT, HOT, EMPTY, SHAPE, MISSING_RUN)


@dataclass(frozen=True)
class Limits:
    """When a check flags: a camera unchanged this many seconds, an episode of fewer frames."""

    frozen_s: float = 2.0
    min_frames: int = 1

    def as_json(self) -> dict[str, Any]:
        return {"frozen_s": self.frozen_s, "min_frames": self.min_frames}

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> Limits:
        return cls(float(data["frozen_s"]), int(data["min_frames"]))


@dataclass(frozen=True)
class Flag:
    check: str
    entity: str | None
    detail: str

    def as_json(self) -> dict[str, Any]:
        return {"check": self.check, "entity": self.entity, "detail": self.detail}


def image_digest(value: Any) -> int | None:
    """A cheap identity of an image row's bytes (two frames of a frozen camera are the same bytes)."""
    if isinstance(value, RawImage):
        return hash(value.buffer)
    if isinstance(value, EncodedImage):
        return hash(value.blob)
    return None


@dataclass
class _Camera:
    digest: int | None = None
    since: int = 0  # time of the first row with this digest
    last: int = 0
    longest: tuple[int, int] | None = None  # the longest frozen stretch (start, end) at or past the limit


@dataclass
class EpisodeQuality:
    """Fed with an episode's rows as an export reads them; `flags()` at the end."""

    limits: Limits
    cameras: frozenset[str] = frozenset()
    backwards: dict[str, int] = field(default_factory=dict)
    repeats: dict[str, int] = field(default_factory=dict)
    _cameras: dict[str, _Camera] = field(default_factory=dict)
    flagged: list[Flag] = field(default_factory=list)

    def rows(self, entity: str, times: np.ndarray, values: list[Any]) -> None:
        """A chunk's rows of `entity` as logged (times in the chunk's order)."""
        if len(times) > 1:
            back = int(np.count_nonzero(np.diff(times) < 0))
            if back:
                self.backwards[entity] = self.backwards.get(entity, 0) + back
        if entity in self.cameras:
            self._frozen(entity, times, values)

    def duplicates(self, entity: str, count: int) -> None:
        """`count` more rows of `entity` at a time another of its rows has."""
        if count:
            self.repeats[entity] = self.repeats.get(entity, 0) + count

    def _frozen(self, entity: str, times: np.ndarray, values: list[Any]) -> None:
        state = self._cameras.setdefault(entity, _Camera())
        limit = int(self.limits.frozen_s * NS)
        for time, value in zip(times.tolist(), values, strict=True):
            digest = image_digest(value)
            if digest is None or digest != state.digest:
                state.digest, state.since = digest, time
            state.last = time
            stretch = state.last - state.since
            best = state.longest
            if digest is not None and stretch >= limit and (best is None or stretch > best[1] - best[0]):
                state.longest = (state.since, state.last)

    def add(self, flag: Flag) -> None:
        self.flagged.append(flag)

    def blocked(self) -> bool:
        """A flag that stops the episode from being exported."""
        return any(f.check in BLOCKING for f in self.flagged)

    def flags(self) -> list[Flag]:
        out = list(self.flagged)
        for entity, state in sorted(self._cameras.items()):
            if state.longest is not None:
                start, end = state.longest
                out.append(
                    Flag(FROZEN, entity, f"the same image for {(end - start) / NS:.1f} s (from {start} to {end} ns)")
                )
        for entity in sorted(set(self.backwards) | set(self.repeats)):
            said = []
            if self.backwards.get(entity):
                said.append(f"{self.backwards[entity]} time(s) going back within a chunk")
            if self.repeats.get(entity):
                said.append(f"{self.repeats[entity]} row(s) at a time another row already has")
            out.append(Flag(TIMESTAMPS, entity, "; ".join(said)))
        return out
