"""What a dataset snapshot selects, checked whole and kept as canonical JSON text: the runs (every
filter `fleet runs ls` takes), optionally windows around events of some kinds, the entities, the
timeline and rate an export samples at, and a split of the runs, seeded."""

from __future__ import annotations

import datetime as dt
import json
import math
import re
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from typing import Any

from core.clock import iso_utc
from core.errors import BadParameterError
from services.rrd.entity_patterns import check_entity_patterns
from services.runs.service import MAX_CORPUS_FILTERS, RunFilter

MAX_WINDOW_S = 3600.0  # before + after: an episode is a scene, not a run
MAX_FPS = 1000.0
MAX_SPLITS = 16
SPLIT_NAME = re.compile(r"[a-z][a-z0-9_-]{0,31}")
SPLIT_TOLERANCE = 1e-9
KIND = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.:/-]{0,127}")  # an event kind as the catalog holds it
MAX_TIMELINE = 256
SEED_RANGE = (-(2**63), 2**63 - 1)


@dataclass(frozen=True)
class EventWindow:
    """An episode per event of these kinds: [event start - before_s, event end + after_s] on the
    event's timeline (seconds on timestamp and duration timelines, steps on sequence ones)."""

    event: tuple[str, ...]
    before_s: float = 0.0
    after_s: float = 0.0

    def check(self) -> None:
        if not self.event:
            raise BadParameterError("event_window.event", "name at least one event kind to put windows around")
        if len(self.event) > MAX_CORPUS_FILTERS:
            raise BadParameterError("event_window.event", f"{len(self.event)} kinds: at most {MAX_CORPUS_FILTERS}")
        for kind in self.event:
            if not KIND.fullmatch(kind):
                raise BadParameterError(
                    "event_window.event", f"{kind[:200]!r}: letters, digits and _ . : / -, 1 to 128 characters"
                )
        for name, value in (("before_s", self.before_s), ("after_s", self.after_s)):
            if not math.isfinite(value) or value < 0:
                raise BadParameterError(f"event_window.{name}", f"{value}: seconds, 0 or more")
        if self.before_s + self.after_s > MAX_WINDOW_S:
            raise BadParameterError(
                "event_window", f"before_s + after_s is {self.before_s + self.after_s:g} s: at most {MAX_WINDOW_S:g}"
            )


@dataclass(frozen=True)
class Selection:
    """A snapshot's selection. The run filters mean what `GET /v1/runs` means by them."""

    robot: tuple[str, ...] = ()
    application: tuple[str, ...] = ()
    since: dt.datetime | None = None
    until: dt.datetime | None = None
    status: str | None = None
    tier: str | None = None
    entity: tuple[str, ...] = ()
    properties: tuple[tuple[str, str], ...] = ()  # ("fleet.robot_id", "robot-7")
    metric: tuple[str, ...] = ()
    tag: tuple[str, ...] = ()
    event: tuple[str, ...] = ()  # runs with an event of each of these kinds
    event_window: EventWindow | None = None
    include: tuple[str, ...] = ("/**",)
    exclude: tuple[str, ...] = ()
    timeline: str = "log_time"
    fps: float | None = None  # the rate an export samples at
    split: tuple[tuple[str, float], ...] = ()  # ("train", 0.9), in the order given
    seed: int = 0

    def run_filter(self, limit: int = 100, cursor: str | None = None) -> RunFilter:
        """The runs this selection reads, as `list_runs` takes them (in id order: pages are stable)."""
        return RunFilter(
            robot=list(self.robot),
            application=list(self.application),
            since=self.since,
            until=self.until,
            status=self.status,
            tier=self.tier,
            entity=list(self.entity),
            properties=dict(self.properties),
            metric=list(self.metric),
            tag=list(self.tag),
            event=list(self.event),
            sort="id",
            limit=limit,
            cursor=cursor,
        )

    def check(self) -> Selection:
        """Refuse what cannot be resolved (a 422 naming the field); the selection itself if fine."""
        self.run_filter().check()
        if self.since is not None and self.until is not None and self.since >= self.until:
            raise BadParameterError("until", f"{iso_utc(self.until)} is not after since ({iso_utc(self.since)})")
        if self.event_window is not None:
            self.event_window.check()
        if not self.include:
            raise BadParameterError("include", "name at least one entity pattern (default: /** for every entity)")
        check_entity_patterns("include", self.include)
        check_entity_patterns("exclude", self.exclude)
        if not self.timeline or len(self.timeline) > MAX_TIMELINE or "\x00" in self.timeline:
            raise BadParameterError("timeline", f"a timeline's name, 1 to {MAX_TIMELINE} characters (e.g. log_time)")
        if self.fps is not None and not (math.isfinite(self.fps) and 0 < self.fps <= MAX_FPS):
            raise BadParameterError("fps", f"{self.fps}: frames per second, more than 0 and at most {MAX_FPS:g}")
        _check_split(self.split)
        if not SEED_RANGE[0] <= self.seed <= SEED_RANGE[1]:
            raise BadParameterError("seed", f"{self.seed}: a signed 64-bit integer")
        return self

    def to_dict(self) -> dict[str, Any]:
        """The selection as JSON values (what `to_json` writes and the answers show)."""
        out = asdict(self)
        out["since"], out["until"] = iso_utc(self.since), iso_utc(self.until)
        out["properties"] = dict(self.properties)
        out["split"] = {name: fraction for name, fraction in self.split} if self.split else None
        for key in ("robot", "application", "entity", "metric", "tag", "event", "include", "exclude"):
            out[key] = list(out[key])
        if self.event_window is not None:
            out["event_window"] = {**asdict(self.event_window), "event": list(self.event_window.event)}
        return out

    def to_json(self) -> str:
        """Canonical JSON text: sorted keys, no spaces; the same selection is the same text."""
        return json.dumps(self.to_dict(), sort_keys=True, separators=(",", ":"))


def _check_split(split: tuple[tuple[str, float], ...]) -> None:
    if not split:
        return
    if len(split) > MAX_SPLITS:
        raise BadParameterError("split", f"{len(split)} splits: at most {MAX_SPLITS}")
    names = [name for name, _ in split]
    for name, fraction in split:
        if not SPLIT_NAME.fullmatch(name):
            raise BadParameterError("split", f"{name[:80]!r}: a split's name is [a-z][a-z0-9_-]{{0,31}} (e.g. train)")
        if not (math.isfinite(fraction) and fraction > 0):
            raise BadParameterError("split", f"{name}={fraction}: a fraction more than 0")
    if len(set(names)) != len(names):
        raise BadParameterError("split", f"a split named twice: {', '.join(names)}")
    total = math.fsum(fraction for _, fraction in split)
    if abs(total - 1.0) > SPLIT_TOLERANCE:
        raise BadParameterError("split", f"the fractions sum to {total:.12g}: they must sum to 1")


def parse_split(text: str) -> tuple[tuple[str, float], ...]:
    """`train=0.9,val=0.1` as (name, fraction) pairs, in order (422 naming `split` if malformed)."""
    pairs = []
    for item in filter(None, (part.strip() for part in text.split(","))):
        name, sep, value = item.partition("=")
        try:
            fraction = float(value)
        except ValueError:
            fraction = math.nan
        if not sep or math.isnan(fraction):
            raise BadParameterError("split", f"{item!r} is not NAME=FRACTION (e.g. train=0.9,val=0.1)")
        pairs.append((name.strip(), fraction))
    return tuple(pairs)


def split_pairs(split: Mapping[str, float] | None) -> tuple[tuple[str, float], ...]:
    """A JSON object's splits as pairs, in the order given."""
    return tuple((str(name), float(fraction)) for name, fraction in (split or {}).items())
