"""A hot run as other services see it (a frozen `HotRunView`), and the one way it leaves the hot tier
(`IngestService.hand_over`): refused if the run changed since the caller looked, else the caller's
commit under the run's lock, then forgotten and its folder set aside."""

from __future__ import annotations

import dataclasses
import datetime as dt
from collections.abc import Iterator
from pathlib import Path

import pytest

from core.errors import ConflictError
from core.states import RunStatus, Tier
from services.cluster.ownership import Lease
from services.facts.sealed import SealedInfo
from services.ingest.service import IngestService
from services.ingest.view import HotRunView
from tests.services.ingest.factory import ingest_service
from tests.services.rrd.synthetic import chunk_id, recording_events, write_recording

RUN = "run-hand-over"


@pytest.fixture
def ingest(tmp_path: Path) -> Iterator[IngestService]:
    service = ingest_service(tmp_path, default_robot="robot", max_streams=4)
    yield service
    service.hot.close()


def feed(ingest: IngestService, path: Path, *, live: bool = False) -> None:
    source = ingest.open_source(live=live)
    for event in recording_events(path):
        ingest.accept(source, event)
    ingest.close_source(source)


def hot_run(ingest: IngestService) -> HotRunView:
    run = ingest.hot_run(RUN)
    assert run is not None
    return run


def test_a_view_is_a_frozen_copy_of_the_run(ingest: IngestService, tmp_path: Path):
    feed(ingest, write_recording(tmp_path / "six.rrd", RUN, 6))
    view = hot_run(ingest)
    assert view.status == RunStatus.CLOSED and view.size == view.path.stat().st_size
    assert view.chunk_ids == {chunk_id(RUN, i) for i in range(6)}  # copied now, kept from here on
    with pytest.raises(dataclasses.FrozenInstanceError):
        view.status = RunStatus.LIVE  # type: ignore[misc]

    feed(ingest, write_recording(tmp_path / "nine.rrd", RUN, 9))  # three chunks more
    now = hot_run(ingest)
    assert now.size == now.path.stat().st_size > view.size  # the view keeps the size it was taken with
    assert len(view.chunk_ids) == 6 and len(now.chunk_ids) == 9 and now.chunks > view.chunks
    assert view.in_hot_file(chunk_id(RUN, 8))  # asked of the run as it is, without a copy
    assert [run.run_id for run in ingest.closed_runs()] == [RUN]


def test_a_hand_over_is_refused_while_the_run_changes_and_done_once(ingest: IngestService, tmp_path: Path):
    nine = write_recording(tmp_path / "nine.rrd", RUN, 9)
    feed(ingest, write_recording(tmp_path / "six.rrd", RUN, 6))
    stale = hot_run(ingest)
    feed(ingest, nine)
    with pytest.raises(ConflictError, match=f"run {RUN} received data while being checked: checked later"):
        ingest.hand_over(stale, doing="being checked", then="checked later")

    source = ingest.open_source(live=True)  # a stream replaying chunks held: closed, but fed
    for event in recording_events(nine):
        ingest.accept(source, event)
    fed = hot_run(ingest)
    assert fed.status == RunStatus.CLOSED and fed.live_sources == 1 and fed.size == hot_run(ingest).size
    with pytest.raises(ConflictError, match="received data while being sealed: promoted later"):
        ingest.hand_over(fed, lambda _: None, doing="being sealed", then="promoted later")
    ingest.close_source(source)

    run = hot_run(ingest)

    def failing(_: Lease | None) -> SealedInfo | None:
        raise RuntimeError("the catalog said no")

    with pytest.raises(RuntimeError):
        ingest.hand_over(run, failing, doing="being sealed", then="promoted later")
    assert not ingest.has_left(run) and ingest.hot_run(RUN) is not None and run.path.is_file()

    went = SealedInfo(Tier.WARM, f"robot/2024-01-01/{RUN}", "robot", dt.date(2024, 1, 1), run.chunk_ids)
    leases: list[Lease | None] = []

    def commit(lease: Lease | None) -> SealedInfo:
        leases.append(lease)
        assert ingest.hot_run(RUN) is not None  # under the lock, before the run is forgotten
        return went

    left = ingest.hand_over(run, commit, doing="being sealed", then="promoted later")
    assert leases == [None] and left.lease is None and left.folder.is_dir() and not run.path.exists()
    assert ingest.has_left(run) and ingest.hot_run(RUN) is None and ingest.recently_sealed[RUN] is went
    with pytest.raises(ConflictError, match="left the hot tier while being sealed"):
        ingest.hand_over(run, commit, doing="being sealed", then="promoted later")
    assert leases == [None]  # the commit ran once


def test_leases_are_set_through_ingest(ingest: IngestService, tmp_path: Path):
    feed(ingest, write_recording(tmp_path / "six.rrd", RUN, 6))
    ingest.flush_catalog()  # nothing dirty from here
    lease = Lease(RUN, 3)
    ingest.take_lease(RUN, lease)
    assert hot_run(ingest).lease == lease and ingest.runs[RUN].dirty  # its catalog row is written next
    ingest.lose_lease(RUN)
    assert hot_run(ingest).lease is None
    ingest.take_lease("run-elsewhere", Lease("run-elsewhere", 1))  # not hot here: nothing to own
    assert ingest.hot_run("run-elsewhere") is None
