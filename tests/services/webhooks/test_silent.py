"""`robot.silent`: a robot whose live run sends nothing for FLEET_SILENT_AFTER_S is told of once
per silence, whether its stream is still open or ingest closed the run for being idle; a robot that
ended its stream is not silent."""

from __future__ import annotations

import datetime as dt
import json
from collections.abc import Iterator
from pathlib import Path

import pytest
from sqlalchemy.orm import Session, sessionmaker

from catalog import webhooks as rows
from catalog.db import session_scope
from services.ingest.service import IngestService
from services.rrd import iter_events
from services.webhooks import service
from services.webhooks.deliver import deliver_due
from services.webhooks.service import Webhooks
from services.webhooks.silent import silent_pass
from tests.services.ingest.feeding import feed
from tests.services.nodes import ingest_of, node_of
from tests.services.retention.conftest import Clock
from tests.services.rrd.recordings import Recording
from tests.services.webhooks.conftest import Receiver

RUN = "rec-points"  # the recording id of the "points" scene


@pytest.fixture
def ingest(catalog: sessionmaker[Session], clock: Clock, tmp_path: Path, hooks: Webhooks) -> Iterator[IngestService]:
    live = ingest_of(node_of(tmp_path / "ingest", catalog, settings=hooks.settings, clock=clock))
    yield live
    live.close()


def test_a_live_run_that_goes_quiet_is_told_of_once(
    hooks: Webhooks,
    ingest: IngestService,
    clock: Clock,
    receiver: Receiver,
    recordings: dict[str, Recording],
):
    added = service.add_webhook(hooks, receiver.url, ["robot.silent"], "json", "alice")
    source = ingest.open_source(live=True, robot="robot-7")
    feed(ingest, source, iter_events(recordings["points"].path))
    last_data = clock()
    assert silent_pass(hooks, ingest.hot_runs()) == 0  # it just sent data
    clock.advance(seconds=hooks.settings.silent_after_s - 1)
    assert silent_pass(hooks, ingest.hot_runs()) == 0
    clock.advance(seconds=1)
    assert silent_pass(hooks, ingest.hot_runs()) == 1
    assert silent_pass(hooks, ingest.hot_runs()) == 0  # the same silence: told once
    assert ingest.close_idle() == [RUN]  # closed for being idle, its stream still open: still that silence
    clock.advance(seconds=600)
    assert silent_pass(hooks, ingest.hot_runs()) == 0
    deliver_due(hooks)
    (got,) = receiver.got
    body = json.loads(got.body)
    assert body["occurrence"] == "robot.silent" and body["id"].startswith(f"{RUN}@")
    assert (body["run_id"], body["robot_id"], body["silent_s"]) == (RUN, "robot-7", hooks.settings.silent_after_s)
    assert body["last_data_at"] == last_data.isoformat().replace("+00:00", "Z")
    assert len(service.deliveries_answer(hooks, added["id"], 10, None)["deliveries"]) == 1


def test_a_robot_that_ended_its_stream_is_not_silent(
    hooks: Webhooks, ingest: IngestService, clock: Clock, receiver: Receiver, recordings: dict[str, Recording]
):
    service.add_webhook(hooks, receiver.url, ["robot.silent"], "json", "alice")
    source = ingest.open_source(live=True)
    feed(ingest, source, iter_events(recordings["points"].path))
    ingest.close_source(source)  # the run is over
    clock.advance(seconds=hooks.settings.silent_after_s * 2)
    assert [r.run_id for r in ingest.hot_runs()] == [RUN]
    assert silent_pass(hooks, ingest.hot_runs()) == 0


def test_a_run_closed_for_being_idle_whose_stream_then_broke_is_silent(
    hooks: Webhooks, ingest: IngestService, clock: Clock, receiver: Receiver, recordings: dict[str, Recording]
):
    service.add_webhook(hooks, receiver.url, ["robot.silent"], "json", "alice")
    source = ingest.open_source(live=True)
    feed(ingest, source, iter_events(recordings["points"].path))
    clock.advance(seconds=hooks.settings.close_after_s)
    assert ingest.close_idle() == [RUN]
    ingest.close_source(source)  # the connection dropped later
    clock.advance(seconds=hooks.settings.silent_after_s)
    assert silent_pass(hooks, ingest.hot_runs()) == 1
    assert silent_pass(hooks, ingest.hot_runs()) == 0
    with session_scope(hooks.catalog) as session:
        (delivery,) = rows.claim_due(session, clock(), limit=10, hold=dt.timedelta(0))
    assert json.loads(delivery.body)["robot_id"] == hooks.default_robot  # a run that names no robot
