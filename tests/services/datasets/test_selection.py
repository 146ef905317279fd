"""A snapshot's selection: each bad field refused naming it, canonical JSON text, and the split of
runs by a seeded hash (deterministic, every fraction respected over many runs)."""

from __future__ import annotations

import datetime as dt
import json
from collections import Counter
from typing import Any

import pytest

from core.errors import BadParameterError
from services.datasets.resolve import split_of
from services.datasets.selection import EventWindow, Selection, parse_split

WINDOW = EventWindow(("intervention",), 5, 2)


@pytest.mark.parametrize(
    ("changes", "field"),
    [
        ({"status": "asleep"}, "status"),
        ({"tier": "lukewarm"}, "tier"),
        ({"metric": ("distance_m~3",)}, "metric"),
        ({"properties": (("no_dot", "x"),)}, "property"),
        ({"robot": ("a\x00b",)}, "robot"),
        ({"tag": tuple(f"t{i}" for i in range(33))}, "tag"),
        ({"since": dt.datetime(2026, 2, 1, tzinfo=dt.UTC), "until": dt.datetime(2026, 1, 1, tzinfo=dt.UTC)}, "until"),
        ({"event_window": EventWindow(())}, "event_window.event"),
        ({"event_window": EventWindow(("bad kind",))}, "event_window.event"),
        ({"event_window": EventWindow(("x",), before_s=-1)}, "event_window.before_s"),
        ({"event_window": EventWindow(("x",), after_s=float("nan"))}, "event_window.after_s"),
        ({"event_window": EventWindow(("x",), before_s=3000, after_s=601)}, "event_window"),
        ({"include": ()}, "include"),
        ({"include": ("robot",)}, "include"),
        ({"exclude": ("/a/**/b",)}, "exclude"),
        ({"timeline": ""}, "timeline"),
        ({"timeline": "t" * 257}, "timeline"),
        ({"fps": 0.0}, "fps"),
        ({"fps": 1000.5}, "fps"),
        ({"fps": float("inf")}, "fps"),
        ({"split": (("train", 0.9), ("val", 0.2))}, "split"),
        ({"split": (("Train", 0.5), ("val", 0.5))}, "split"),
        ({"split": (("train", 1.0), ("val", 0.0))}, "split"),
        ({"split": (("train", 0.5), ("train", 0.5))}, "split"),
        ({"split": (("a" * 33, 1.0),)}, "split"),
        ({"seed": 2**63}, "seed"),
    ],
)
def test_a_bad_field_is_refused_naming_it(changes: dict[str, Any], field: str):
    with pytest.raises(BadParameterError) as info:
        Selection(**changes).check()
    assert info.value.parameter == field, info.value
    assert info.value.http_status() == 422


def test_good_selections_pass():
    Selection().check()
    Selection(
        robot=("robot-7",),
        event_window=EventWindow(("intervention",), 3000, 600),
        fps=1000.0,
        split=(("train", 0.8), ("val", 0.1), ("test", 0.1)),  # 0.8 + 0.1 + 0.1 is 1 within 1e-9
        seed=-(2**63),
    ).check()


def test_the_selection_is_canonical_json():
    one = Selection(robot=("b", "a"), since=dt.datetime(2026, 1, 1, tzinfo=dt.UTC), event_window=WINDOW, fps=10.0)
    text = one.to_json()
    assert text == Selection(**{**one.__dict__}).to_json()  # the same selection: the same text
    assert " " not in text and list(json.loads(text)) == sorted(json.loads(text))
    shown = json.loads(text)
    assert shown["robot"] == ["b", "a"] and shown["since"] == "2026-01-01T00:00:00Z"
    assert shown["event_window"] == {"event": ["intervention"], "before_s": 5, "after_s": 2}
    assert shown["include"] == ["/**"] and shown["timeline"] == "log_time" and shown["split"] is None
    assert json.loads(Selection(split=(("val", 0.1), ("train", 0.9))).to_json())["split"] == {"val": 0.1, "train": 0.9}


def test_a_split_is_parsed_in_order():
    assert parse_split("train=0.9, val=0.1") == (("train", 0.9), ("val", 0.1))
    for bad in ("train", "train=x", "train=0.9,val"):
        with pytest.raises(BadParameterError, match="'split'"):
            parse_split(bad)


SPLIT = (("train", 0.7), ("val", 0.2), ("test", 0.1))
RUNS = [f"run-{i:05d}" for i in range(20_000)]


def test_the_same_seed_splits_the_same_way_and_another_may_not():
    first = [split_of(0, run, SPLIT) for run in RUNS[:500]]
    assert first == [split_of(0, run, SPLIT) for run in RUNS[:500]]
    other = [split_of(1, run, SPLIT) for run in RUNS[:500]]
    assert other != first
    assert split_of(0, "run-1", ()) is None


def test_the_fractions_are_respected_over_many_runs():
    counts = Counter(split_of(7, run, SPLIT) for run in RUNS)
    for name, fraction in SPLIT:
        assert abs(counts[name] / len(RUNS) - fraction) < 0.015, counts  # about 5 standard deviations
    assert set(counts) == {"train", "val", "test"}


def test_order_given_decides_the_buckets():
    """The same fractions given in another order put runs in other splits: the order is part of the
    selection, as its JSON keeps it."""
    one = [split_of(3, run, (("a", 0.5), ("b", 0.5))) for run in RUNS[:200]]
    swapped = [split_of(3, run, (("b", 0.5), ("a", 0.5))) for run in RUNS[:200]]
    assert one == [{"a": "b", "b": "a"}[s] for s in swapped]  # type: ignore[index]
