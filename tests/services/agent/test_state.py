"""The agent's SQLite state: runs, watched files, pulls and facts written and read back, updated in
place, forgotten, kept across a reopening, and read by a second, read-only handle while the agent
holds the file."""

from __future__ import annotations

import sqlite3
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from services.agent.state import STATE_FILE, AgentState, BagRecord, PullState, RunState, run_state_dict


@pytest.fixture
def spool(tmp_path: Path) -> Path:
    return tmp_path / "spool"


@pytest.fixture
def state(spool: Path) -> Iterator[AgentState]:
    opened = AgentState(spool)
    yield opened
    opened.close()


def test_a_new_state_makes_its_folder_and_file_and_is_empty(state: AgentState, spool: Path):
    assert (spool / STATE_FILE).is_file()
    assert state.runs() == {} and state.file_progress() == {} and state.pulls() == {} and state.facts() == {}
    assert state.bags() == {}


def test_runs_round_trip_and_upsert(state: AgentState):
    first = RunState("run-a", checked_until=1000, confirmed_until=500, depot_tier="hot")
    other = RunState("run-b", 7, 7, True, "warm", local_only_chunks=3, local_only_bytes=4096)
    state.save_run(first)
    state.save_run(other)
    assert state.runs() == {"run-a": first, "run-b": other}
    moved = RunState("run-a", 2000, 1500, True, "warm", local_only_chunks=1, local_only_bytes=10)
    state.save_run(moved)  # the same run again: updated in place, not added
    assert state.runs() == {"run-a": moved, "run-b": other}
    assert isinstance(state.runs()["run-b"].confirmed, bool)
    assert run_state_dict(moved) == {
        "run_id": "run-a",
        "checked_until": 2000,
        "confirmed_until": 1500,
        "confirmed": True,
        "depot_tier": "warm",
        "local_only_chunks": 1,
        "local_only_bytes": 10,
    }


def test_forget_run_removes_that_run_only(state: AgentState):
    state.save_run(RunState("run-a", 1))
    state.save_run(RunState("run-b", 2))
    state.forget_run("run-a")
    assert list(state.runs()) == ["run-b"]
    state.forget_run("run-a")  # forgetting what is not there is harmless
    assert list(state.runs()) == ["run-b"]


def test_files_round_trip_upsert_and_forget(state: AgentState):
    progress = {"path": "/var/spool/robot/a.rrd", "offset": 4096, "phase": "messages", "inode": 12}
    state.save_file("/var/spool/robot/a.rrd", progress)
    state.save_file("/var/spool/robot/b.rrd", {"offset": 12})
    assert state.file_progress()["/var/spool/robot/a.rrd"] == progress
    state.save_file("/var/spool/robot/a.rrd", {**progress, "offset": 8192, "phase": "done"})
    assert state.file_progress() == {
        "/var/spool/robot/a.rrd": {**progress, "offset": 8192, "phase": "done"},
        "/var/spool/robot/b.rrd": {"offset": 12},
    }
    state.forget_file("/var/spool/robot/b.rrd")
    assert list(state.file_progress()) == ["/var/spool/robot/a.rrd"]


def test_pulls_round_trip_and_upsert_keeps_their_spec(state: AgentState):
    spec = {"entities": ["/camera/**"], "from_ns": 1, "to_ns": 2}
    pull = PullState("pull-1", "run-a", "pending", spec)
    state.save_pull(pull)
    state.save_pull(PullState("pull-2", "run-b", "sending", {}, chunks_sent=4, bytes_sent=400))
    assert state.pulls()["pull-1"] == pull
    progressed = PullState("pull-1", "run-a", "sending", spec, chunks_sent=2, bytes_sent=2048)
    state.save_pull(progressed)
    assert state.pulls() == {
        "pull-1": progressed,
        "pull-2": PullState("pull-2", "run-b", "sending", {}, 4, 400),
    }
    state.forget_pull("pull-1")
    assert list(state.pulls()) == ["pull-2"]


def test_bags_remember_what_was_sent_or_refused_upsert_and_forget(state: AgentState):
    sent = BagRecord("/bags/b/b_0.mcap", "b", "rosbag2", 12, 4096, 1_700_000_000_123_456_789, "uploaded", "imp-1")
    refused = BagRecord("/bags/x.mcap", "x", "mcap", 13, 10, 5, "failed", error="400 INVALID_ARGUMENT: bad")
    state.save_bag(sent)
    state.save_bag(refused)
    assert state.bags() == {sent.path: sent, refused.path: refused}  # nanoseconds kept whole
    grown = BagRecord(sent.path, "b", "rosbag2", 12, 8192, 1_700_000_100_000_000_000, "uploaded", "imp-2")
    state.save_bag(grown)  # the file grew and was sent again: the row is replaced
    retried = BagRecord(refused.path, "x", "mcap", 14, 20, 6, "uploaded", "imp-3")
    state.save_bag(retried)  # a refused file that changed and was taken: no error left
    assert state.bags() == {sent.path: grown, refused.path: retried}
    state.forget_bag(sent.path)
    state.forget_bag(sent.path)  # forgetting what is not there is harmless
    assert list(state.bags()) == [refused.path]


def test_a_readonly_handle_on_a_state_without_bags_has_none(spool: Path):
    spool.mkdir()
    db = sqlite3.connect(spool / STATE_FILE)  # what an agent from before bags wrote
    db.execute("CREATE TABLE facts (key TEXT PRIMARY KEY, value TEXT NOT NULL, updated_at REAL NOT NULL)")
    db.commit()
    db.close()
    reader = AgentState(spool, readonly=True)
    try:
        assert reader.bags() == {}
    finally:
        reader.close()
    writer = AgentState(spool)  # the new agent adds the table on start
    try:
        writer.save_bag(BagRecord("/a.mcap", "a", "mcap", 1, 2, 3, "uploaded"))
        assert list(writer.bags()) == ["/a.mcap"]
    finally:
        writer.close()


def test_facts_hold_any_json_value_with_when_it_was_written(state: AgentState):
    before = time.time()
    state.set_fact("link", {"up": False, "error": "connection refused", "refused": None})
    state.set_fact("counters", {"messages_sent": 3})
    state.set_fact("counters", {"messages_sent": 5})  # replaced, not added
    after = time.time()
    facts = state.facts()
    assert set(facts) == {"link", "counters"}
    assert facts["link"][0] == {"up": False, "error": "connection refused", "refused": None}
    assert facts["counters"][0] == {"messages_sent": 5}
    assert all(before <= at <= after for _, at in facts.values())


def test_the_state_survives_reopening(spool: Path):
    state = AgentState(spool)
    run = RunState("run-a", 100, 50, False, "hot", 2, 20)
    pull = PullState("pull-1", "run-a", "done", {"entities": ["/a"]}, 1, 10)
    state.save_run(run)
    state.save_file("/f.rrd", {"offset": 99})
    state.save_pull(pull)
    state.set_fact("agent", {"started_at": 1.0})
    bag = BagRecord("/bags/a.mcap", "a", "mcap", 1, 2, 3, "uploaded", "imp-1")
    state.save_bag(bag)
    state.close()
    reopened = AgentState(spool)  # a restart: the schema is there already
    try:
        assert reopened.bags() == {bag.path: bag}
        assert reopened.runs() == {"run-a": run}
        assert reopened.file_progress() == {"/f.rrd": {"offset": 99}}
        assert reopened.pulls() == {"pull-1": pull}
        assert reopened.facts()["agent"][0] == {"started_at": 1.0}
    finally:
        reopened.close()


def test_a_readonly_handle_reads_while_the_agent_holds_the_state(state: AgentState, spool: Path):
    state.save_run(RunState("run-a", 10))
    reader = AgentState(spool, readonly=True)
    try:
        assert list(reader.runs()) == ["run-a"]
        state.save_run(RunState("run-b", 20))  # the agent writes on while the reader is open
        state.set_fact("agent", {"started_at": 2.0})
        assert set(reader.runs()) == {"run-a", "run-b"}  # each write is committed at once
        assert reader.facts()["agent"][0] == {"started_at": 2.0}
        with pytest.raises(sqlite3.OperationalError, match="readonly"):
            reader.save_run(RunState("run-c"))  # and it cannot change anything
    finally:
        reader.close()
    assert set(state.runs()) == {"run-a", "run-b"}


def test_a_readonly_handle_makes_no_file(tmp_path: Path):
    with pytest.raises(sqlite3.OperationalError):
        AgentState(tmp_path / "nowhere", readonly=True).runs()
    assert not (tmp_path / "nowhere").exists()
