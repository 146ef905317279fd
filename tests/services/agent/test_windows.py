"""A trigger's window: its bounds on the event's timeline, kept across restarts in the agent's state,
and the day's budgets per trigger and for the whole robot."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

from services.agent.state import AgentState, PullState
from services.agent.windows import DEPOT_STATE, Budgets, Window, saved_windows, trigger_key, window_bounds
from services.rules.evaluate import FoundEvent
from services.rules.triggers import TriggerRule

RULE = TriggerRule(("hard_brake",), ("/camera/**",), before_s=10, after_s=5, max_bytes_per_robot_day=1000)
NOON = dt.datetime(2026, 11, 29, 12, tzinfo=dt.UTC)


def found(timeline_type: str, start: int, end: int) -> FoundEvent:
    return FoundEvent("hard_brake", "warn", "t", timeline_type, start, end, "rule", "hard_brake", "")


def test_window_bounds_by_timeline_type():
    assert window_bounds(found("timestamp", 100 * 10**9, 101 * 10**9), RULE) == (90 * 10**9, 106 * 10**9)
    assert window_bounds(found("duration", 100 * 10**9, 100 * 10**9), RULE) == (90 * 10**9, 105 * 10**9)
    assert window_bounds(found("sequence", 100, 102), RULE) == (90, 107)  # steps on a sequence timeline
    halves = TriggerRule(("hard_brake",), ("/camera/**",), before_s=1.5, after_s=0.2)
    assert window_bounds(found("sequence", 100, 100), halves) == (98, 101)  # rounded up, as the depot does


def test_windows_survive_a_restart_and_a_persons_pull_is_not_one(tmp_path: Path):
    state = AgentState(tmp_path)
    window = Window.fire("run-1", found("timestamp", 5, 6), RULE, 4, 1.0)
    window.save(state)
    state.save_pull(PullState("pull-000000000001", "run-1", "sending", {"include": ["/a"]}))
    state.close()
    again = saved_windows(AgentState(tmp_path))
    assert list(again) == [window.pull_id]
    assert again[window.pull_id] == window
    report = window.report()
    assert report["state"] == DEPOT_STATE[window.state] == "pending"
    assert report["window"] == {
        "timeline": "t",
        "start": str(5 - 10 * 10**9),
        "end": str(6 + 5 * 10**9),
        "include": ["/camera/**"],
        "exclude": [],
    }


def test_budgets_per_trigger_and_for_the_robot(tmp_path: Path):
    state = AgentState(tmp_path)
    budgets = Budgets(state, cap=1500)
    key = trigger_key(RULE)
    assert budgets.refusal(key, 1000, 800, NOON) is None
    budgets.charge(key, 800, NOON)
    refusal = budgets.refusal(key, 1000, 300, NOON)
    assert refusal is not None and "over budget" in refusal and "1000" in refusal
    assert budgets.refusal("other", None, 600, NOON) is None
    budgets.charge("other", 600, NOON)
    cap = budgets.refusal("third", None, 200, NOON)  # 1400 + 200 > the robot's 1500
    assert cap is not None and "agent_trigger_max_bytes_per_day" in cap
    assert Budgets(state, cap=1500).refusal(key, 1000, 300, NOON) is not None  # kept across a restart
    tomorrow = NOON + dt.timedelta(days=1)
    assert budgets.refusal(key, 1000, 1000, tomorrow) is None  # a new day, a new budget
