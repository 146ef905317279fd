"""The actor written into a run's events and tombstone is the token's subject, whatever a client
says of itself (X-Fleet-User names the actor only when auth is off)."""

from __future__ import annotations

import pytest

from catalog import queries
from catalog.db import session_scope
from catalog.models import RunLifecycle
from tests.services.auth.conftest import Depot, bearer
from tests.services.rrd.recordings import Recording

pytestmark = pytest.mark.sdk

RUN = "rec-points"


def test_pins_and_deletes_are_done_by_the_tokens_subject(depot: Depot, scenes: dict[str, Recording]):
    bob = bearer(depot.token("write", name="bob")) | {"X-Fleet-User": "mallory"}
    alice = bearer(depot.token("admin", name="alice")) | {"X-Fleet-User": "mallory"}
    client = depot.client
    assert client.post("/v1/uploads", content=scenes["points"].data, headers=bob).status_code == 200
    assert client.post(f"/v1/runs/{RUN}/promote", headers=bob).status_code == 200
    pinned = client.post(f"/v1/runs/{RUN}/pin", headers=bob)
    assert pinned.status_code == 200 and pinned.json()["by"] == "bob", pinned.text
    assert client.get(f"/v1/runs/{RUN}", headers=bob).json()["pinned_by"] == "bob"
    assert client.delete(f"/v1/runs/{RUN}/pin", headers=bob).status_code == 200
    assert client.delete(f"/v1/runs/{RUN}", headers=bob).status_code == 403  # deleting takes admin
    deleted = client.delete(f"/v1/runs/{RUN}", headers=alice)
    assert deleted.status_code == 200, deleted.text

    events = client.get(f"/v1/runs/{RUN}", headers=alice).json()["events"]
    actors = {e["action"]: e["actor"] for e in events}
    assert actors["pin"] == "bob" and actors["unpin"] == "bob" and actors["delete"] == "alice", events
    assert actors["promote"] == "bob", events  # asked for by a person: not done by "retention"
    with session_scope(depot.app.state.catalog) as session:
        stored = [(e.action, e.actor) for e in queries.run_events(session, RUN)]
        tombstone = session.get(RunLifecycle, RUN)
        assert tombstone is not None and tombstone.deleted_by == "alice"
    assert ("delete", "alice") in stored and not any(actor == "mallory" for _, actor in stored)
