"""Depots for the catalog-server tests: one over a catalog alone (its rows written as ingest and
retention write them), and `fleet serve` holding recordings logged with the real SDK."""

from __future__ import annotations

import datetime as dt
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import grpc
import httpx
from sqlalchemy.orm import sessionmaker

from catalog import queries
from catalog.db import create_engine, session_scope
from catalog.queries import EntityRecord, RunRecord, TimelineRecord
from services.redap.depot import Depot
from services.redap.pb import cloud_pb2
from services.redap.tuid import Tuid
from services.settings import load_settings
from tests.catalog.records import run_record
from tests.services.ingest.live_server import LiveServer
from tests.services.nodes import node_of
from tests.services.redap.client import Redap
from tests.services.rrd.recordings import Recording

NOW = dt.datetime(2026, 11, 21, 12, 0, tzinfo=dt.UTC)
# Scenes both depots serve: one dataset per application id (fleet_merge has two runs, with
# different timelines), recording properties (fleet_props), a robot id from a property.
SCENES = ("points", "properties", "merge_a", "merge_b")


def record(run_id: str, application: str = "nav", **changes: Any) -> RunRecord:
    """A run's catalog record as ingest writes it; `changes` set its fields."""
    return run_record(
        run_id,
        NOW,
        **{
            "application_id": application,
            "started_at": NOW - dt.timedelta(minutes=5),
            "chunks": 3,
            "rows": 30,
            "bytes": 1000,
            "properties": {
                "fleet": {"robot_id": "robot-7"},
                "recording": {"RecordingInfo:start_time": 1_700_000_000 * 10**9},
            },
            "entities": [
                EntityRecord("/world/points", 2, 0, 20, 900, ["rerun.archetypes.Points3D"], ["Points3D:positions"]),
                EntityRecord(
                    "/__properties", 1, 1, 1, 50, ["rerun.archetypes.RecordingInfo"], ["RecordingInfo:start_time"]
                ),
                EntityRecord("/__properties/fleet", 1, 1, 1, 50, [], ["robot_id"]),
            ],
            "timelines": [TimelineRecord("frame", "sequence", 0, 9)],
            **changes,
        },
    )


def save(
    depot: Depot, *records: RunRecord, now: dt.datetime = NOW, later: dict[str, dict[str, Any]] | None = None
) -> None:
    """Write runs as ingest does; `later` sets columns retention owns afterwards (run id ->
    {column: value}: its tier, its pin)."""
    with session_scope(depot.catalog, write=True) as session:
        for made in records:
            queries.save_run(session, made, now)
        for run_id, columns in (later or {}).items():
            run = queries.require_run(session, run_id)
            for column, value in columns.items():
                if (column, value) == ("tier", "deleted"):  # as retention deletes a run
                    queries.mark_deleted(session, run_id, now)
                else:
                    setattr(run, column, value)


def entry_of(depot: Depot, name: str) -> Tuid:
    with session_scope(depot.catalog) as session:
        found = queries.dataset_entry_id(session, name)
    assert found is not None, f"no dataset {name!r}"
    return Tuid.parse(found)


@contextmanager
def catalog_depot(url: str, public_url: str = "") -> Iterator[Depot]:
    """A depot over the catalog at `url` (no hot runs, nothing in its stores: the catalog answers
    all), its node in a folder of its own."""
    engine = create_engine(url)
    try:
        with tempfile.TemporaryDirectory(prefix="catalog-depot-") as root:
            settings = load_settings(data_dir=Path(root) / "data", public_url=public_url)
            yield Depot(node_of(Path(root), sessionmaker(engine), settings=settings), None)
    finally:
        engine.dispose()


# --- `fleet serve` holding the scenes --------------------------------------------------------


def upload(server: LiveServer, recording: Recording, headers: dict[str, str] | None = None) -> list[str]:
    answer = httpx.post(f"{server.url}/v1/uploads", content=recording.data, headers=headers or {}, timeout=60)
    assert answer.status_code == 200, answer.text
    runs: list[str] = answer.json()["runs"]
    return runs


def promote(server: LiveServer, run_id: str, headers: dict[str, str] | None = None) -> None:
    """Seal a closed run into the warm tier now (an uploaded run is closed once uploaded)."""
    answer = httpx.post(f"{server.url}/v1/runs/{run_id}/promote", headers=headers or {}, timeout=60)
    assert answer.status_code == 200, answer.text
    assert answer.json()["tier"] == "warm", answer.text


def dataset_ids(client: Redap) -> dict[str, str]:
    """name -> entry id of every dataset a catalog server lists."""
    kinds = [cloud_pb2.ENTRY_KIND_DATASET]
    found = client.call("FindEntries", cloud_pb2.FindEntriesRequest(filter=cloud_pb2.EntryFilter(entry_kinds=kinds)))
    return {e.name: str(Tuid.from_proto(e.id.id)) for e in found.entries}


def table_ids(client: Redap) -> dict[str, str]:
    kinds = [cloud_pb2.ENTRY_KIND_TABLE]
    found = client.call("FindEntries", cloud_pb2.FindEntriesRequest(filter=cloud_pb2.EntryFilter(entry_kinds=kinds)))
    return {e.name: str(Tuid.from_proto(e.id.id)) for e in found.entries}


# --- the same scenes in the depot and in Rerun's own server --------------------------------------


@contextmanager
def serving(scenes: dict[str, Recording], data_dir: Path, **settings: str) -> Iterator[LiveServer]:
    """`fleet serve` holding the scenes, rec-points sealed into the warm tier, the others hot;
    `settings` as for LiveServer (auth="on": uploads and promotion with the admin token)."""
    server = LiveServer(data_dir, scheduler="false", promote_after_s="0", **settings)
    server.start()
    try:
        for scene in SCENES:
            upload(server, scenes[scene], server.headers)
        promote(server, "rec-points", server.headers)
        yield server
    finally:
        server.stop()


def reference_datasets(scenes: dict[str, Recording]) -> dict[str, list[Recording]]:
    """The scenes as Rerun's server loads them: a dataset per application id, named after it."""
    found: dict[str, list[Recording]] = {}
    for scene in SCENES:
        found.setdefault(scenes[scene].recordings[0]["application_id"], []).append(scenes[scene])
    return found


def rerun_own(name: str) -> bool:
    """Entries Rerun's server makes that the depot has no use for: blueprint and asset datasets."""
    return name.startswith(("__bp_", "__as_"))


def status_of(client: Redap, rpc: str, request: object, entry: str | None = None) -> grpc.StatusCode:
    try:
        client.call(rpc, request, entry=entry)
    except grpc.RpcError as exc:
        return exc.code()  # type: ignore[no-any-return,attr-defined]
    return grpc.StatusCode.OK
