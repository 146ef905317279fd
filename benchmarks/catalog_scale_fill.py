"""The fleet `benchmarks/catalog_scale.py` measures: a catalog filled with `runs` runs of 200 robots
over a year, every table a run has, generated with numpy (seeded) and loaded in bulk (Postgres
`COPY`, DuckDB from Arrow), into a schema the project's migrations made.

Run k (0 = the oldest) is robot k mod 200's; runs start evenly over the year up to now, last 5 to 60
minutes, and each robot works on one of four applications (its dataset). Where each run is follows
the retention policies (`policies()`: the service's defaults, 30 days warm and 365 cold, and 7 + 60
days for the `mapping` application, which gives the fleet its tombstones) as if the retention job
last ran an hour ago, so the plan has work to do: runs that crossed a boundary in that hour. Runs
that end less than 10 minutes ago are hot (live while their end is ahead). Every run has its
entities, two timelines, its rules evaluation and five metrics (as docs/corpus.md's rules file
makes); a fifth of the runs have 1 to 3 events, a quarter tags; sealed runs have their lifecycle row,
four objects while warm or cold, and retention's events. Beside them: robots, datasets, a month of
job runs, some pulls, and a dataset snapshot of 5,000 intervention windows.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from services.policies import Policies, Policy, PolicyOverride

ROBOTS = 200
DAYS = 365
CHUNK_RUNS = 100_000  # runs generated and loaded at a time
APPLICATIONS = ("warehouse-nav", "pick-place", "inspection", "mapping")
SITES = 10
RULES_VERSION = 3
PROMOTE_AFTER_S = 600
RETENTION_LAG_S = 3600  # the retention job last ran this long ago
PINNED = 0.003
WITH_EVENTS, WITH_TAGS, TWO_TAGS = 0.2, 0.25, 0.05
TAGS = ("night-shift", "dock-2", "rain", "demo", "calibration", "regression", "new-map", "firmware-2.4")
# (kind, severity, origin, share of events)
EVENT_KINDS = (
    ("intervention", "warn", "rule", 0.6),
    ("too_hot", "warn", "rule", 0.15),
    ("stuck", "error", "rule", 0.15),
    ("hard_brake", "error", "robot", 0.1),
)
METRICS = ("distance_m", "interventions", "intervention_s", "mean_temp", "sw_version")
OBJECTS = ("recording.rrd", "chunks.parquet", "run.json", "analytics/scalars/part.parquet")
SNAPSHOT, SNAPSHOT_EPISODES = "interventions", 5_000


def _entity(path: str, archetypes: list[str], components: list[str]) -> tuple[str, str, str]:
    quoted = ", ".join(f'"{name}"' for name in archetypes), ", ".join(f'"{name}"' for name in components)
    return path, f"[{quoted[0]}]", f"[{quoted[1]}]"


ENTITIES = (
    _entity("/__properties", ["rerun.archetypes.RecordingInfo"], ["RecordingInfo:name", "RecordingInfo:start_time"]),
    _entity("/__properties/fleet", [], ["robot_id", "site", "sw_version"]),
    _entity("/world/robot", ["rerun.archetypes.Transform3D"], ["Transform3D:translation"]),
    _entity("/sensors/ambient_temp", ["rerun.archetypes.Scalars"], ["Scalars:scalars"]),
    _entity("/autonomy/engaged", ["rerun.archetypes.Scalars"], ["Scalars:scalars"]),
    _entity("/logs", ["rerun.archetypes.TextLog"], ["TextLog:level", "TextLog:text"]),
    _entity("/camera/image", ["rerun.archetypes.EncodedImage"], ["EncodedImage:blob", "EncodedImage:media_type"]),
    _entity("/lidar/points", ["rerun.archetypes.Points3D"], ["Points3D:colors", "Points3D:positions"]),
)


def policies() -> Policies:
    override = PolicyOverride.model_validate(
        {"name": "mapping", "application": "mapping", "warm_days": 7, "cold_days": 60}
    )
    return Policies(Policy("default", 30.0, 365.0), (override,))


def robot_name(number: int) -> str:
    return f"robot-{number:03d}"


def _utc(ns: np.ndarray) -> pa.Array:
    return pa.array(ns // 1000, type=pa.timestamp("us", tz="UTC"))


@dataclass(frozen=True)
class Fleet:
    runs: int
    entities: int
    now: dt.datetime
    seed: int = 34

    @property
    def now_ns(self) -> int:
        return int(self.now.timestamp() * 1e9)

    @property
    def step_ns(self) -> int:
        return DAYS * 86_400 * 10**9 // self.runs


@dataclass
class Chunk:
    """Runs `lo` to `hi` - 1, each attribute an array over them."""

    lo: int
    ids: np.ndarray
    robot: np.ndarray
    start_ns: np.ndarray
    end_ns: np.ndarray
    app: np.ndarray
    live: np.ndarray
    hot: np.ndarray
    warm: np.ndarray
    cold: np.ndarray
    deleted: np.ndarray
    pinned: np.ndarray
    no_start: np.ndarray
    rng: np.random.Generator

    @property
    def sealed(self) -> np.ndarray:
        return ~self.hot

    @property
    def size(self) -> int:
        return len(self.ids)


def _run_ids(rng: np.random.Generator, count: int) -> np.ndarray:
    """Rerun recording ids (UUIDs), so their order is not the runs' order in time."""
    words = rng.integers(0, 2**63, size=(count, 2), dtype=np.int64)
    hexes = [f"{a:016x}{b:016x}" for a, b in words.tolist()]
    return np.array([f"{h[:8]}-{h[8:12]}-{h[12:16]}-{h[16:20]}-{h[20:]}" for h in hexes], dtype=object)


def make_chunk(fleet: Fleet, lo: int, hi: int) -> Chunk:
    rng = np.random.default_rng([fleet.seed, lo])
    index = np.arange(lo, hi, dtype=np.int64)
    robot = index % ROBOTS
    start = fleet.now_ns - DAYS * 86_400 * 10**9 + index * fleet.step_ns + rng.integers(0, fleet.step_ns, hi - lo)
    end = start + rng.integers(300, 3600, hi - lo) * 10**9
    app = robot % len(APPLICATIONS)
    age_s = (fleet.now_ns - end) / 1e9
    live = age_s < 0
    hot = age_s < PROMOTE_AFTER_S
    pinned = ~hot & (rng.random(hi - lo) < PINNED)
    mapping = app == APPLICATIONS.index("mapping")
    warm_days = np.where(mapping, 7.0, 30.0)
    delete_days = warm_days + np.where(mapping, 60.0, 365.0)
    deleted = ~hot & ~pinned & (age_s >= delete_days * 86_400 + RETENTION_LAG_S)
    cold = ~hot & ~deleted & (age_s >= warm_days * 86_400 + RETENTION_LAG_S)
    warm = ~hot & ~deleted & ~cold
    no_start = rng.random(hi - lo) < 0.005  # runs whose start the catalog never learnt: sorted by created_at
    return Chunk(
        lo, _run_ids(rng, hi - lo), robot, start, end, app, live, hot, warm, cold, deleted, pinned, no_start, rng
    )


def tier_of(chunk: Chunk) -> np.ndarray:
    tiers = np.full(chunk.size, "warm", dtype=object)
    tiers[chunk.hot], tiers[chunk.cold], tiers[chunk.deleted] = "hot", "cold", "deleted"
    return tiers


def _robots(chunk: Chunk) -> np.ndarray:
    names: np.ndarray = np.array([robot_name(r) for r in range(ROBOTS)], dtype=object)
    return names[chunk.robot]  # type: ignore[no-any-return]


def _promoted_ns(chunk: Chunk) -> np.ndarray:
    return chunk.end_ns + (PROMOTE_AFTER_S + 30) * 10**9


def runs_table(fleet: Fleet, chunk: Chunk) -> pa.Table:
    seconds = (chunk.end_ns - chunk.start_ns) // 10**9
    robots, apps = _robots(chunk), np.array(APPLICATIONS, dtype=object)[chunk.app]
    month = (np.arange(chunk.lo, chunk.lo + chunk.size) * 12) // fleet.runs
    properties = [
        f'{{"fleet": {{"robot_id": "{robot}", "site": "site-{r % SITES}", "sw_version": "2.{m}.0"}}, '
        f'"recording": {{"RecordingInfo:name": "{app}", "RecordingInfo:start_time": {start}}}}}'
        for robot, r, m, app, start in zip(
            robots, chunk.robot.tolist(), month.tolist(), apps, chunk.start_ns.tolist(), strict=True
        )
    ]
    created = chunk.start_ns + 10**9
    started = pa.array(np.where(chunk.no_start, 0, chunk.start_ns) // 1000, type=pa.timestamp("us", tz="UTC"))
    started = pc.if_else(pa.array(chunk.no_start), pa.nulls(chunk.size, started.type), started)
    last_data = np.where(chunk.live, fleet.now_ns - 10**9, chunk.end_ns)
    ended = pc.if_else(pa.array(chunk.live), pa.nulls(chunk.size, pa.timestamp("us", tz="UTC")), _utc(chunk.end_ns))
    chunks = seconds * 60
    sizes = (seconds * 2_000_000 * chunk.rng.uniform(0.5, 1.5, chunk.size)).astype(np.int64)
    return pa.table(
        {
            "id": chunk.ids,
            "robot_id": robots,
            "application_id": apps,
            "date": pa.array(chunk.start_ns // 86_400_000_000_000, type=pa.int32()).cast(pa.date32()),
            "status": np.where(chunk.live, "live", "closed").astype(object),
            "tier": tier_of(chunk),
            "started_at": started,
            "ended_at": ended,
            "last_data_at": _utc(last_data),
            "sdk_version": np.full(chunk.size, "0.41.0", dtype=object),
            "chunks": chunks,
            "rows": chunks * 4,
            "bytes": sizes,
            "properties": properties,
            "pinned": chunk.pinned,
            "pinned_by": pc.if_else(pa.array(chunk.pinned), "alice", pa.scalar(None, pa.string())),
            "created_at": _utc(created),
            "updated_at": _utc(np.where(chunk.hot, last_data, _promoted_ns(chunk))),
        }
    )


def _prefixes(chunk: Chunk, rows: np.ndarray) -> list[str]:
    days = (chunk.start_ns[rows] // 86_400_000_000_000).tolist()
    robots = _robots(chunk)[rows]
    return [
        f"{robot}/{dt.date.fromordinal(dt.date(1970, 1, 1).toordinal() + day).isoformat()}/{run}"
        for robot, day, run in zip(robots, days, chunk.ids[rows], strict=True)
    ]


def lifecycle_table(chunk: Chunk) -> pa.Table:
    rows = np.flatnonzero(chunk.sealed)
    archived = chunk.cold[rows] | chunk.deleted[rows]
    mapping = chunk.app[rows] == APPLICATIONS.index("mapping")
    end = chunk.end_ns[rows]
    archived_ns = end + (np.where(mapping, 7, 30) * 86_400 + chunk.rng.integers(0, RETENTION_LAG_S, len(rows))) * 10**9
    deleted_ns = end + (np.where(mapping, 67, 395) * 86_400 + RETENTION_LAG_S // 2) * 10**9
    none_ts = pa.nulls(len(rows), pa.timestamp("us", tz="UTC"))
    none_text = pa.nulls(len(rows), pa.string())
    restored = chunk.cold[rows] & (np.arange(len(rows)) % 5000 == 7)
    restoring = chunk.cold[rows] & (np.arange(len(rows)) % 5000 == 11)
    restore_state = np.full(len(rows), None, dtype=object)
    restore_state[restored], restore_state[restoring] = "restored", "restoring"
    dead = pa.array(chunk.deleted[rows])
    return pa.table(
        {
            "run_id": chunk.ids[rows],
            "prefix": _prefixes(chunk, rows),
            "promoted_at": _utc(_promoted_ns(chunk)[rows]),
            "archived_at": pc.if_else(pa.array(archived), _utc(archived_ns), none_ts),
            "archive_mode": pc.if_else(pa.array(archived), "store", none_text),
            "restore_state": pa.array(restore_state, type=pa.string()),
            "restore_requested_at": pc.if_else(pa.array(restored | restoring), _utc(archived_ns), none_ts),
            "restore_until": pc.if_else(pa.array(restored), _utc(archived_ns + 7 * 86_400 * 10**9), none_ts),
            "deleted_at": pc.if_else(dead, _utc(deleted_ns), none_ts),
            "deleted_by": pc.if_else(dead, "retention", none_text),
            "deleted_policy": pc.if_else(dead, pa.array(np.where(mapping, "mapping", "default")), none_text),
        }
    )


def objects_table(chunk: Chunk, runs: pa.Table) -> pa.Table:
    rows = np.flatnonzero(chunk.warm | chunk.cold)
    prefixes = _prefixes(chunk, rows)
    count = len(OBJECTS)
    sizes = np.stack(
        [
            runs.column("bytes").to_numpy()[rows],
            runs.column("chunks").to_numpy()[rows] * 150,
            np.full(len(rows), 2_000),
            runs.column("rows").to_numpy()[rows] * 12,
        ],
        axis=1,
    ).reshape(-1)
    ids = chunk.ids[rows]
    return pa.table(
        {
            "run_id": np.repeat(ids, count),
            "name": np.tile(np.array(OBJECTS, dtype=object), len(rows)),
            "key": [f"{prefix}/{name}" for prefix in prefixes for name in OBJECTS],
            "tier": np.repeat(np.where(chunk.cold[rows], "cold", "warm").astype(object), count),
            "size": sizes,
            "sha256": np.repeat(np.array([run.replace("-", "") * 2 for run in ids], dtype=object), count),
        }
    )


def entities_table(fleet: Fleet, chunk: Chunk) -> pa.Table:
    extra = [_entity(f"/joints/j{k}", ["rerun.archetypes.Scalars"], ["Scalars:scalars"]) for k in range(64)]
    listed = (list(ENTITIES) + extra)[: fleet.entities]
    seconds = (chunk.end_ns - chunk.start_ns) // 10**9
    count = len(listed)
    chunks = np.repeat(seconds * 60 // count, count)
    return pa.table(
        {
            "run_id": np.repeat(chunk.ids, count),
            "path": np.tile(np.array([e[0] for e in listed], dtype=object), chunk.size),
            "chunks": chunks,
            "static_chunks": np.tile(
                np.array([1 if e[0].startswith("/__properties") else 0 for e in listed]), chunk.size
            ),
            "rows": chunks * 4,
            "bytes": chunks * 30_000,
            "archetypes": np.tile(np.array([e[1] for e in listed], dtype=object), chunk.size),
            "components": np.tile(np.array([e[2] for e in listed], dtype=object), chunk.size),
        }
    )


def timelines_table(chunk: Chunk) -> pa.Table:
    frames = (chunk.end_ns - chunk.start_ns) // 10**8
    return pa.table(
        {
            "run_id": np.repeat(chunk.ids, 2),
            "name": np.tile(np.array(["frame", "log_time"], dtype=object), chunk.size),
            "type": np.tile(np.array(["sequence", "timestamp"], dtype=object), chunk.size),
            "min": np.stack([np.zeros(chunk.size, dtype=np.int64), chunk.start_ns], axis=1).reshape(-1),
            "max": np.stack([frames, chunk.end_ns], axis=1).reshape(-1),
        }
    )


@dataclass
class Events:
    """A chunk's events, and how many interventions (and seconds of them) each run has."""

    table: pa.Table
    interventions: np.ndarray
    intervention_s: np.ndarray


def events_of(chunk: Chunk) -> Events:
    rng = chunk.rng
    runs = np.flatnonzero(rng.random(chunk.size) < WITH_EVENTS)
    per_run = rng.integers(1, 4, len(runs))
    owner = np.repeat(runs, per_run)
    kinds = rng.choice(len(EVENT_KINDS), size=len(owner), p=[share for *_, share in EVENT_KINDS])
    span = chunk.end_ns[owner] - chunk.start_ns[owner]
    start = chunk.start_ns[owner] + (rng.random(len(owner)) * span * 0.9).astype(np.int64)
    length_ns = rng.integers(1, 10, len(owner)) * 10**9
    names = np.array([k[0] for k in EVENT_KINDS], dtype=object)[kinds]
    origins = np.array([k[2] for k in EVENT_KINDS], dtype=object)[kinds]
    words = rng.integers(0, 2**63, len(owner), dtype=np.int64).tolist()
    intervention = kinds == 0
    table = pa.table(
        {
            "id": [f"ev-{w:016x}" for w in words],
            "run_id": chunk.ids[owner],
            "robot_id": _robots(chunk)[owner],
            "kind": names,
            "severity": np.array([k[1] for k in EVENT_KINDS], dtype=object)[kinds],
            "timeline": np.full(len(owner), "log_time", dtype=object),
            "timeline_type": np.full(len(owner), "timestamp", dtype=object),
            "range_start": start,
            "range_end": start + length_ns,
            "origin": np.where(origins == "robot", "robot", "rule").astype(object),
            "source": [
                f"rule {n}@{RULES_VERSION}" if o == "rule" else "robot" for n, o in zip(names, origins, strict=True)
            ],
            "rules_version": np.full(len(owner), RULES_VERSION),
            "label": np.full(len(owner), "", dtype=object),
            "note": np.full(len(owner), "", dtype=object),
            "created_at": _utc(_promoted_ns(chunk)[owner]),
        }
    )
    counts = np.bincount(owner[intervention], minlength=chunk.size)
    seconds = np.bincount(owner[intervention], weights=length_ns[intervention] / 1e9, minlength=chunk.size)
    return Events(table, counts, seconds)


def evaluations_table(chunk: Chunk) -> pa.Table:
    return pa.table(
        {
            "run_id": chunk.ids,
            "rules_version": np.full(chunk.size, RULES_VERSION),
            "state": np.where(chunk.hot, "live", "final").astype(object),
            "events_capped": np.zeros(chunk.size, dtype=bool),
            "note": pa.nulls(chunk.size, pa.string()),
            "evaluated_at": _utc(np.where(chunk.hot, chunk.end_ns, _promoted_ns(chunk))),
        }
    )


def metrics_table(fleet: Fleet, chunk: Chunk, events: Events) -> pa.Table:
    seconds = (chunk.end_ns - chunk.start_ns) / 1e9
    numbers = np.stack(
        [
            seconds * chunk.rng.uniform(0.2, 1.5, chunk.size),
            events.interventions.astype(np.float64),
            events.intervention_s,
            chunk.rng.uniform(18.0, 45.0, chunk.size),
            np.full(chunk.size, np.nan),
        ],
        axis=1,
    ).reshape(-1)
    month = (np.arange(chunk.lo, chunk.lo + chunk.size) * 12) // fleet.runs
    texts = np.full((chunk.size, len(METRICS)), None, dtype=object)
    texts[:, -1] = [f"2.{m}.0" for m in month.tolist()]
    when = np.where(chunk.hot, chunk.end_ns, _promoted_ns(chunk))
    return pa.table(
        {
            "run_id": np.repeat(chunk.ids, len(METRICS)),
            "name": np.tile(np.array(METRICS, dtype=object), chunk.size),
            "robot_id": np.repeat(_robots(chunk), len(METRICS)),
            "value": pa.array(numbers, from_pandas=True),  # NaN: no number (the text metric)
            "text_value": pa.array(texts.reshape(-1), type=pa.string()),
            "rules_version": np.full(chunk.size * len(METRICS), RULES_VERSION),
            "computed_at": _utc(np.repeat(when, len(METRICS))),
        }
    )


def tags_table(chunk: Chunk) -> pa.Table:
    rng = chunk.rng
    tagged = np.flatnonzero(rng.random(chunk.size) < WITH_TAGS)
    first = rng.integers(0, len(TAGS), len(tagged))
    second = tagged[rng.random(len(tagged)) < TWO_TAGS / WITH_TAGS]
    second_tag = (first[np.searchsorted(tagged, second)] + 1) % len(TAGS)
    runs = np.concatenate([tagged, second])
    tags = np.array(TAGS, dtype=object)[np.concatenate([first, second_tag])]
    return pa.table(
        {
            "run_id": chunk.ids[runs],
            "tag": tags,
            "added_by": np.where(rng.random(len(runs)) < 0.5, "robot", "alice").astype(object),
            "added_at": _utc(chunk.end_ns[runs]),
        }
    )


def retention_events_table(chunk: Chunk) -> pa.Table:
    promoted = np.flatnonzero(chunk.sealed)
    archived = np.flatnonzero(chunk.cold | chunk.deleted)
    deleted = np.flatnonzero(chunk.deleted)
    runs = np.concatenate([promoted, archived, deleted])
    actions = np.repeat(
        np.array(["promote", "archive", "delete"], dtype=object), [len(promoted), len(archived), len(deleted)]
    )
    mapping = chunk.app[runs] == APPLICATIONS.index("mapping")
    archive_s, delete_s = np.where(mapping, 7, 30) * 86_400 + 60, np.where(mapping, 67, 395) * 86_400 + 1800
    offset = np.select([actions == "promote", actions == "archive"], [PROMOTE_AFTER_S + 30, archive_s], delete_s)
    words = chunk.rng.integers(0, 2**63, size=(len(runs), 2), dtype=np.int64).tolist()
    return pa.table(
        {
            "id": [f"{a:016x}{b:016x}" for a, b in words],
            "run_id": chunk.ids[runs],
            "action": actions,
            "occurred_at": _utc(chunk.end_ns[runs] + offset * 10**9),
            "actor": np.full(len(runs), "retention", dtype=object),
            "policy": pc.if_else(pa.array(actions == "delete"), "default", pa.scalar(None, pa.string())),
            "detail": np.where(actions == "delete", "4 objects removed", "").astype(object),
        }
    )


def chunk_tables(fleet: Fleet, chunk: Chunk) -> Iterator[tuple[str, pa.Table]]:
    """Every table's rows for the chunk's runs, in the order they are loaded."""
    runs = runs_table(fleet, chunk)
    yield "runs", runs
    yield "run_lifecycle", lifecycle_table(chunk)
    yield "run_objects", objects_table(chunk, runs)
    yield "run_entities", entities_table(fleet, chunk)
    yield "run_timelines", timelines_table(chunk)
    events = events_of(chunk)
    yield "events", events.table
    yield "run_evaluations", evaluations_table(chunk)
    yield "run_metrics", metrics_table(fleet, chunk, events)
    yield "run_tags", tags_table(chunk)
    yield "retention_events", retention_events_table(chunk)
