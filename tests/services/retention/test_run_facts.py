"""A sealed run's facts have one home, the catalog: its `run.json` is written from the catalog rows in
the transaction that changes them (promotion, pin, archive), and ingest asks the catalog for a run's
tier rather than trusting what it remembers of sealing it."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from catalog import queries
from catalog.db import session_scope
from core.errors import ConflictError
from services.retention.schedule import retention_job
from services.retention.service import plan, run_plan, set_pinned
from services.sealed.tiers import RunJson, Tiers, catalog_run_json, parse_run_json
from services.sealed.write import RECORDING, RUN_JSON
from services.storage.objectstore import ObjectInfo, ObjectStore, StorageError
from tests.services.retention.conftest import Clock, Node, NodeFactory, log_run

pytestmark = pytest.mark.sdk

RUN = "facts-run"


@pytest.fixture(scope="module")
def logged(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return log_run(tmp_path_factory.mktemp("facts") / f"{RUN}.rrd", RUN, entities=2, frames=5, points=50)


def _promote(node: Node, path: Path) -> None:
    node.upload(path)
    node.clock.advance(seconds=node.retention.promote_after.total_seconds() + 1)
    assert all(o.ok for o in run_plan(node.retention, plan(node.retention, ["promote"])))


def _archive(node: Node) -> None:
    node.clock.advance(days=31)
    outcomes = retention_job(node.retention)
    assert outcomes is not None and [(o.action.action, o.ok) for o in outcomes] == [("archive", True)]


def _in_bucket(node: Node) -> RunJson:
    with session_scope(node.catalog) as session:
        life = queries.lifecycle(session, RUN)
        assert life is not None
        prefix = life.prefix
    return parse_run_json(node.tiers.warm.get_range(f"{prefix}/{RUN_JSON}"))


def _in_catalog(node: Node) -> RunJson:
    with session_scope(node.catalog) as session:
        found = catalog_run_json(session, RUN)
    assert found is not None
    return found


def test_run_json_says_what_the_catalog_says_after_each_change(tiers: Tiers, make_node: NodeFactory, logged: Path):
    node = make_node(tiers, clock=Clock(), warm_days=30, cold_days=365)
    _promote(node, logged)
    sealed = _in_bucket(node)
    assert sealed == _in_catalog(node)
    assert (sealed.record.tier, sealed.record.status, sealed.pinned) == ("warm", "closed", False)

    set_pinned(node.retention, RUN, True, "bob@lab")
    pinned = _in_bucket(node)
    assert pinned == _in_catalog(node) and (pinned.pinned, pinned.pinned_by) == (True, "bob@lab")

    _archive(node)
    archived = _in_bucket(node)
    assert archived == _in_catalog(node)
    assert archived.record.tier == "cold" and archived.pinned
    assert {o.name: o.tier for o in archived.objects}[RECORDING] == "cold"

    set_pinned(node.retention, RUN, False, "bob@lab")
    unpinned = _in_bucket(node)
    assert unpinned == _in_catalog(node) and (unpinned.pinned, unpinned.pinned_by) == (False, None)


class RunJsonFails:
    """The warm store, refusing to write run.json while `armed`."""

    def __init__(self, inner: ObjectStore) -> None:
        self.inner, self.url, self.armed = inner, inner.url, False

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)

    def put(self, key: str, data: Any) -> ObjectInfo:
        if self.armed and key.endswith(f"/{RUN_JSON}"):
            raise StorageError(f"injected: cannot write {key}")
        return self.inner.put(key, data)


@pytest.mark.parametrize("tiers", ["file"], indirect=True)
def test_a_pin_whose_run_json_cannot_be_written_is_not_recorded(tiers: Tiers, make_node: NodeFactory, logged: Path):
    warm = RunJsonFails(tiers.warm)
    node = make_node(Tiers(warm, tiers.cold), clock=Clock())  # type: ignore[arg-type]
    _promote(node, logged)
    warm.armed = True
    with pytest.raises(StorageError):
        set_pinned(node.retention, RUN, True, "bob@lab")
    with session_scope(node.catalog) as session:
        assert queries.pin_state(session, RUN) == (False, None)
        assert [e.action for e in queries.run_events(session, RUN)] == ["promote"]
    assert _in_bucket(node) == _in_catalog(node)

    warm.armed = False
    set_pinned(node.retention, RUN, True, "bob@lab")
    assert _in_bucket(node).pinned and _in_catalog(node).pinned


@pytest.mark.parametrize("tiers", ["file"], indirect=True)
def test_data_for_a_run_archived_since_this_node_sealed_it_is_refused(
    tiers: Tiers, make_node: NodeFactory, logged: Path
):
    """Ingest remembers the runs it sealed lately (for data that comes while the catalog does not
    answer), but the catalog's tier wins: the run is cold now, and takes no data until restored."""
    node = make_node(tiers, clock=Clock(), warm_days=30, cold_days=365)
    _promote(node, logged)
    assert node.ingest.recently_sealed[RUN].tier == "warm"
    _archive(node)
    with pytest.raises(ConflictError, match="is cold"):
        node.upload(logged)
    assert node.ingest.hot_run(RUN) is None
