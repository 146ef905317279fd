"""The agent's triggers in one process: a recording of the real SDK filed into the spool (as a watched
file is), the rules evaluated over it, windows fired once per event and trigger, started within the
day's budget and reported. The depot is a stand-in here that lacks every chunk and records what it
is told (the end-to-end test in test_triggers.py runs the real one)."""

from __future__ import annotations

import asyncio
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import rerun as rr

from services.agent.bandwidth import Priority
from services.agent.link import Held
from services.agent.pulls import PullSpec
from services.agent.service import Agent
from services.agent.settings import load_agent_settings
from services.agent.windows import DONE, FAILED, HELD, SENDING
from services.rrd.decoder import iter_events

FRAME_NS = 100_000_000
START_NS = 1_790_000_000_000_000_000
RULES = """
[[event]]
name = "hard_brake"
entity = "/metrics/brake"
when = "rises_above"
threshold = 5.0
timeline = "sim_time"

[[trigger]]
event = "hard_brake"
include = ["/camera/**"]
before_s = 1
after_s = 1
max_bytes_per_robot_day = BUDGET
priority = "high"
"""


def drive(path: Path, frames: int, brakes: set[int]) -> None:
    rec = rr.RecordingStream("trigger_unit", recording_id="run-unit")
    rec.save(str(path))
    rec.send_property("fleet", rr.AnyValues(robot_id="robot-unit"))
    for i in range(frames):
        rec.set_time("sim_time", timestamp=np.datetime64(START_NS + i * FRAME_NS, "ns"))
        rec.log("/camera/front", rr.Image(np.full((8, 8, 3), i % 255, dtype=np.uint8)))
        rec.log("/metrics/brake", rr.Scalars([9.0 if i in brakes else 0.5]))
        rec.flush(timeout_sec=10)
    rec.disconnect()


class Depot:
    """What the agent's link is asked: every chunk is missing; reports are kept."""

    def __init__(self) -> None:
        self.reports: list[dict[str, Any]] = []

    async def held(self, run_id: str, chunk_ids: list[bytes]) -> Held:
        return Held("hot", "live", True, set(chunk_ids), set(), "node-1")

    async def call(self, fn: Any, *args: Any, **kwargs: Any) -> Any:
        self.reports.append(args[1])
        return {"pull": {"id": args[1]["pull_id"]}, "event": {"id": "ev-" + args[1]["pull_id"][5:]}}

    @property
    def api(self) -> Any:
        class Api:
            report_triggered = "report_triggered"

        return Api()


@pytest.fixture
def agent(tmp_path: Path) -> Iterator[Agent]:
    loop = asyncio.new_event_loop()  # the agent's gRPC channel belongs to a loop
    asyncio.set_event_loop(loop)
    made = Agent(load_agent_settings(agent_spool=tmp_path / "spool", agent_min_free_bytes=0))
    made.spool.recover()
    yield made
    made.spool.close()
    made.state.close()
    asyncio.set_event_loop(None)
    loop.close()


def file_drive(agent: Agent, path: Path) -> None:
    agent.spool.file_events(path, list(iter_events(path)))
    agent.spool.file_done(path)


@pytest.mark.parametrize("budget", [10**9, 1])
def test_each_brake_fires_one_window_sent_within_its_budget(agent: Agent, tmp_path: Path, budget: int):
    agent.rules.take({"version": 1, "text": RULES.replace("BUDGET", str(budget))})
    depot = Depot()
    agent.link = depot  # type: ignore[assignment]
    started: list[Any] = []
    agent.sender_for = lambda run_id: type("S", (), {"add_pull": started.append})()  # type: ignore[method-assign]
    path = tmp_path / "drive.rrd"
    drive(path, 60, {20, 40})
    file_drive(agent, path)

    async def ticks() -> None:
        for _ in range(3):
            await agent.triggers.tick()

    run = asyncio.get_event_loop().run_until_complete
    run(ticks())
    windows = sorted(agent.triggers.windows.values(), key=lambda w: w.start)
    assert [w.event["start"] for w in windows] == [START_NS + 20 * FRAME_NS, START_NS + 40 * FRAME_NS]
    assert [(w.start, w.end) for w in windows] == [
        (w.event["start"] - 10 * FRAME_NS, w.event["end"] + 10 * FRAME_NS) for w in windows
    ]
    if budget > 1:
        assert [w.state for w in windows] == [SENDING, SENDING]
        assert [job.pull_id for job in started] == [w.pull_id for w in windows]
        frames = [e.meta.entity_path for e in started[0].entries if e.meta is not None]
        assert set(frames) == {"/camera/front", "/__properties", "/__properties/fleet"}  # properties, as pulls
        assert 22 <= frames.count("/camera/front") <= 23  # 10..31, and the newest before its start
    else:
        assert [w.state for w in windows] == [HELD, HELD] and not started
        assert all("over budget" in (w.error or "") for w in windows)
    told = {r["pull_id"]: r for r in depot.reports}
    assert set(told) == {w.pull_id for w in windows}
    assert {r["event"]["kind"] for r in told.values()} == {"hard_brake"}
    assert agent.triggers.counters["fired"] == 2
    # evaluated again (the same run filed again, say): no new windows
    file_drive(agent, path)
    run(agent.triggers.tick())
    assert len(agent.triggers.windows) == 2
    assert agent.triggers.protected_runs() == {"run-unit"}
    for window in windows:
        if window.state == SENDING:
            job = agent.triggers.jobs[window.pull_id]
            job.done.set()
    run(agent.triggers.tick())
    if budget > 1:
        assert {w.state for w in agent.triggers.windows.values()} == {DONE}
        assert agent.triggers.protected_runs() == set()
    else:  # a person dismisses one held window at the depot (cancels its pull): no longer kept
        reported = len(depot.reports)
        agent.triggers.dismissed({windows[0].pull_id})
        assert [w.state for w in windows] == [FAILED, HELD]
        assert agent.triggers.held_pulls() == {windows[1].pull_id}
        agent.triggers.dismissed({w.pull_id for w in windows})
        assert agent.triggers.protected_runs() == set()
        run(agent.triggers.tick())
        assert len(depot.reports) == reported  # the depot cancelled them: nothing to tell it


class Progress(Depot):
    """The stand-in depot, also taking pull progress reports."""

    def __init__(self) -> None:
        super().__init__()
        self.progress: list[tuple[str, str]] = []

    async def call(self, fn: Any, *args: Any, **kwargs: Any) -> Any:
        if fn == "pull_progress":
            self.progress.append((args[0], kwargs["state"]))
            return {}
        return await super().call(fn, *args, **kwargs)

    @property
    def api(self) -> Any:
        class Api:
            report_triggered = "report_triggered"
            pull_progress = "pull_progress"

        return Api()


def one_brake(agent: Agent, tmp_path: Path) -> tuple[Progress, list[Any]]:
    """A drive with one brake filed into the spool; the stand-in depot, and the jobs senders get."""
    depot = Progress()
    agent.link = depot  # type: ignore[assignment]
    started: list[Any] = []
    agent.sender_for = lambda run_id: type("S", (), {"add_pull": started.append})()  # type: ignore[method-assign]
    path = tmp_path / "drive.rrd"
    drive(path, 60, {20})
    file_drive(agent, path)
    return depot, started


def test_a_window_the_depot_fired_is_sent_and_its_pull_told(agent: Agent, tmp_path: Path):
    """An agent without the rules yet (they changed at the depot a moment ago): the depot's live rules
    found the brake in the summary and queued its window; the agent serves it as a window."""
    depot, started = one_brake(agent, tmp_path)
    start, end = START_NS + 10 * FRAME_NS, START_NS + 31 * FRAME_NS
    pull = {
        "id": "pull-00000000d3a0",
        "run_id": "run-unit",
        "include": ["/camera/**"],
        "timeline": "sim_time",
        "start": str(start),
        "end": str(end),
        "origin": "trigger",
        "priority": "high",
        "event_id": "ev-0000000000000001",
    }
    agent.triggers.take_depot_pull(PullSpec.of(pull))
    agent.triggers.take_depot_pull(PullSpec.of(pull))  # polled again: the same window
    run = asyncio.get_event_loop().run_until_complete
    run(agent.triggers.tick())
    (window,) = agent.triggers.windows.values()
    assert window.from_depot and (window.start, window.end) == (start, end) and window.state == SENDING
    assert [job.pull_id for job in started] == ["pull-00000000d3a0"]
    assert started[0].priority == Priority.TRIGGER
    assert depot.reports == []  # no event to file: the depot found it
    assert depot.progress == [("pull-00000000d3a0", "sending")]
    started[0].done.set()
    run(agent.triggers.tick())
    assert depot.progress[-1] == ("pull-00000000d3a0", "done") and window.state == DONE


def test_a_depot_pull_of_a_window_the_robot_fired_sends_nothing_more(agent: Agent, tmp_path: Path):
    agent.rules.take({"version": 1, "text": RULES.replace("BUDGET", "1000000000")})
    depot, started = one_brake(agent, tmp_path)
    run = asyncio.get_event_loop().run_until_complete
    run(agent.triggers.tick())
    (mine,) = agent.triggers.windows.values()
    overlapping = {  # the depot's own window of the same brake (its live rules found it too)
        "id": "pull-00000000beef",
        "run_id": "run-unit",
        "include": ["/camera/**"],
        "timeline": "sim_time",
        "start": str(mine.start + FRAME_NS),
        "end": str(mine.end),
        "origin": "trigger",
        "priority": "high",
    }
    agent.triggers.take_depot_pull(PullSpec.of(overlapping))
    assert list(agent.triggers.windows) == [mine.pull_id] and mine.also == ["pull-00000000beef"]
    assert len(started) == 1  # one window sent
    started[0].done.set()
    run(agent.triggers.tick())
    assert ("pull-00000000beef", "done") in depot.progress  # told as the robot's own window is
