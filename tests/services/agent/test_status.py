"""`fleet agent status`: where each spooled run stands, read from the spool and the agent's state
whether the agent runs or not (its heartbeat says which), as text and as JSON; a folder that is no
spool is one clear error."""

from __future__ import annotations

import json
import time
import types
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from click.testing import CliRunner

from services.agent import state as state_module
from services.agent.settings import load_agent_settings
from services.agent.spool import Spool
from services.agent.state import AgentState, BagRecord, PullState, RunState
from services.agent.status import STALE_S, status_report
from services.agent.windows import HELD, Window
from services.cli.agent import agent
from services.rrd import iter_events
from services.rules.evaluate import FoundEvent
from services.rules.triggers import TriggerRule
from tests.services.rrd.synthetic import write_recording


@pytest.fixture
def spool_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.delenv("FLEET_CONFIG", raising=False)
    return tmp_path / "spool"


@pytest.fixture
def sizes(spool_dir: Path) -> dict[str, int]:
    """Three closed runs in a spool (then closed, as when the agent has stopped)."""
    spool = Spool(load_agent_settings(agent_spool=spool_dir, agent_min_free_bytes=0))
    spool.recover()
    try:
        for run_id, chunks in (("run-a", 4), ("run-b", 8), ("run-c", 6)):
            path = write_recording(spool_dir.parent / f"{run_id}.rrd", run_id, chunks)
            source = spool.ingest.open_source(live=False)
            for event in iter_events(path):
                spool.ingest.accept(source, event)
            spool.ingest.close_source(source)
        return {run.run_id: run.size for run in spool.runs()}
    finally:
        spool.close()


@pytest.fixture
def state(spool_dir: Path, sizes: dict[str, int]) -> Iterator[AgentState]:
    """What a running agent wrote: run-a confirmed, run-b sent in part with robot-only chunks and
    still open, run-c never started; a pull; the link, counters and progress."""
    state = AgentState(spool_dir)
    state.save_run(RunState("run-a", sizes["run-a"], sizes["run-a"], True, "warm"))
    state.save_run(RunState("run-b", 100, 50, False, "hot", local_only_chunks=2, local_only_bytes=300))
    state.save_pull(PullState("pull-1", "run-b", "sending", {"entities": ["/camera/**"]}, 1, 10))
    state.set_fact("progress", {"run-b": {"sent_until": sizes["run-b"] - 50, "open": True}})
    state.set_fact("link", {"up": False, "since": 1.0, "error": "connection refused", "refused": None})
    state.set_fact("counters", {"messages_sent": 7, "bytes_resent": 0})
    yield state
    state.close()


def beat(state: AgentState, age_s: float) -> None:
    """The running agent's heartbeat, written `age_s` seconds ago."""
    written = time.time() - age_s
    with pytest.MonkeyPatch.context() as clock:
        clock.setattr(state_module, "time", types.SimpleNamespace(time=lambda: written))
        state.set_fact("agent", {"started_at": written, "listen": "127.0.0.1:9876"})


def runs_by_id(report: dict[str, Any]) -> dict[str, dict[str, Any]]:
    return {run["run"]: run for run in report["runs"]}


def test_a_running_agent_and_each_runs_standing(state: AgentState, spool_dir: Path, sizes: dict[str, int]):
    beat(state, 1.0)
    report = status_report(spool_dir)
    assert "error" not in report and report["spool"] == str(spool_dir)
    assert report["running"] is True and 0.5 <= report["heartbeat_age_s"] < STALE_S
    assert report["link"]["error"] == "connection refused" and report["counters"]["messages_sent"] == 7
    assert [run["run"] for run in report["runs"]] == ["run-a", "run-b", "run-c"]
    runs = runs_by_id(report)
    assert runs["run-a"] == {
        "run": "run-a",
        "local_bytes": sizes["run-a"],
        "open": False,
        "sent_bytes": sizes["run-a"],
        "unconfirmed_at_depot_bytes": 0,
        "local_only_chunks": 0,
        "local_only_bytes": 0,
        "depot_tier": "warm",
        "confirmed": True,
    }
    assert runs["run-b"] == {
        "run": "run-b",
        "local_bytes": sizes["run-b"],
        "open": True,
        "sent_bytes": sizes["run-b"] - 50,  # the running sender's progress, ahead of the state row
        "unconfirmed_at_depot_bytes": sizes["run-b"] - 100,  # what the depot is not known to hold
        "local_only_chunks": 2,
        "local_only_bytes": 300,
        "depot_tier": "hot",
        "confirmed": False,
    }
    assert runs["run-c"]["sent_bytes"] == 0 and runs["run-c"]["depot_tier"] is None
    assert runs["run-c"]["unconfirmed_at_depot_bytes"] == sizes["run-c"]
    assert report["spool_bytes"] == sum(sizes.values())
    assert report["backlog_bytes"] == 50 + sizes["run-c"]  # what is left to send of unconfirmed runs
    assert report["pulls"] == [
        {
            "pull_id": "pull-1",
            "run_id": "run-b",
            "state": "sending",
            "spec": {"entities": ["/camera/**"]},
            "chunks_sent": 1,
            "bytes_sent": 10,
        }
    ]


def test_an_old_heartbeat_says_the_agent_stopped(state: AgentState, spool_dir: Path):
    beat(state, STALE_S + 20)
    report = status_report(spool_dir)
    assert report["running"] is False and report["heartbeat_age_s"] >= STALE_S + 20
    assert len(report["runs"]) == 3  # the spool is read all the same


def test_no_heartbeat_at_all_is_not_running(state: AgentState, spool_dir: Path):
    report = status_report(spool_dir)
    assert report["running"] is False and report["heartbeat_age_s"] is None


def test_sent_bytes_never_exceed_what_is_on_the_robot(state: AgentState, spool_dir: Path, sizes: dict[str, int]):
    state.set_fact("progress", {"run-b": {"sent_until": sizes["run-b"] + 10_000, "open": False}})
    assert runs_by_id(status_report(spool_dir))["run-b"]["sent_bytes"] == sizes["run-b"]


def test_a_folder_that_is_no_spool_is_an_error(tmp_path: Path):
    report = status_report(tmp_path)
    assert report["running"] is False
    assert report["error"] == f"no agent state in {tmp_path}: is this the spool?"


# --- the command ----------------------------------------------------------------------------------


def invoke(*args: str, env: dict[str, str] | None = None) -> Any:
    return CliRunner().invoke(agent, ["status", *args], env=env, terminal_width=10_000)


def test_status_prints_the_agent_the_link_and_each_run(state: AgentState, spool_dir: Path, sizes: dict[str, int]):
    beat(state, 1.0)
    result = invoke("--spool", str(spool_dir))
    assert result.exit_code == 0, result.output
    lines = result.stdout.splitlines()
    assert lines[0] == f"agent: running; spool {spool_dir}: {sum(sizes.values())} bytes"
    assert lines[1] == "depot link: down (connection refused)"
    assert lines[2] == f"backlog: {50 + sizes['run-c']} bytes not yet sent"
    assert lines[3] == f"  run-a: {sizes['run-a']} B local, {sizes['run-a']} B sent, confirmed at the depot"
    assert lines[4] == (
        f"  run-b: {sizes['run-b']} B local, {sizes['run-b'] - 50} B sent, {sizes['run-b'] - 100} B unconfirmed, "
        "open, 2 chunks on the robot only"
    )
    assert lines[5] == f"  run-c: {sizes['run-c']} B local, 0 B sent, {sizes['run-c']} B unconfirmed"
    assert len(lines) == 6 and result.stderr == ""


def test_status_of_a_stopped_agent_says_when_it_was_last_seen(state: AgentState, spool_dir: Path):
    beat(state, 60)
    result = invoke("--spool", str(spool_dir))
    assert result.exit_code == 0, result.output
    assert result.stdout.startswith("agent: not running (last seen 6")  # 60.x s ago
    assert " s ago); spool " in result.stdout.splitlines()[0]


def test_status_of_an_agent_never_seen_running_says_so(state: AgentState, spool_dir: Path):
    result = invoke("--spool", str(spool_dir))
    assert result.exit_code == 0, result.output
    first = result.stdout.splitlines()[0]
    assert first.startswith("agent: not running (") and "None" not in first


def test_status_json_is_the_report(state: AgentState, spool_dir: Path):
    beat(state, 1.0)
    result = invoke("--spool", str(spool_dir), "--json")
    assert result.exit_code == 0, result.output
    shown = json.loads(result.stdout)
    report = status_report(spool_dir)
    assert shown["running"] is True
    assert {k: v for k, v in shown.items() if k != "heartbeat_age_s"} == {
        k: v for k, v in report.items() if k != "heartbeat_age_s"
    }


def test_status_reads_the_spool_from_the_environment(state: AgentState, spool_dir: Path):
    result = invoke("--json", env={"FLEET_AGENT_SPOOL": str(spool_dir)})
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["spool"] == str(spool_dir)


def test_status_of_a_folder_that_is_no_spool_is_one_line_and_fails(tmp_path: Path):
    result = invoke("--spool", str(tmp_path))
    assert result.exit_code == 1
    assert result.stdout == ""
    assert result.stderr.splitlines() == [f"Error: no agent state in {tmp_path}: is this the spool?"]
    as_json = invoke("--spool", str(tmp_path), "--json")
    assert as_json.exit_code == 1  # a script reading the JSON learns it failed too
    assert json.loads(as_json.stdout)["error"] == f"no agent state in {tmp_path}: is this the spool?"


def test_the_rules_and_the_trigger_windows(state: AgentState, spool_dir: Path):
    rule = TriggerRule(("hard_brake",), ("/camera/**",))
    window = Window.fire("run-b", FoundEvent("hard_brake", "warn", "t", "sequence", 5, 5, "rule", "x", ""), rule, 2, 0)
    window.state, window.error = HELD, "over budget: 10 bytes would take this trigger to 20 of its 15 a day"
    window.save(state)
    state.set_fact("rules", {"version": 2, "triggers": 1, "refused_version": 3, "refused_why": "line 4: unknown key"})
    report = status_report(spool_dir)
    assert [p["pull_id"] for p in report["pulls"]] == ["pull-1"]  # a window is no person's pull
    assert report["windows"] == [
        {
            "window": window.pull_id,
            "run": "run-b",
            "event": "hard_brake",
            "state": HELD,
            "chunks_sent": 0,
            "bytes_sent": 0,
            "error": window.error,
        }
    ]
    text = CliRunner().invoke(agent, ["status", "--spool", str(spool_dir)]).output
    assert "rules: version 2, 1 triggers; version 3 refused: line 4: unknown key" in text
    assert f"trigger window {window.pull_id} of run-b (hard_brake): held, 0 B sent (over budget:" in text


def test_the_bags_pending_uploaded_and_failed(state: AgentState, spool_dir: Path):
    assert status_report(spool_dir)["bags"] == {
        "pending": 0,
        "uploaded": 0,
        "failed": 0,
        "uploading": None,
        "error": None,
        "failures": [],
    }
    assert "bags:" not in invoke("--spool", str(spool_dir)).stdout  # no line for an agent with no bags
    state.save_bag(BagRecord("/bags/a/a_0.mcap", "a", "rosbag2", 1, 100, 1, "uploaded", "imp-1"))
    state.save_bag(BagRecord("/bags/a/a_1.mcap", "a", "rosbag2", 2, 100, 1, "uploaded", "imp-2"))
    state.save_bag(BagRecord("/bags/x.mcap", "x", "mcap", 3, 10, 1, "failed", error="400 INVALID_ARGUMENT: bad"))
    stopped = status_report(spool_dir)["bags"]  # no running agent has said more: the state file's counts
    assert (stopped["pending"], stopped["uploaded"], stopped["failed"]) == (0, 2, 1)
    assert stopped["failures"] == [{"path": "/bags/x.mcap", "run": "x", "error": "400 INVALID_ARGUMENT: bad"}]
    live = {"pending": 2, "uploaded": 2, "failed": 1, "uploading": "/bags/b/b_0.mcap", "error": "ConnectError"}
    state.set_fact("bags", {**live, "bytes_uploaded": 200, "uploads": 2})
    report = status_report(spool_dir)["bags"]
    assert {k: report[k] for k in live} == live
    lines = invoke("--spool", str(spool_dir)).stdout.splitlines()
    assert lines[-2:] == [
        "bags: 2 pending, 2 uploaded, 1 failed; uploading /bags/b/b_0.mcap; ConnectError",
        "  failed /bags/x.mcap (run x): 400 INVALID_ARGUMENT: bad",
    ]
