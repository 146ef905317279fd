"""Disaster recovery: the catalog dropped, an empty one rebuilt from the stores' run.json +
chunks.parquet by `fleet catalog rebuild`, and the service answers as it did before."""

from __future__ import annotations

import datetime as dt
import json
import re
import subprocess
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import httpx
import pytest
import sqlalchemy as sa

from catalog import queries
from catalog.db import session_scope
from services.redap.pb import cloud_pb2
from services.redap.tuid import Tuid
from services.retention.rebuild import rebuild
from services.retention.service import PROMOTE, plan, run_plan
from services.sealed.tiers import Tiers, parse_run_json
from services.sealed.write import RUN_JSON
from tests.postgres import admin_engine, temporary_database
from tests.services.ingest.live_server import FLEET, LiveServer
from tests.services.redap.client import Redap
from tests.services.retention.conftest import Clock, Node, NodeFactory, log_run
from tests.services.rrd.recordings import Recording, rerun_rrd_ok

pytestmark = pytest.mark.sdk

# runs of these applications are archived to cold as soon as they are warm; the others stay warm
POLICIES = json.dumps(
    [
        {"name": "camera-short", "application": "fleet_camera", "warm_days": 0},
        {"name": "logs-short", "application": "fleet_logs", "warm_days": 0},
    ]
)
SCENES = ("points", "image", "scalars", "textlogs", "properties")
COLD = {"rec-image", "rec-textlogs"}
PINNED = {"rec-points", "rec-image"}  # one warm, one cold
# What a rebuild cannot bring back: the history (replaced by one "rebuild" event), when a run was
# archived (read from its cold object's time) and the rules' evaluation (`fleet rules backfill` makes
# it again from the data).
LOST = {"events", "lifecycle.archived_at", "evaluation"}


def fleet(server: LiveServer, *args: str) -> subprocess.CompletedProcess[str]:
    result = subprocess.run([FLEET, *args, "--api-url", server.url], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, f"fleet {' '.join(args)}: {result.stdout}{result.stderr}"
    return result


def get(server: LiveServer, path: str) -> Any:
    answer = httpx.get(f"{server.url}{path}", timeout=30)
    assert answer.status_code == 200, f"{path}: {answer.status_code} {answer.text}"
    return answer.json()


def answers(server: LiveServer, run_ids: list[str]) -> dict[str, Any]:
    """What clients see: the run lists (all tiers) and each run in full."""
    seen: dict[str, Any] = {
        f"/v1/runs{q}": get(server, f"/v1/runs{q}")
        for q in ("", "?tier=hot", "?tier=warm", "?tier=cold", "?sort=id&limit=2")
    }
    for run_id in run_ids:
        seen[f"/v1/runs/{run_id}"] = get(server, f"/v1/runs/{run_id}")
    return seen


def catalog_datasets(server: LiveServer) -> dict[str, str]:
    """The datasets the catalog server lists (FindEntries, as Rerun's clients ask): name -> entry id."""
    client = Redap(server.grpc_port)
    try:
        found = client.call(
            "FindEntries",
            cloud_pb2.FindEntriesRequest(filter=cloud_pb2.EntryFilter(entry_kinds=[cloud_pb2.ENTRY_KIND_DATASET])),
        )
    finally:
        client.close()
    return {e.name: str(Tuid.from_proto(e.id.id)) for e in found.entries}


def run_retention(server: LiveServer, *actions: str) -> dict[str, Any]:
    """`POST /v1/retention/run` (what `fleet retention run` sends); its last NDJSON line."""
    answer = httpx.post(f"{server.url}/v1/retention/run", params={"action": list(actions)}, timeout=120)
    assert answer.status_code == 200, answer.text
    end: dict[str, Any] = json.loads(answer.text.strip().splitlines()[-1])
    return end


def recordings_served(server: LiveServer, run_ids: list[str]) -> dict[str, tuple[int, bytes]]:
    out = {}
    for run_id in run_ids:
        answer = httpx.get(f"{server.url}/v1/runs/{run_id}/recording.rrd", timeout=60)
        out[run_id] = (answer.status_code, answer.content if answer.status_code == 200 else b"")
    return out


def differences(before: Any, after: Any, path: str = "") -> set[str]:
    """Dotted paths where two JSON answers differ."""
    if isinstance(before, dict) and isinstance(after, dict):
        return {
            d
            for key in before.keys() | after.keys()
            for d in differences(before.get(key), after.get(key), f"{path}.{key}" if path else key)
        }
    if isinstance(before, list) and isinstance(after, list) and len(before) == len(after) and path != "events":
        return {d for i, (b, a) in enumerate(zip(before, after, strict=True)) for d in differences(b, a, path)}
    return set() if before == after else {path}


class Catalog:
    """The service's catalog, which the test drops: the embedded DuckDB file, or a Postgres database."""

    def __init__(self, kind: str, data_dir: Path, stack: ExitStack) -> None:
        self.kind, self.data_dir = kind, data_dir
        self.url = stack.enter_context(temporary_database("fleet_rebuild")) if kind == "postgres" else ""
        self.create()

    def settings(self) -> dict[str, str]:
        return {"catalog_url": self.url} if self.url else {}

    def create(self) -> None:
        if self.url:  # a server catalog is made by `fleet db upgrade`; the embedded one by `fleet serve`
            done = subprocess.run(
                [FLEET, "db", "upgrade", "--catalog-url", self.url], capture_output=True, text=True, timeout=60
            )
            assert done.returncode == 0, done.stderr

    def drop(self) -> None:
        if not self.url:
            files = list(self.data_dir.glob("catalog.duckdb*"))
            assert self.data_dir / "catalog.duckdb" in files
            for file in files:
                file.unlink()
            return
        name = self.url.rsplit("/", 1)[1]
        admin = admin_engine()
        with admin.connect() as conn:
            conn.execute(sa.text(f'DROP DATABASE "{name}" WITH (FORCE)'))
            conn.execute(sa.text(f'CREATE DATABASE "{name}"'))
        admin.dispose()
        self.create()


@pytest.fixture(params=["duckdb", pytest.param("postgres", marks=pytest.mark.postgres)])
def catalog(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Catalog]:
    with ExitStack() as stack:
        yield Catalog(request.param, tmp_path / "data", stack)


def test_rebuilt_catalog_answers_as_before(
    catalog: Catalog, tmp_path: Path, recordings: dict[str, Recording], rerun_bin: str
):
    server = LiveServer(
        tmp_path / "data", scheduler="false", promote_after_s="0", retention_policies=POLICIES, **catalog.settings()
    )
    run_ids = sorted(recordings[s].recordings[0]["recording_id"] for s in SCENES)
    try:
        server.start()
        for scene in SCENES:
            assert httpx.post(f"{server.url}/v1/uploads", content=recordings[scene].data, timeout=60).status_code == 200
        assert run_retention(server) == {"event": "end", "done": len(SCENES), "failed": 0}  # promoted
        assert run_retention(server) == {"event": "end", "done": len(COLD), "failed": 0}  # archived
        for run_id in PINNED:
            assert httpx.post(f"{server.url}/v1/runs/{run_id}/pin", timeout=10).status_code == 200
        before = answers(server, run_ids)
        served_before = recordings_served(server, run_ids)
        datasets_before = catalog_datasets(server)
        server.stop()

        catalog.drop()
        server.start()
        assert get(server, "/v1/runs")["runs"] == []  # an empty catalog
        rebuilt = fleet(server, "catalog", "rebuild")
        assert rebuilt.stdout.strip() == f"{len(run_ids)} runs added, 0 already present, 0 skipped"
        after = answers(server, run_ids)
        served_after = recordings_served(server, run_ids)
        datasets_after = catalog_datasets(server)

        again = fleet(server, "catalog", "rebuild")  # repeatable: the catalog is left as it is
        assert again.stdout.strip() == f"0 runs added, {len(run_ids)} already present, 0 skipped"
        assert answers(server, run_ids) == after

        # the rebuilt catalog is one retention can work with: nothing due again, restores work
        assert get(server, "/v1/retention/plan") == {"actions": [], "upcoming": [], "kept": []}
        assert httpx.post(f"{server.url}/v1/runs/rec-image/restore", timeout=10).status_code == 202
        # the copy back from the cold store starts at once, in the background
        server.wait_for(
            lambda: get(server, "/v1/runs/rec-image")["lifecycle"]["restore_state"] == "restored",
            timeout=30,
            what="the restore of a rebuilt cold run",
        )
        restored = tmp_path / "restored.rrd"
        restored.write_bytes(recordings_served(server, ["rec-image"])["rec-image"][1])
    finally:
        server.stop()

    # Rerun's clients find the same datasets under the same entry ids (kept in run.json)
    assert sorted(datasets_before) == sorted({r["application_id"] for r in before["/v1/runs"]["runs"]})
    assert datasets_after == datasets_before
    # the tiers are where the data is, as before
    assert {r["id"] for r in before["/v1/runs?tier=cold"]["runs"]} == COLD
    assert {r["id"] for r in before["/v1/runs?tier=warm"]["runs"]} == set(run_ids) - COLD
    assert {r["id"] for r in before["/v1/runs"]["runs"] if r["pinned"]} == PINNED
    # every list answers exactly as before
    for query in (q for q in before if q.count("/") == 2):
        assert after[query] == before[query], f"GET {query}: {sorted(differences(before[query], after[query]))}"
    # each run answers as before, but for what the stores cannot tell
    for run_id in run_ids:
        query = f"/v1/runs/{run_id}"
        lost = differences(before[query], after[query])
        assert lost <= LOST, f"GET {query}: {sorted(lost - LOST)} differ after the rebuild"
        if run_id in COLD:  # the cold object's time stands in for the archive's
            archived = [dt.datetime.fromisoformat(a[query]["lifecycle"]["archived_at"]) for a in (before, after)]
            assert abs(archived[1] - archived[0]) < dt.timedelta(seconds=30), archived
        assert [e["action"] for e in after[query]["events"]] == ["rebuild"]
        assert after[query]["lifecycle"]["promoted_at"] == before[query]["lifecycle"]["promoted_at"]
    # recordings: warm ones byte for byte, cold ones refused (409) until restored
    assert served_after == served_before
    assert {r for r, (status, _) in served_before.items() if status == 409} == COLD
    source = next(recordings[s] for s in SCENES if recordings[s].recordings[0]["recording_id"] == "rec-image")
    rerun_rrd_ok(rerun_bin, "compare", "--unordered", source.path, restored)


# --- datasets: their entry ids are kept in run.json and come back with a rebuild -----------------


@pytest.fixture(scope="module")
def app_runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Three small runs logged with the real SDK: two of application `nav` (robots a and b), one of `arm`."""
    folder = tmp_path_factory.mktemp("dataset-runs")
    runs = {"nav-a": ("nav", "robot-a"), "nav-b": ("nav", "robot-b"), "arm-a": ("arm", "robot-a")}
    with ThreadPoolExecutor(2) as pool:
        made = {
            run_id: pool.submit(
                log_run, folder / f"{run_id}.rrd", run_id, entities=1, frames=3, points=10, robot=robot, application=app
            )
            for run_id, (app, robot) in runs.items()
        }
        return {run_id: future.result() for run_id, future in made.items()}


def _datasets(node: Node) -> dict[str, str]:
    with session_scope(node.catalog) as session:
        return {d.name: d.entry_id for d in queries.datasets(session)}


def _run_json_key(node: Node, run_id: str) -> str:
    with session_scope(node.catalog) as session:
        life = queries.lifecycle(session, run_id)
        assert life is not None, f"{run_id} is not sealed"
        return f"{life.prefix}/{RUN_JSON}"


@pytest.mark.parametrize("tiers", ["file"], indirect=True)
def test_a_rebuild_gives_each_dataset_the_entry_id_its_run_json_kept(
    tiers: Tiers, make_node: NodeFactory, app_runs: dict[str, Path]
):
    clock = Clock()
    node = make_node(tiers, clock=clock, promote_after_s=60)
    for path in app_runs.values():
        node.upload(path)
    clock.advance(seconds=60)
    assert [o.ok for o in run_plan(node.retention, plan(node.retention, [PROMOTE]))] == [True] * 3
    kept = _datasets(node)
    assert sorted(kept) == ["arm", "nav"]
    for run_id in app_runs:  # every sealed run carries its dataset's entry id
        found = parse_run_json(tiers.warm.get_range(_run_json_key(node, run_id)))
        assert found.dataset_id == kept[found.record.application_id], run_id
    # The first nav run listed (robot-a's) was sealed before datasets existed: its run.json has no id.
    old_key = _run_json_key(node, "nav-a")
    old = json.loads(tiers.warm.get_range(old_key))
    del old["dataset_id"]
    tiers.warm.put(old_key, json.dumps(old).encode())
    arm_key = _run_json_key(node, "arm-a")
    arm = json.loads(tiers.warm.get_range(arm_key))
    del arm["dataset_id"]  # an application whose every run.json is that old
    tiers.warm.put(arm_key, json.dumps(arm).encode())

    with session_scope(node.catalog, write=True) as session:  # the catalog is lost
        for table in ("runs", "run_lifecycle", "run_objects", "run_entities", "run_timelines", "datasets"):
            session.execute(sa.text(f"DELETE FROM {table}"))
    steps = rebuild(node.catalog, node.tiers, clock.advance(days=1))
    assert sorted(s.outcome for s in steps) == ["added"] * 3
    after = _datasets(node)
    assert after["nav"] == kept["nav"]  # from nav-b's run.json, though nav-a's came first
    assert after["arm"] != kept["arm"] and re.fullmatch(r"[0-9A-F]{16}[0-9a-f]{16}", after["arm"])
    again = rebuild(node.catalog, node.tiers, clock.advance(days=1))  # repeatable: ids stay as they are
    assert {s.outcome for s in again} == {"present"} and _datasets(node) == after
