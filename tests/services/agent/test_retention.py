"""Retention on the robot: a spooled run goes only once the depot confirmed it, at its age or under
size pressure (oldest first, runs holding robot-only chunks last); what nothing can free is reported,
never deleted. Time is given (`now=`, runs' `last_data_at`), not waited for."""

from __future__ import annotations

import datetime as dt
import logging
from collections.abc import Iterator
from pathlib import Path

import pytest

from services.agent.retention import RetentionReport, enforce
from services.agent.settings import load_agent_settings
from services.agent.spool import RUNS_DIR, Spool
from services.agent.state import AgentState, RunState
from services.rrd import iter_events
from tests.services.rrd.synthetic import write_recording

NOW = dt.datetime(2025, 6, 1, 12, 0, tzinfo=dt.UTC)
DAY = dt.timedelta(hours=24)


@pytest.fixture
def spool(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Spool]:
    monkeypatch.delenv("FLEET_CONFIG", raising=False)
    spool = Spool(load_agent_settings(agent_spool=tmp_path / "spool", agent_min_free_bytes=0))
    spool.recover()
    yield spool
    spool.close()


@pytest.fixture
def state(spool: Spool) -> Iterator[AgentState]:
    state = AgentState(spool.root)
    yield state
    state.close()


def add_run(spool: Spool, run_id: str, age: dt.timedelta, chunks: int = 6) -> int:
    """A closed run whose last data came `age` before NOW; returns its size."""
    path = write_recording(spool.root.parent / f"{run_id}.rrd", run_id, chunks)
    source = spool.ingest.open_source(live=False)
    for event in iter_events(path):
        spool.ingest.accept(source, event)
    spool.ingest.close_source(source)
    run = spool.run(run_id)
    assert run is not None and not spool.is_open(run)
    spool.ingest.runs[run_id].last_data_at = NOW - age  # its age, as ingest holds it
    return run.size


def confirm(state: AgentState, run_id: str, local_only_bytes: int = 0) -> None:
    chunks = 1 if local_only_bytes else 0
    state.save_run(RunState(run_id, 10**9, 10**9, True, "warm", chunks, local_only_bytes))


def on_disk(spool: Spool) -> set[str]:
    return {p.name for p in (spool.root / RUNS_DIR).iterdir() if not p.name.startswith(".")}


def keep(spool: Spool, state: AgentState, max_bytes: int = 0, retain: dt.timedelta = DAY) -> RetentionReport:
    return enforce(spool, state, retain=retain, max_bytes=max_bytes, now=NOW)


def test_unconfirmed_runs_are_never_deleted(spool: Spool, state: AgentState):
    sizes = {run_id: add_run(spool, run_id, dt.timedelta(days=30)) for run_id in ("run-a", "run-b")}
    state.save_run(RunState("run-a", checked_until=500, confirmed_until=100))  # sent in part, not confirmed
    total = sum(sizes.values())
    report = keep(spool, state)  # far older than a day
    assert report.deleted == [] and on_disk(spool) == {"run-a", "run-b"}
    assert report.spool_bytes == report.unconfirmed_bytes == total and report.over_by == 0
    report = keep(spool, state, max_bytes=1000)  # and far over the cap
    assert report.deleted == [] and on_disk(spool) == {"run-a", "run-b"}
    assert report.over_by == total - 1000
    assert set(state.runs()) == {"run-a"}


def test_confirmed_runs_go_at_their_age_and_their_state_with_them(spool: Spool, state: AgentState):
    old = add_run(spool, "run-old", dt.timedelta(hours=30))
    add_run(spool, "run-edge", DAY)  # exactly the retention: goes
    add_run(spool, "run-young", dt.timedelta(hours=23))
    add_run(spool, "run-unconfirmed", dt.timedelta(hours=40))
    for run_id in ("run-old", "run-edge", "run-young"):
        confirm(state, run_id)
    state.save_run(RunState("run-unconfirmed", 100))
    report = keep(spool, state)
    assert [(d.run_id, d.why) for d in report.deleted] == [("run-old", "age"), ("run-edge", "age")]  # oldest first
    assert report.deleted[0].bytes == old and report.deleted[0].local_only_bytes == 0
    assert on_disk(spool) == {"run-young", "run-unconfirmed"}
    assert {r.run_id for r in spool.runs()} == {"run-young", "run-unconfirmed"}
    assert set(state.runs()) == {"run-young", "run-unconfirmed"}
    assert report.spool_bytes == spool.size() and report.over_by == 0


def test_confirmed_runs_with_robot_only_chunks_go_at_their_age_too(
    spool: Spool, state: AgentState, caplog: pytest.LogCaptureFixture
):
    add_run(spool, "run-kept-chunks", dt.timedelta(days=2))
    confirm(state, "run-kept-chunks", local_only_bytes=4096)
    with caplog.at_level(logging.WARNING, logger="fleet.agent"):
        report = keep(spool, state)
    assert [(d.run_id, d.local_only_bytes) for d in report.deleted] == [("run-kept-chunks", 4096)]
    assert "4096 bytes kept on the robot only" in caplog.text


def test_size_pressure_deletes_oldest_confirmed_first_and_robot_only_chunks_last(spool: Spool, state: AgentState):
    hour = dt.timedelta(hours=1)
    sizes = {
        "run-1-local-only": add_run(spool, "run-1-local-only", 9 * hour),  # the oldest, but holds robot-only chunks
        "run-2": add_run(spool, "run-2", 8 * hour),
        "run-3": add_run(spool, "run-3", 7 * hour),
        "run-4": add_run(spool, "run-4", 6 * hour),
        "run-5-unconfirmed": add_run(spool, "run-5-unconfirmed", 10 * hour),
    }
    confirm(state, "run-1-local-only", local_only_bytes=100)
    for run_id in ("run-2", "run-3", "run-4"):
        confirm(state, run_id)
    total = sum(sizes.values())
    cap = total - sizes["run-2"] - sizes["run-3"] // 2  # two runs must go
    report = keep(spool, state, max_bytes=cap)
    assert [(d.run_id, d.why) for d in report.deleted] == [("run-2", "size"), ("run-3", "size")]
    assert on_disk(spool) == {"run-1-local-only", "run-4", "run-5-unconfirmed"}
    assert report.spool_bytes == spool.size() <= cap and report.over_by == 0

    cap = sizes["run-5-unconfirmed"] + sizes["run-1-local-only"]  # run-4 goes before the robot-only chunks
    report = keep(spool, state, max_bytes=cap)
    assert [d.run_id for d in report.deleted] == ["run-4"]
    report = keep(spool, state, max_bytes=cap - 1)  # now only they can go
    assert [(d.run_id, d.local_only_bytes) for d in report.deleted] == [("run-1-local-only", 100)]
    assert on_disk(spool) == {"run-5-unconfirmed"} and set(state.runs()) == set()


def test_over_the_cap_with_only_unconfirmed_runs_left_is_reported(
    spool: Spool, state: AgentState, caplog: pytest.LogCaptureFixture
):
    confirmed = add_run(spool, "run-confirmed", dt.timedelta(hours=2))
    unconfirmed = add_run(spool, "run-unconfirmed", dt.timedelta(hours=1), chunks=12)
    confirm(state, "run-confirmed")
    cap = unconfirmed // 2
    with caplog.at_level(logging.WARNING, logger="fleet.agent"):
        report = keep(spool, state, max_bytes=cap)
    assert [d.run_id for d in report.deleted] == ["run-confirmed"] and report.deleted[0].bytes == confirmed
    assert on_disk(spool) == {"run-unconfirmed"}
    assert report.spool_bytes == report.unconfirmed_bytes == unconfirmed
    assert report.over_by == unconfirmed - cap
    assert f"needs {unconfirmed - cap} bytes freed" in caplog.text and "agent_max_bytes" in caplog.text


def test_running_again_is_harmless(spool: Spool, state: AgentState):
    add_run(spool, "run-old", dt.timedelta(days=2))
    young = add_run(spool, "run-young", dt.timedelta(hours=1))
    confirm(state, "run-old")
    confirm(state, "run-young")
    first = keep(spool, state, max_bytes=young * 10)
    assert [d.run_id for d in first.deleted] == ["run-old"]
    for _ in range(2):
        again = keep(spool, state, max_bytes=young * 10)
        assert again == RetentionReport([], young, 0, 0)
    assert on_disk(spool) == {"run-young"} and set(state.runs()) == {"run-young"}


def test_a_run_still_fed_is_kept_even_if_confirmed(spool: Spool, state: AgentState, tmp_path: Path):
    path = write_recording(tmp_path / "growing.rrd", "run-growing", 5)
    spool.file_events(path, list(iter_events(path)))  # a watched file still being read
    run = spool.run("run-growing")
    assert run is not None and spool.is_open(run)
    spool.ingest.runs["run-growing"].last_data_at = NOW - dt.timedelta(days=3)
    confirm(state, "run-growing")
    report = keep(spool, state, max_bytes=1)
    assert report.deleted == [] and on_disk(spool) == {"run-growing"}
    spool.file_done(path)
    assert [d.run_id for d in keep(spool, state).deleted] == ["run-growing"]


def test_a_run_that_cannot_be_removed_is_not_counted_as_deleted(
    spool: Spool, state: AgentState, monkeypatch: pytest.MonkeyPatch
):
    """A run something feeds again between the look and the removal stays, and the sizes reported
    are those of the spool as it is."""
    for i, run_id in enumerate(("run-a", "run-b", "run-c")):
        add_run(spool, run_id, dt.timedelta(hours=5 - i))
        confirm(state, run_id)
    remove = spool.remove
    monkeypatch.setattr(spool, "remove", lambda run_id: False if run_id == "run-a" else remove(run_id))
    report = keep(spool, state, max_bytes=1)
    assert [d.run_id for d in report.deleted] == ["run-b", "run-c"]
    assert on_disk(spool) == {"run-a"} and "run-a" in state.runs()
    assert report.spool_bytes == spool.size()
    assert report.over_by == spool.size() - 1


def test_a_nearly_full_disk_frees_confirmed_runs_oldest_first_and_never_the_rest(spool: Spool, state: AgentState):
    sizes = {run_id: add_run(spool, run_id, dt.timedelta(minutes=m)) for run_id, m in (("old", 30), ("new", 10))}
    add_run(spool, "unsent", dt.timedelta(minutes=50))
    confirm(state, "old")
    confirm(state, "new")
    free = 1000

    def disk_free() -> int:
        return free

    # a little short of the target: the oldest confirmed run is enough
    report = enforce(
        spool, state, retain=DAY, max_bytes=0, now=NOW, free_target=free + sizes["old"] - 1, disk_free=disk_free
    )
    assert [d.run_id for d in report.deleted] == ["old"] and report.deleted[0].why == "disk"
    assert on_disk(spool) == {"new", "unsent"} and report.over_by == 0
    # far short: every confirmed run goes, the unconfirmed one stays and the shortfall is said
    report = enforce(spool, state, retain=DAY, max_bytes=0, now=NOW, free_target=10**12, disk_free=disk_free)
    assert [d.run_id for d in report.deleted] == ["new"]
    assert on_disk(spool) == {"unsent"} and report.over_by == 10**12 - free - sizes["new"]


def test_a_run_holding_a_trigger_window_the_depot_lacks_is_kept(spool: Spool, state: AgentState):
    add_run(spool, "run-window", DAY * 2)
    add_run(spool, "run-plain", DAY * 2)
    confirm(state, "run-window")
    confirm(state, "run-plain")
    report = enforce(spool, state, retain=DAY, max_bytes=1, now=NOW, keep={"run-window"})  # old and over the cap
    assert [d.run_id for d in report.deleted] == ["run-plain"]
    assert on_disk(spool) == {"run-window"}
    report = enforce(spool, state, retain=DAY, max_bytes=1, now=NOW)  # the window reached the depot
    assert [d.run_id for d in report.deleted] == ["run-window"]
