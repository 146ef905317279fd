"""Choosing candidate chunks from index rows alone: what each mode keeps, and latest-at fill from
per-component ranges (test_query.py checks the same against `rerun server` and Rerun's reader)."""

from __future__ import annotations

from services.redap.candidates import (
    EXACT_SAMPLES,
    Contents,
    Everything,
    Samples,
    StaticOnly,
    TimeRange,
    normal_entity_path,
    select,
)
from services.sealed.index import CHUNK, ComponentRange, IndexRow, TimelineRange

POSITIONS, COLORS = "Points3D:positions", "Points3D:colors"


def row(
    name: str,
    entity: str = "/robot",
    span: tuple[int, int] | None = None,
    components: dict[str, tuple[int, int]] | None = None,
    *,
    static: bool = False,
    known: bool = True,
) -> IndexRow:
    """A chunk on `frame` over `span`, its components' ranges (all of the span by default)."""
    comps = components or {POSITIONS: span or (0, 0)}
    ranges = tuple(ComponentRange(c, "frame", lo, hi, 1) for c, (lo, hi) in comps.items()) if span else ()
    return IndexRow(
        CHUNK,
        "recording",
        0,
        100,
        name.encode().ljust(16, b"."),
        entity,
        static,
        1,
        (TimelineRange("frame", "sequence", *span),) if span else (),
        tuple(sorted(comps)),
        ranges if known else None,
    )


def names(rows: list[IndexRow]) -> list[str]:
    return [(r.chunk_id or b"").rstrip(b".").decode() for r in rows]


ROWS = [
    row("static", "/map", static=True),
    row("a", span=(0, 9)),
    row("b", span=(10, 19)),
    row("c", span=(20, 29)),
    row("other", "/other", span=(5, 25)),
    row("sim-only", "/sim", span=None),  # no `frame`: on another timeline
]


def test_static_only_keeps_the_static_chunks():
    assert names(select(ROWS, Contents(), StaticOnly())) == ["static"]


def test_a_range_keeps_static_chunks_and_those_overlapping_it_bounds_included():
    assert names(select(ROWS, Contents(), TimeRange("frame", 9, 10))) == ["static", "a", "b", "other"]
    assert names(select(ROWS, Contents(), TimeRange("frame", 26))) == ["static", "c"]
    assert names(select(ROWS, Contents(), TimeRange("frame", None, 5))) == ["static", "a", "other"]


def test_a_range_without_bounds_and_everything_keep_every_chunk_on_the_timeline_or_not():
    every = ["static", "a", "b", "c", "other", "sim-only"]
    assert names(select(ROWS, Contents(), TimeRange("frame"))) == every
    assert names(select(ROWS, Contents(), Everything())) == every


def test_contents_keep_the_entities_and_components_asked_for():
    robot = Contents({"/robot": None})
    assert names(select(ROWS, robot, TimeRange("frame"))) == ["a", "b", "c"]
    with_colors = [row("p", span=(0, 5)), row("pc", span=(0, 5), components={POSITIONS: (0, 5), COLORS: (2, 2)})]
    assert names(select(with_colors, Contents({"/robot": frozenset({COLORS})}), TimeRange("frame"))) == ["pc"]
    assert names(select(with_colors, Contents({"/robot": frozenset()}), TimeRange("frame"))) == []
    assert select(ROWS, Contents({}), TimeRange("frame")) == []


def test_entity_paths_are_named_with_or_without_their_slashes():
    assert normal_entity_path("world/points/") == normal_entity_path("/world/points") == "/world/points"
    assert names(select(ROWS, Contents({"/other": None}), Everything())) == ["other"]


def test_latest_at_fill_adds_the_chunk_with_each_component_s_newest_earlier_value():
    # `c` straddles 25: its rows from 20 on are newer than anything in `b`, which is not needed
    assert names(select(ROWS, Contents({"/robot": None}), TimeRange("frame", 25, 30, latest_at=True))) == ["c"]
    assert names(select(ROWS, Contents({"/robot": None}), TimeRange("frame", 20, 30, latest_at=True))) == ["b", "c"]
    # a sparse component: colors last logged in `a`, so `a` holds the newest colors before 25
    sparse = [
        row("a", span=(0, 9), components={POSITIONS: (0, 9), COLORS: (3, 3)}),
        row("b", span=(10, 19), components={POSITIONS: (10, 19)}),
        row("c", span=(20, 29), components={POSITIONS: (20, 29)}),
    ]
    assert names(select(sparse, Contents(), TimeRange("frame", 25, 30, latest_at=True))) == ["a", "c"]
    # asked for positions alone, colors' chunk is not needed
    positions = Contents({"/robot": frozenset({POSITIONS})})
    assert names(select(sparse, positions, TimeRange("frame", 25, 30, latest_at=True))) == ["c"]


def test_latest_at_fill_keeps_a_chunk_straddling_the_start_and_ties_on_the_newest_end():
    straddling = [
        row("before", span=(0, 8)),
        row("straddle", span=(5, 40), components={POSITIONS: (5, 40)}),
        row("tie-1", span=(1, 9)),
        row("tie-2", span=(2, 9)),
    ]
    # the straddling chunk may hold a row at 9 or later before 10: every chunk ending at 9 stays too
    kept = names(select(straddling, Contents(), TimeRange("frame", 10, latest_at=True)))
    assert kept == ["straddle", "tie-1", "tie-2"]


def test_latest_at_fill_without_per_component_ranges_keeps_every_earlier_chunk():
    older = [row("a", span=(0, 9), known=False), row("b", span=(10, 19), known=False), row("c", span=(30, 39))]
    assert names(select(older, Contents(), TimeRange("frame", 25, latest_at=True))) == ["a", "b", "c"]


def test_samples_keep_the_chunks_holding_each_time_and_with_fill_those_before():
    assert names(select(ROWS, Contents(), Samples("frame", (12,)))) == ["static", "b", "other"]
    filled = select(ROWS, Contents({"/robot": None}), Samples("frame", (12, 35), latest_at=True))
    assert names(filled) == ["b", "c"]  # `b` holds 12 (and a row before it), `c` the newest value before 35
    filled = select(ROWS, Contents({"/robot": None}), Samples("frame", (10, 35), latest_at=True))
    assert names(filled) == ["a", "b", "c"]  # before 10, only `a` has rows
    assert select(ROWS, Contents(), Samples("frame", ())) == []  # no times: nothing, not even static


def test_many_samples_keep_a_superset_of_what_each_needs():
    times = tuple(range(12, 12 + 2 * (EXACT_SAMPLES + 1), 2))
    few = {n for t in times for n in names(select(ROWS, Contents(), Samples("frame", (t,), latest_at=True)))}
    many = set(names(select(ROWS, Contents(), Samples("frame", times, latest_at=True))))
    assert few <= many
