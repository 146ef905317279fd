"""Warm -> cold -> deleted: archive by copying to a cold store (local, moto, a real SeaweedFS) or by
an S3 storage class (moto, which enforces archive semantics: reads fail with InvalidObjectState
until a restore, which takes time), restores over REST, expiry with pins and tombstones, and
archive/delete steps that fail part way through leaving the run whole."""

from __future__ import annotations

import datetime as dt
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from catalog import queries
from catalog.db import session_scope
from core.errors import ConflictError
from services.analytics.service import Analytics, extract_hot_run
from services.analytics.sql import Limits
from services.api.app import create_app
from services.retention.schedule import retention_job
from services.retention.service import plan, run_plan
from services.rrd import iter_events
from services.sealed.tiers import Tiers
from services.sealed.write import INDEX, RECORDING, RUN_JSON
from services.storage.objectstore import ObjectInfo, ObjectStore, StorageError, open_store
from services.storage.s3 import S3Store
from tests.seaweedfs import seaweedfs
from tests.services.ingest import feeding
from tests.services.retention.conftest import Clock, Node, NodeFactory, listing, log_run
from tests.services.rrd.recordings import rerun_rrd_ok
from tests.waiting import wait_for

pytestmark = pytest.mark.sdk

RUN_A, RUN_B = "arch-a", "arch-b"
SEAWEED_BUCKET = "fleet-retention"
CREDENTIALS = (("AWS_ACCESS_KEY_ID", "test"), ("AWS_SECRET_ACCESS_KEY", "test"), ("AWS_DEFAULT_REGION", "us-east-1"))


@pytest.fixture(scope="module")
def logged(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Two small runs logged with the real SDK, reused by every test (each test has its own catalog)."""
    root = tmp_path_factory.mktemp("archive-runs")
    return {run: log_run(root / f"{run}.rrd", run, entities=3, frames=10, points=200) for run in (RUN_A, RUN_B)}


def _promoted(node: Node, logged: dict[str, Path], *runs: str) -> dict[str, tuple[str, bytes]]:
    """Upload and promote `runs`; returns each run's prefix and its sealed recording's bytes."""
    for run in runs:
        node.upload(logged[run])
    node.clock.advance(seconds=node.retention.promote_after.total_seconds() + 1)
    promotions = plan(node.retention, ["promote"])
    assert sorted(a.run_id for a in promotions) == sorted(runs)
    assert all(o.ok for o in run_plan(node.retention, promotions))
    out = {}
    for run in runs:
        prefix = next(k for k in listing(node.tiers.warm) if k.endswith(f"/{run}/{RUN_JSON}")).rsplit("/", 1)[0]
        out[run] = (prefix, node.tiers.warm.get_range(f"{prefix}/{RECORDING}"))
    return out


def _client(node: Node) -> TestClient:
    return TestClient(create_app(node.context, node.ingest, node.retention))


def _retention(node: Node) -> list[tuple[str, str, str]]:
    outcomes = retention_job(node.retention)
    assert outcomes is not None
    assert all(o.ok for o in outcomes), [o.to_dict() for o in outcomes]
    return [(o.action.run_id, o.action.action, o.detail) for o in outcomes]


def _planned(node: Node) -> list[tuple[str, str]]:
    return [(a.run_id, a.action) for a in plan(node.retention)]


def _detail(client: TestClient, run: str) -> dict[str, Any]:
    got = client.get(f"/v1/runs/{run}")
    assert got.status_code == 200, got.text
    body: dict[str, Any] = got.json()
    return body


def _wait_restored(client: TestClient, run: str) -> None:
    """The copy back from the cold tier runs in a thread: wait for the run to read as restored."""
    wait_for(lambda: _detail(client, run)["lifecycle"]["restore_state"] == "restored", 30, "the restore to finish")


def _download(client: TestClient, run: str) -> Any:
    return client.get(f"/v1/runs/{run}/recording.rrd")


def _keys(store: ObjectStore, prefix: str) -> set[str]:
    return {k for k in listing(store) if k.startswith(prefix + "/")}


def _iso(when: dt.datetime) -> dt.datetime:
    return when.replace(microsecond=0)


def _at(text: str) -> dt.datetime:
    return _iso(dt.datetime.fromisoformat(text.replace("Z", "+00:00")))


# --- store-copy mode: the cold tier is a separate store ------------------------------------------


def _store_cycle(node: Node, logged: dict[str, Path], rerun_bin: str | None = None) -> None:
    """Archive to the cold store, a restore over REST, serving while restored, and the restore's end."""
    [(prefix, original)] = _promoted(node, logged, RUN_A).values()
    client = _client(node)
    key = f"{prefix}/{RECORDING}"
    node.clock.advance(days=29)
    assert _planned(node) == []
    node.clock.advance(days=2)  # past warm_days = 30
    assert _planned(node) == [(RUN_A, "archive")]
    [(_, _, detail)] = _retention(node)
    assert node.tiers.cold.url in detail
    assert _keys(node.tiers.warm, prefix) == {f"{prefix}/{INDEX}", f"{prefix}/{RUN_JSON}"}
    assert _keys(node.tiers.cold, prefix) == {key} and node.tiers.cold.get_range(key) == original
    run = _detail(client, RUN_A)
    assert run["tier"] == "cold" and run["lifecycle"]["archive_mode"] == "store"
    assert _at(run["lifecycle"]["archived_at"]) == _iso(node.clock.now)
    tiers_of = {o["name"]: o["tier"] for o in run["objects"]}
    assert tiers_of.pop(RECORDING) == "cold" and set(tiers_of.values()) == {"warm"}  # the index, analytics
    [archived] = [e for e in run["events"] if e["action"] == "archive"]
    assert archived["actor"] == "retention" and archived["policy"] == "default"
    assert _planned(node) == []  # archiving is done once

    refused = _download(client, RUN_A)
    assert refused.status_code == 409 and f"POST /v1/runs/{RUN_A}/restore" in refused.json()["message"]

    asked = client.post(f"/v1/runs/{RUN_A}/restore", headers={"X-Fleet-User": "alice@lab"})
    assert asked.status_code == 202, asked.text
    assert asked.json()["restore_state"] == "restoring"
    assert _at(asked.json()["restore_until"]) == _iso(node.clock.now + dt.timedelta(days=7))
    _wait_restored(client, RUN_A)
    events = _detail(client, RUN_A)["events"]
    assert any(e["action"] == "restore" and e["actor"] == "alice@lab" for e in events)
    served = _download(client, RUN_A)
    assert served.status_code == 200 and served.content == original
    assert node.tiers.warm.get_range(key) == original
    if rerun_bin is not None:
        copy = node.root / "restored.rrd"
        copy.write_bytes(served.content)
        rerun_rrd_ok(rerun_bin, "compare", "--unordered", logged[RUN_A], copy)

    node.clock.advance(days=6)
    assert _planned(node) == []  # still inside restore_days
    node.clock.advance(days=1, seconds=1)
    assert _planned(node) == [(RUN_A, "restore")]
    assert [d for *_, d in _retention(node)] == ["restore ended"]
    assert _keys(node.tiers.warm, prefix) == {f"{prefix}/{INDEX}", f"{prefix}/{RUN_JSON}"}
    assert node.tiers.cold.get_range(key) == original
    assert _detail(client, RUN_A)["lifecycle"]["restore_state"] is None
    ended = _download(client, RUN_A)
    assert ended.status_code == 409 and "restore" in ended.json()["message"]


def test_store_archive_restore_and_its_end(
    tiers: Tiers, make_node: NodeFactory, logged: dict[str, Path], rerun_bin: str
):
    _store_cycle(make_node(tiers, clock=Clock()), logged, rerun_bin)


def test_restore_asked_twice_changes_nothing(tiers: Tiers, make_node: NodeFactory, logged: dict[str, Path]):
    """`fleet runs restore RUN` run again while restoring or once restored answers the same state."""
    node = make_node(tiers, clock=Clock())
    _promoted(node, logged, RUN_A)
    client = _client(node)
    node.clock.advance(days=31)
    _retention(node)
    first = client.post(f"/v1/runs/{RUN_A}/restore", headers={"X-Fleet-User": "alice@lab"})
    assert first.status_code == 202
    _wait_restored(client, RUN_A)
    again = client.post(f"/v1/runs/{RUN_A}/restore", headers={"X-Fleet-User": "bob@lab"})
    assert again.status_code == 202, again.text
    assert again.json()["restore_state"] == "restored"
    assert again.json()["restore_until"] == first.json()["restore_until"]  # not extended by asking again
    assert not any(e["actor"] == "bob@lab" for e in _detail(client, RUN_A)["events"])


@pytest.fixture(scope="module")
def seaweed_endpoint(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    import boto3

    with seaweedfs(tmp_path_factory.mktemp("seaweedfs")) as endpoint:
        # One bucket; warm/ and cold/ prefixes per test (each SeaweedFS bucket reserves volumes of its own).
        boto3.client(
            "s3", endpoint_url=endpoint, region_name="us-east-1", aws_access_key_id="test", aws_secret_access_key="test"
        ).create_bucket(Bucket=SEAWEED_BUCKET)
        yield endpoint


@pytest.mark.s3server
def test_store_archive_on_seaweedfs(
    seaweed_endpoint: str,
    make_node: NodeFactory,
    logged: dict[str, Path],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
):
    for name, value in CREDENTIALS:
        monkeypatch.setenv(name, value)
    warm, cold = (
        open_store(f"s3://{SEAWEED_BUCKET}/{tmp_path.name}/{tier}", endpoint_url=seaweed_endpoint, region="us-east-1")
        for tier in ("warm", "cold")
    )
    _store_cycle(make_node(Tiers(warm, cold), clock=Clock()), logged)


# --- storage-class mode on moto ------------------------------------------------------------------


@pytest.fixture
def moto_stores(monkeypatch: pytest.MonkeyPatch) -> Iterator[tuple[S3Store, S3Store]]:
    for name, value in CREDENTIALS:
        monkeypatch.setenv(name, value)
    from moto import mock_aws

    with mock_aws():
        import boto3

        client = boto3.client("s3", region_name="us-east-1")
        for bucket in ("fleet-warm", "fleet-cold"):
            client.create_bucket(Bucket=bucket)
        # (moto answers inside botocore: no reads on the event loop, which would bypass it)
        warm, cold = (
            S3Store(f"s3://{bucket}/depot", region="us-east-1", loop_reads=False)
            for bucket in ("fleet-warm", "fleet-cold")
        )
        yield warm, cold


@pytest.fixture
def slow_restores() -> Iterator[None]:
    """moto restores an object only after it was read a few times: a restore that takes time."""
    from moto.moto_api import state_manager

    state_manager.set_transition(model_name="s3::keyrestore", transition={"progression": "manual", "times": 2})
    yield
    state_manager.unset_transition(model_name="s3::keyrestore")


@pytest.mark.parametrize("storage_class", ["GLACIER", "DEEP_ARCHIVE"])
def test_storage_class_archive_and_restore(
    moto_stores: tuple[S3Store, S3Store],
    make_node: NodeFactory,
    logged: dict[str, Path],
    slow_restores: None,
    storage_class: str,
):
    warm, cold = moto_stores
    node = make_node(Tiers(warm, cold, cold_storage_class=storage_class), clock=Clock())
    [(prefix, original)] = _promoted(node, logged, RUN_A).values()
    client = _client(node)
    key = f"{prefix}/{RECORDING}"
    node.clock.advance(days=31)
    [(_, _, detail)] = _retention(node)
    assert storage_class in detail
    assert warm.head(key).storage_class == storage_class and listing(cold) == []  # archived in place
    with pytest.raises(ConflictError, match="is archived: restore it"):  # S3 (moto) refuses: InvalidObjectState
        warm.get_range(key, 0, 16)
    assert warm.get_range(f"{prefix}/{INDEX}")  # the index stays readable
    run = _detail(client, RUN_A)
    assert run["tier"] == "cold" and run["lifecycle"]["archive_mode"] == storage_class
    assert _download(client, RUN_A).status_code == 409

    asked = client.post(f"/v1/runs/{RUN_A}/restore", headers={"X-Fleet-User": "carol@lab"})
    assert asked.status_code == 202 and asked.json()["restore_state"] == "restoring"
    under_way = 0
    for _ in range(20):  # each retention run looks at the object once; moto finishes after a few looks
        [(_, action, detail)] = _retention(node)
        assert action == "restore"
        if detail == "restored":
            break
        assert detail == "restore under way"
        under_way += 1
        assert _detail(client, RUN_A)["lifecycle"]["restore_state"] == "restoring"
        busy = _download(client, RUN_A)
        assert busy.status_code == 409 and "under way" in busy.json()["message"]
    assert under_way >= 1, "the restore was never seen in progress"
    assert _detail(client, RUN_A)["lifecycle"]["restore_state"] == "restored"
    served = _download(client, RUN_A)
    assert served.status_code == 200 and served.content == original
    assert warm.head(key).storage_class == storage_class  # served from the restored copy, still archived

    node.clock.advance(days=7, seconds=1)
    assert [d for *_, d in _retention(node)] == ["restore ended"]
    assert _download(client, RUN_A).status_code == 409


def test_standard_ia_cold_run_serves_without_a_restore(
    moto_stores: tuple[S3Store, S3Store], make_node: NodeFactory, logged: dict[str, Path]
):
    """STANDARD_IA is cheaper to keep but reads like any object (S3 refuses RestoreObject for it):
    a run archived there stays downloadable, and a restore is refused as not needed."""
    warm, cold = moto_stores
    node = make_node(Tiers(warm, cold, cold_storage_class="STANDARD_IA"), clock=Clock())
    [(prefix, original)] = _promoted(node, logged, RUN_A).values()
    client = _client(node)
    node.clock.advance(days=31)
    _retention(node)
    assert warm.head(f"{prefix}/{RECORDING}").storage_class == "STANDARD_IA"
    assert warm.get_range(f"{prefix}/{RECORDING}") == original  # S3 itself serves it
    assert _detail(client, RUN_A)["tier"] == "cold"
    served = _download(client, RUN_A)
    assert served.status_code == 200 and served.content == original
    refused = client.post(f"/v1/runs/{RUN_A}/restore")
    assert refused.status_code == 409 and "without a restore" in refused.json()["message"]
    assert _detail(client, RUN_A)["lifecycle"]["restore_state"] is None


def test_storage_class_archive_is_safe_to_repeat(
    moto_stores: tuple[S3Store, S3Store], make_node: NodeFactory, logged: dict[str, Path]
):
    """A crash after the storage-class change but before the catalog switch: the next run finishes it."""
    warm, cold = moto_stores
    node = make_node(Tiers(warm, cold, cold_storage_class="GLACIER"), clock=Clock())
    [(prefix, _)] = _promoted(node, logged, RUN_A).values()
    warm.set_storage_class(f"{prefix}/{RECORDING}", "GLACIER")  # what the crashed attempt did
    node.clock.advance(days=31)
    _retention(node)
    assert _detail(_client(node), RUN_A)["tier"] == "cold"


# --- expiry --------------------------------------------------------------------------------------


def test_expiry_deletes_objects_then_keeps_a_tombstone_unless_pinned(
    tiers: Tiers, make_node: NodeFactory, logged: dict[str, Path]
):
    node = make_node(tiers, clock=Clock(), warm_days=30, cold_days=365)
    sealed = _promoted(node, logged, RUN_A, RUN_B)
    client = _client(node)
    pinned = client.post(f"/v1/runs/{RUN_B}/pin", headers={"X-Fleet-User": "bob@lab"})
    assert pinned.status_code == 200 and pinned.json() == {"run": RUN_B, "pinned": True, "by": "bob@lab"}
    run_b = _detail(client, RUN_B)
    assert run_b["pinned"] is True and run_b["lifecycle"]["pinned_by"] == "bob@lab"
    assert b'"pinned": true' in tiers.warm.get_range(f"{sealed[RUN_B][0]}/{RUN_JSON}")  # for rebuilds

    node.clock.advance(days=31)
    assert sorted(_planned(node)) == [(RUN_A, "archive"), (RUN_B, "archive")]  # pins do not stop archiving
    _retention(node)
    node.clock.advance(days=363)
    assert _planned(node) == []
    node.clock.advance(days=1)
    [action] = plan(node.retention)
    assert (action.run_id, action.action, action.policy) == (RUN_A, "delete", "default")
    assert "30 days warm + 365 days cold" in action.reason
    prefix_a, prefix_b = sealed[RUN_A][0], sealed[RUN_B][0]
    keys_a = {o["key"] for o in _detail(client, RUN_A)["objects"]} | _keys(tiers.warm, prefix_a)
    assert f"{prefix_a}/{RUN_JSON}" in keys_a and _keys(tiers.cold, prefix_a) == {f"{prefix_a}/{RECORDING}"}
    [(_, _, detail)] = _retention(node)
    assert detail == f"deleted ({len(keys_a)} objects)"  # recording.rrd cold; the rest warm

    assert not keys_a & set(listing(tiers.warm)) and not keys_a & set(listing(tiers.cold))
    assert _keys(tiers.cold, prefix_b) == {f"{prefix_b}/{RECORDING}"}
    run_a = _detail(client, RUN_A)
    assert run_a["tier"] == "deleted" and run_a["objects"] == []
    life = run_a["lifecycle"]
    assert _at(life["deleted_at"]) == _iso(node.clock.now)
    assert (life["deleted_by"], life["deleted_policy"]) == ("retention", "default")
    assert run_a["events"][-1]["action"] == "delete"
    gone = _download(client, RUN_A)
    assert gone.status_code == 410 and "retention policy 'default'" in gone.json()["message"]
    assert client.post(f"/v1/runs/{RUN_A}/pin").status_code == 409
    assert client.post(f"/v1/runs/{RUN_A}/restore").status_code == 409
    assert _detail(client, RUN_B)["tier"] == "cold"

    node.clock.advance(days=100)
    assert _planned(node) == []  # pinned: kept however old
    assert client.request("DELETE", f"/v1/runs/{RUN_B}/pin", headers={"X-Fleet-User": "bob@lab"}).status_code == 200
    assert _detail(client, RUN_B)["lifecycle"]["pinned_by"] is None
    assert _planned(node) == [(RUN_B, "delete")]
    _retention(node)
    assert listing(tiers.warm) == [] and listing(tiers.cold) == []
    assert _detail(client, RUN_B)["lifecycle"]["deleted_by"] == "retention"


def test_no_cold_days_goes_straight_from_warm_to_deleted(tiers: Tiers, make_node: NodeFactory, logged: dict[str, Path]):
    node = make_node(tiers, clock=Clock(), warm_days=10, cold_days=0)
    _promoted(node, logged, RUN_A)
    node.clock.advance(days=9)
    assert _planned(node) == []
    node.clock.advance(days=1, seconds=1)
    assert _planned(node) == [(RUN_A, "delete")]
    _retention(node)
    assert listing(tiers.warm) == [] and listing(tiers.cold) == []
    run = _detail(_client(node), RUN_A)
    assert run["tier"] == "deleted" and run["lifecycle"]["archived_at"] is None
    assert [e["action"] for e in run["events"]] == ["promote", "delete"]


# --- failures part way through ---------------------------------------------------------------------


class Faulty:
    """A store whose puts or deletes fail on purpose while `armed`; everything else is the real store."""

    def __init__(self, inner: ObjectStore, fault: str) -> None:
        self.inner, self.fault, self.armed = inner, fault, True
        self.url = inner.url

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)

    def put(self, key: str, data: Any) -> ObjectInfo:
        if not self.armed or self.fault not in ("crash", "short"):
            return self.inner.put(key, data)
        half = data.read(-1) if hasattr(data, "read") else bytes(data)
        info = self.inner.put(key, half[: len(half) // 2])  # a torn upload left behind
        if self.fault == "crash":
            raise StorageError(f"injected: connection reset while writing {key}")
        return info  # "short": the store says it holds less than was sent

    def delete(self, key: str) -> None:
        if self.armed and self.fault == "delete":
            raise StorageError(f"injected: cannot delete {key}")
        self.inner.delete(key)


@pytest.mark.parametrize("fault", ["crash", "short"])
def test_archive_that_fails_leaves_the_run_warm(
    tiers: Tiers, make_node: NodeFactory, logged: dict[str, Path], fault: str
):
    faulty = Faulty(tiers.cold, fault)
    node = make_node(Tiers(tiers.warm, faulty), clock=Clock())  # type: ignore[arg-type]
    [(prefix, original)] = _promoted(node, logged, RUN_A).values()
    client = _client(node)
    node.clock.advance(days=31)
    [outcome] = retention_job(node.retention) or []
    assert not outcome.ok and "StorageError" in outcome.detail
    run = _detail(client, RUN_A)
    assert run["tier"] == "warm" and not any(e["action"] == "archive" for e in run["events"])
    assert tiers.warm.get_range(f"{prefix}/{RECORDING}") == original
    served = _download(client, RUN_A)
    assert served.status_code == 200 and served.content == original
    assert client.get("/v1/retention").json()["recent_jobs"][0]["outcome"] == "failed"

    faulty.armed = False
    assert _planned(node) == [(RUN_A, "archive")]  # tried again at the next run
    _retention(node)
    assert _detail(client, RUN_A)["tier"] == "cold"
    assert tiers.cold.get_range(f"{prefix}/{RECORDING}") == original  # the torn copy was replaced
    assert _keys(tiers.warm, prefix) == {f"{prefix}/{INDEX}", f"{prefix}/{RUN_JSON}"}


def test_delete_that_fails_leaves_no_tombstone(tiers: Tiers, make_node: NodeFactory, logged: dict[str, Path]):
    faulty = Faulty(tiers.cold, "delete")
    node = make_node(Tiers(tiers.warm, faulty), clock=Clock(), warm_days=1, cold_days=1)  # type: ignore[arg-type]
    [(prefix, _)] = _promoted(node, logged, RUN_A).values()
    client = _client(node)
    node.clock.advance(days=1, seconds=1)
    _retention(node)
    node.clock.advance(days=1)
    [outcome] = retention_job(node.retention) or []
    assert outcome.action.action == "delete" and not outcome.ok
    run = _detail(client, RUN_A)
    assert run["tier"] == "cold" and run["lifecycle"]["deleted_at"] is None  # not marked while objects remain
    assert _keys(tiers.cold, prefix) == {f"{prefix}/{RECORDING}"}
    faulty.armed = False
    assert _planned(node) == [(RUN_A, "delete")]
    _retention(node)
    assert listing(tiers.warm) == [] and listing(tiers.cold) == []
    assert _detail(client, RUN_A)["lifecycle"]["deleted_by"] == "retention"


def test_analytics_written_early_are_kept_once_and_deleted_with_the_run(
    tiers: Tiers, make_node: NodeFactory, tmp_path: Path
):
    """A hot run's analytics written early (under the default robot: its identity came later) are
    replaced at promotion, not added to, and go with the run when it is deleted."""
    node = make_node(tiers, clock=Clock())
    early = log_run(tmp_path / "early.rrd", "early-run", entities=1, frames=5, points=10)
    later = log_run(tmp_path / "later.rrd", "early-run", entities=1, frames=5, points=10, robot="robot-7")
    node.upload(early)
    analytics = Analytics(node.context, Limits())
    written = extract_hot_run(analytics, node.ingest, "early-run")
    assert written and all("robot_id=robot-0/" in w["key"] for w in written)
    node.upload(later)  # the robot's identity arrives: the run is filed under robot-7
    node.clock.advance(seconds=node.retention.promote_after.total_seconds() + 1)
    assert all(o.ok for o in run_plan(node.retention, plan(node.retention, ["promote"])))
    files = [k for k in listing(node.tiers.warm) if k.startswith("analytics/")]
    assert files and all("robot_id=robot-7/" in k for k in files)  # one copy per table, the sealed one
    assert sorted({k.split("/")[1] for k in files}) == sorted(k.split("/")[1] for k in files)
    with session_scope(node.catalog) as session:
        assert queries.analytics_keys(session, "early-run") == set(files)
    assert _client(node).delete("/v1/runs/early-run").status_code == 200
    assert [k for k in listing(node.tiers.warm) if k.startswith("analytics/")] == []


def test_user_mistakes_on_run_actions_are_never_500(tiers: Tiers, make_node: NodeFactory, logged: dict[str, Path]):
    node = make_node(tiers, clock=Clock())
    client = _client(node)
    node.upload(logged[RUN_A])  # hot
    restore = client.post(f"/v1/runs/{RUN_A}/restore")
    assert restore.status_code == 409 and "not sealed yet" in restore.json()["message"]
    assert client.post("/v1/runs/no-such-run/restore").status_code == 404
    assert client.post("/v1/runs/no-such-run/promote").status_code == 404
    live = node.ingest.open_source(live=True)  # a stream still sending the run
    feeding.feed(node.ingest, live, iter_events(logged[RUN_B]))
    still_live = client.post(f"/v1/runs/{RUN_B}/promote")
    assert still_live.status_code == 409 and "live" in still_live.json()["message"]
    node.ingest.close_source(live)

    planned = client.get("/v1/retention/plan").json()  # not due yet: the plan says when
    upcoming = {u["run"]: u for u in planned["upcoming"]}
    assert planned["actions"] == [] and set(upcoming) == {RUN_A, RUN_B}
    assert upcoming[RUN_A]["at"] is not None and "idle" in upcoming[RUN_A]["reason"]
    done = client.post(f"/v1/runs/{RUN_A}/promote")  # now, whatever its idle time
    assert done.status_code == 200 and done.json()["tier"] == "warm", done.text
    assert _detail(client, RUN_A)["tier"] == "warm"
    twice = client.post(f"/v1/runs/{RUN_A}/promote")
    assert twice.status_code == 409 and "warm already" in twice.json()["message"]
