"""Analytics tables extracted at promotion: runs logged with the real SDK (scalars, text logs,
transforms given as translation + quaternion, as axis + angle, as a 3x3 matrix, points, static
data) are uploaded into a node and promoted; the warm store then holds Parquet tables `scalars`,
`text_logs`, `transforms` under `analytics/TABLE/robot_id=R/date=D/RUN.parquet`, readable as they
are by pyarrow and DuckDB, holding exactly what the SDK logged. A hot run's tables are written on
demand (POST /v1/runs/RUN/analytics); late data is re-extracted with the rest; deleting a run
deletes its rows."""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import duckdb
import pyarrow as pa
import pyarrow.dataset as pads
import pyarrow.parquet as pq
import pytest

from catalog import queries
from catalog.db import session_scope
from services.analytics.extract import TABLES
from services.retention.service import delete_run
from services.sealed.tiers import Tiers, parse_run_json
from services.sealed.write import RUN_JSON
from services.storage.objectstore import open_store
from tests.services.analytics.conftest import (
    DAY_NS,
    HOUR_NS,
    START_2026_03_01_NS,
    api,
    log_with_sdk,
    promote_all,
    sql_rows,
    upload_all,
)
from tests.services.retention.conftest import NodeFactory, listing

pytestmark = pytest.mark.sdk

RUN, ROBOT, DATE = "telemetry-run", "robot-7", "2026-03-01"
OTHER, OTHER_ROBOT, OTHER_DATE = "other-run", "robot-8", "2026-03-02"
CLASH = "clash-run"
FRAMES, LATE_FRAMES, JOINTS = 6, 3, 4
LEVELS = ("INFO", "WARN", "ERROR")

SCRIPT = """
FRAMES, LATE_FRAMES, JOINTS, LEVELS = {frames}, {late_frames}, {joints}, {levels!r}
rec = recording(FOLDER + "/run.rrd", {run!r}, {robot!r}, {start})
rec.log("/static/notes", rr.TextLog("static note", level="INFO"), static=True)
rec.log("/static/level", rr.Scalars(1.0), static=True)
lo = time.time_ns()
for i in range(FRAMES):
    rec.set_time("frame", sequence=i)
    rec.set_time("sim_time", duration=i * 0.5)
    rec.log("/battery", rr.Scalars(100.0 - 1.5 * i))
    rec.log("/joints/torque", rr.Scalars([10.0 * j + i for j in range(JOINTS)]))
    rec.log("/logs", rr.TextLog(f"step {{i}}", level=LEVELS[i % 3]))
    rec.log("/logs/plain", rr.TextLog(f"plain {{i}}"))
    half = 0.05 * i
    rec.log("/robot/base", rr.Transform3D(translation=[i, 2 * i, 0.5],
                                         quaternion=rr.Quaternion(xyzw=[0, 0, math.sin(half), math.cos(half)])))
    rec.log("/robot/arm", rr.Transform3D(rotation_axis_angle=rr.RotationAxisAngle(axis=[0, 0, 2], radians=0.25 * i)))
    rec.log("/robot/lift", rr.Transform3D(translation=[0, 0, 0.25 * i]))
    rec.log("/robot/camera", rr.Transform3D(mat3x3=[[0, -1, 0], [1, 0, 0], [0, 0, 1]]))
    rec.log("/world/points", rr.Points3D(np.full((5, 3), i, dtype=np.float32)))
hi = time.time_ns()
finish(rec)
late = recording(FOLDER + "/late.rrd", {run!r}, {robot!r}, {start})
for i in range(FRAMES, FRAMES + LATE_FRAMES):
    late.set_time("frame", sequence=i)
    late.log("/battery", rr.Scalars(100.0 - 1.5 * i))
finish(late)
other = recording(FOLDER + "/other.rrd", {other!r}, {other_robot!r}, {start} + {day})
for i in range(3):
    other.set_time("frame", sequence=i)
    other.log("/battery", rr.Scalars(50.0 - i))
finish(other)
clash = recording(FOLDER + "/clash.rrd", {clash!r}, {robot!r}, {start})
for i in range(3):
    clash.set_time("date", sequence=100 + i)
    clash.set_time("value", sequence=200 + i)
    clash.log("/battery", rr.Scalars(70.0 + i))
finish(clash)
print(json.dumps({{"log_time": [lo, hi]}}))
"""


@dataclass(frozen=True)
class SdkRuns:
    run: Path  # the telemetry run
    late: Path  # later chunks of the same run
    other: Path  # another robot, another day
    clash: Path  # timelines named like columns: "date", "value"
    log_time: tuple[int, int]  # wall clock around the telemetry run's logging calls


@pytest.fixture(scope="module")
def sdk_runs(tmp_path_factory: pytest.TempPathFactory) -> SdkRuns:
    folder = tmp_path_factory.mktemp("analytics-extract")
    script = f"FOLDER = {str(folder)!r}\n" + SCRIPT.format(
        frames=FRAMES,
        late_frames=LATE_FRAMES,
        joints=JOINTS,
        levels=LEVELS,
        run=RUN,
        robot=ROBOT,
        start=START_2026_03_01_NS + 10 * HOUR_NS,
        other=OTHER,
        other_robot=OTHER_ROBOT,
        day=DAY_NS,
        clash=CLASH,
    )
    truth = log_with_sdk(script, flush_rows=2)  # the SDK's batcher: several chunks per entity
    return SdkRuns(
        folder / "run.rrd", folder / "late.rrd", folder / "other.rrd", folder / "clash.rrd", tuple(truth["log_time"])
    )


def local_tiers(tmp_path: Path) -> Tiers:
    return Tiers(open_store((tmp_path / "warm").as_uri()), open_store((tmp_path / "cold").as_uri()))


def key(table: str, robot: str = ROBOT, date: str = DATE, run: str = RUN) -> str:
    return f"analytics/{table}/robot_id={robot}/date={date}/{run}.parquet"


def analytics_keys(tiers: Tiers) -> list[str]:
    return sorted(k for k in listing(tiers.warm) if k.startswith("analytics/"))


def rows_of(table: pa.Table) -> list[dict[str, Any]]:
    """Rows as dicts, timestamps and durations as integer nanoseconds."""
    for i, fld in enumerate(table.schema):
        if pa.types.is_timestamp(fld.type) or pa.types.is_duration(fld.type):
            table = table.set_column(i, fld.name, table.column(i).cast(pa.int64()))
    rows: list[dict[str, Any]] = table.to_pylist()
    return rows


# --- the files ----------------------------------------------------------------------------------


def test_promotion_writes_one_partitioned_parquet_file_per_table(
    tiers: Tiers, make_node: NodeFactory, sdk_runs: SdkRuns
):
    node = make_node(tiers)
    upload_all(node, [sdk_runs.run, sdk_runs.other])
    assert sorted(promote_all(node)) == sorted([RUN, OTHER])
    assert analytics_keys(tiers) == sorted([key(t) for t in TABLES] + [key("scalars", OTHER_ROBOT, OTHER_DATE, OTHER)])
    with session_scope(node.catalog) as session:
        objects = {name: (o.key, o.tier, o.size, o.sha256) for name, o in queries.run_objects(session, RUN).items()}
        life = queries.lifecycle(session, RUN)
        assert life is not None
        prefix = life.prefix
    sealed = parse_run_json(tiers.warm.get_range(f"{prefix}/{RUN_JSON}"))
    in_run_json = {o.name: o.key for o in sealed.objects}
    expected_columns = {
        "scalars": {"run_id", "entity", "component", "instance", "value"},
        "text_logs": {"run_id", "entity", "level", "text"},
        "transforms": {"run_id", "entity", "tx", "ty", "tz", "qx", "qy", "qz", "qw"},
    }
    for table in TABLES:
        data = tiers.warm.get_range(key(table))
        assert objects[f"analytics/{table}"] == (key(table), "warm", len(data), hashlib.sha256(data).hexdigest())
        assert in_run_json[f"analytics/{table}"] == key(table)
        schema = pq.read_schema(pa.BufferReader(data))
        # robot and date are the Hive partition, not columns of the file
        assert set(schema.names) == expected_columns[table] | {"frame", "sim_time", "log_time"}, table
        assert schema.field("log_time").type == pa.timestamp("ns") and schema.field("run_id").type == pa.string()
    scalars = pq.read_schema(pa.BufferReader(tiers.warm.get_range(key("scalars"))))
    assert scalars.field("instance").type == pa.int32() and scalars.field("value").type == pa.float64()


def test_files_read_as_they_are_with_hive_partitioning(tmp_path: Path, make_node: NodeFactory, sdk_runs: SdkRuns):
    tiers = local_tiers(tmp_path)
    node = make_node(tiers)
    upload_all(node, [sdk_runs.run, sdk_runs.other])
    promote_all(node)
    folder = tmp_path / "warm" / "analytics" / "scalars"
    table = pads.dataset(folder, format="parquet", partitioning="hive").to_table()
    identity = table.select(["robot_id", "date", "run_id"]).to_pylist()
    seen = {(r["robot_id"], str(r["date"]), r["run_id"]) for r in identity}
    assert seen == {(ROBOT, DATE, RUN), (OTHER_ROBOT, OTHER_DATE, OTHER)}
    assert table.num_rows == FRAMES + FRAMES * JOINTS + 3
    found = duckdb.sql(
        f"SELECT robot_id, date::VARCHAR AS date, count(*) AS n FROM read_parquet("
        f"'{folder}/*/*/*.parquet', hive_partitioning = true) GROUP BY ALL ORDER BY ALL"
    ).fetchall()
    assert found == [(ROBOT, DATE, FRAMES + FRAMES * JOINTS), (OTHER_ROBOT, OTHER_DATE, 3)]
    for name, rows in (("text_logs", 2 * FRAMES), ("transforms", 3 * FRAMES)):
        assert pads.dataset(folder.parent / name, format="parquet", partitioning="hive").count_rows() == rows


# --- what is in them ----------------------------------------------------------------------------


def test_values_are_what_the_sdk_logged(tmp_path: Path, make_node: NodeFactory, sdk_runs: SdkRuns):
    tiers = local_tiers(tmp_path)
    node = make_node(tiers)
    upload_all(node, [sdk_runs.run])
    promote_all(node)
    read = {t: rows_of(pq.read_table(pa.BufferReader(tiers.warm.get_range(key(t))))) for t in TABLES}
    lo, hi = sdk_runs.log_time

    scalars = read["scalars"]
    assert {(r["entity"], r["frame"], r["instance"]): r["value"] for r in scalars} == {
        **{("/battery", i, 0): 100.0 - 1.5 * i for i in range(FRAMES)},
        **{("/joints/torque", i, j): 10.0 * j + i for i in range(FRAMES) for j in range(JOINTS)},
    }  # static scalars are left out
    assert len(scalars) == FRAMES + FRAMES * JOINTS
    assert {r["component"] for r in scalars} == {"Scalars:scalars"} and {r["run_id"] for r in scalars} == {RUN}
    assert all(r["sim_time"] == r["frame"] * 500_000_000 for r in scalars)
    for table in TABLES:
        assert all(lo <= r["log_time"] <= hi for r in read[table]), table
    battery = sorted((r["frame"], r["log_time"]) for r in scalars if r["entity"] == "/battery")
    assert [t for _, t in battery] == sorted(t for _, t in battery)  # logged in frame order
    torque_times: dict[int, set[int]] = {}
    for r in scalars:
        if r["entity"] == "/joints/torque":
            torque_times.setdefault(r["frame"], set()).add(r["log_time"])
    assert all(len(times) == 1 for times in torque_times.values())  # one logged list, one time

    assert {(r["entity"], r["frame"]): (r["level"], r["text"]) for r in read["text_logs"]} == {
        **{("/logs", i): (LEVELS[i % 3], f"step {i}") for i in range(FRAMES)},
        **{("/logs/plain", i): (None, f"plain {i}") for i in range(FRAMES)},
    }  # the static text log is left out

    transforms = {(r["entity"], r["frame"]): r for r in read["transforms"]}
    assert {e for e, _ in transforms} == {"/robot/base", "/robot/arm", "/robot/lift"}  # no 3x3 matrix, no points
    for i in range(FRAMES):
        base, arm, lift = (transforms[(e, i)] for e in ("/robot/base", "/robot/arm", "/robot/lift"))
        assert (base["tx"], base["ty"], base["tz"]) == (i, 2 * i, 0.5)
        assert quaternion(base) == pytest.approx((0, 0, math.sin(0.05 * i), math.cos(0.05 * i)), abs=1e-6)
        # axis (0, 0, 2), angle 0.25 i -> the unit quaternion (0, 0, sin(0.125 i), cos(0.125 i))
        assert (arm["tx"], arm["ty"], arm["tz"]) == (None, None, None)
        assert quaternion(arm) == pytest.approx((0, 0, math.sin(0.125 * i), math.cos(0.125 * i)), abs=1e-6)
        assert (lift["tx"], lift["ty"], lift["tz"]) == (0, 0, 0.25 * i) and quaternion(lift) == (None,) * 4
    entities = {r["entity"] for t in TABLES for r in read[t]}
    assert not entities & {"/world/points", "/robot/camera", "/static/notes", "/static/level"}


def quaternion(row: dict[str, Any]) -> tuple[Any, ...]:
    return row["qx"], row["qy"], row["qz"], row["qw"]


def test_timelines_named_like_columns_are_renamed(tmp_path: Path, make_node: NodeFactory, sdk_runs: SdkRuns):
    """docs/analytics.md: a timeline is `timeline_NAME` if its name is one of the table's columns
    (robot_id and date included: they are the Hive partition, and must stay readable as such)."""
    tiers = local_tiers(tmp_path)
    node = make_node(tiers)
    upload_all(node, [sdk_runs.clash])
    promote_all(node)
    schema = pq.read_schema(pa.BufferReader(tiers.warm.get_range(key("scalars", run=CLASH))))
    assert "timeline_value" in schema.names and "value" in schema.names
    assert schema.field("value").type == pa.float64()
    assert "timeline_date" in schema.names and "date" not in schema.names, schema.names
    table = pads.dataset(tmp_path / "warm" / "analytics" / "scalars", format="parquet", partitioning="hive").to_table()
    assert sorted(zip(table["timeline_date"].to_pylist(), table["value"].to_pylist(), strict=True)) == [
        (100, 70.0),
        (101, 71.0),
        (102, 72.0),
    ]


# --- when they are written and removed ---------------------------------------------------------


def test_hot_run_on_demand_then_rewritten_at_promotion(tmp_path: Path, make_node: NodeFactory, sdk_runs: SdkRuns):
    node = make_node(local_tiers(tmp_path))
    upload_all(node, [sdk_runs.run])
    client = api(node)
    counts = (
        "SELECT (SELECT count(*) FROM scalars) AS s, (SELECT count(*) FROM text_logs) AS t, "
        "(SELECT count(*) FROM transforms) AS x"
    )
    assert sql_rows(client, counts) == [{"s": 0, "t": 0, "x": 0}]  # nothing extracted yet: empty tables
    response = client.post(f"/v1/runs/{RUN}/analytics")
    assert response.status_code == 200, response.text
    body = response.json()
    assert body["run"] == RUN
    assert sorted((t["table"], t["key"]) for t in body["tables"]) == sorted((t, key(t)) for t in TABLES)
    assert all(t["bytes"] == node.tiers.warm.head(t["key"]).size for t in body["tables"])
    expected = [{"s": FRAMES + FRAMES * JOINTS, "t": 2 * FRAMES, "x": 3 * FRAMES}]
    assert sql_rows(client, counts) == expected
    assert sql_rows(client, "SELECT DISTINCT robot_id, date, run_id FROM text_logs") == [
        {"robot_id": ROBOT, "date": DATE, "run_id": RUN}
    ]
    missing = client.post("/v1/runs/no-such-run/analytics")
    assert missing.status_code == 404 and "no-such-run" in missing.json()["message"]

    promote_all(node)
    assert analytics_keys(node.tiers) == sorted(key(t) for t in TABLES)  # the same files, rewritten
    assert sql_rows(client, counts) == expected
    assert client.post(f"/v1/runs/{RUN}/analytics").status_code == 404  # sealed: no longer a hot run


def test_late_data_is_extracted_with_the_rest(tmp_path: Path, make_node: NodeFactory, sdk_runs: SdkRuns):
    node = make_node(local_tiers(tmp_path))
    upload_all(node, [sdk_runs.run])
    promote_all(node)
    upload_all(node, [sdk_runs.late])  # late data for a warm run: a hot addendum, sealed in at next promotion
    promote_all(node)
    assert analytics_keys(node.tiers) == sorted(key(t) for t in TABLES)
    battery = sql_rows(api(node), "SELECT frame, value FROM scalars WHERE entity = '/battery' ORDER BY frame")
    assert battery == [{"frame": i, "value": 100.0 - 1.5 * i} for i in range(FRAMES + LATE_FRAMES)]


def test_deleting_a_run_deletes_its_rows(tmp_path: Path, make_node: NodeFactory, sdk_runs: SdkRuns):
    node = make_node(local_tiers(tmp_path))
    upload_all(node, [sdk_runs.run, sdk_runs.other])
    promote_all(node)
    client = api(node)
    assert {r["run_id"] for r in sql_rows(client, "SELECT DISTINCT run_id FROM scalars")} == {RUN, OTHER}
    detail = delete_run(node.retention, RUN, "tester")
    assert detail.startswith("deleted")
    assert analytics_keys(node.tiers) == [key("scalars", OTHER_ROBOT, OTHER_DATE, OTHER)]
    assert sql_rows(client, "SELECT DISTINCT run_id FROM scalars") == [{"run_id": OTHER}]
    assert sql_rows(client, "SELECT count(*) AS n FROM text_logs") == [{"n": 0}]  # no file left: an empty table
    assert sql_rows(client, f"SELECT tier FROM runs WHERE id = '{RUN}'") == [{"tier": "deleted"}]


@pytest.fixture(scope="module")
def malformed_seed(tmp_path_factory: pytest.TempPathFactory) -> Any:
    from tests.services.rrd.malformed import Seed, record_seed

    return Seed.read(record_seed(tmp_path_factory.mktemp("seed") / "seed.rrd"))


@pytest.mark.sdk
@pytest.mark.parametrize(
    "variant", ["scalars_offsets_decreasing", "scalars_int32", "text_not_utf8", "translation_width_2"]
)
def test_an_invalid_chunk_is_skipped_not_read(variant: str, malformed_seed: Any) -> None:
    """A chunk stored before ingest refused such chunks: extraction validates it first and skips it
    (reading its values would go out of bounds or misread them); the other chunks are extracted."""
    from services.analytics.extract import Extractor
    from services.rrd.chunk import chunk_meta
    from services.rrd.decoder import decode_message
    from services.rrd.messages import ArrowMessage
    from tests.services.rrd.malformed import malformed_chunk

    seed = malformed_seed
    original, raw = malformed_chunk(seed, variant)
    chunks = [e for e in seed.events if isinstance(e, ArrowMessage)]
    bad = decode_message(2, raw, original.offset)
    assert isinstance(bad, ArrowMessage)
    damaged = [bad if e.offset == original.offset else e for e in chunks]

    def extract(messages: list[ArrowMessage]) -> dict[str, Any]:
        extractor = Extractor("r")
        for msg in messages:
            extractor.add(msg, chunk_meta(msg))
        return extractor.tables()

    intact_tables = extract(chunks)
    tables = extract(damaged)
    table = {"scalars": "scalars", "text": "text_logs", "translation": "transforms"}[variant.split("_")[0]]
    assert table not in tables
    assert set(tables) == set(intact_tables) - {table}
