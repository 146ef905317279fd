"""The agent's copy of the depot's rules: taken when the version changes, kept in the spool for a
restart while the depot is unreachable, and a version it cannot read refused with the last one kept."""

from __future__ import annotations

from pathlib import Path

from services.agent.rules import RULES_FILE, AgentRules

RULES = """
[[event]]
name = "hard_brake"
entity = "/metrics/brake"
when = "rises_above"
threshold = 5.0

[[trigger]]
event = "hard_brake"
include = ["/camera/**"]
"""


def test_a_new_version_is_taken_and_kept_for_the_next_start(tmp_path: Path):
    rules = AgentRules(tmp_path)
    assert rules.version == 0 and not rules.rules.triggers
    assert rules.take({"version": 3, "text": RULES})
    assert rules.version == 3 and len(rules.rules.triggers) == 1
    assert not rules.take({"version": 3, "text": RULES})  # the same version: nothing to do
    again = AgentRules(tmp_path)  # a restart with the depot out of reach
    assert again.version == 3 and again.rules.triggers == rules.rules.triggers


def test_a_version_the_agent_cannot_read_keeps_the_one_it_runs(tmp_path: Path):
    rules = AgentRules(tmp_path)
    rules.take({"version": 1, "text": RULES})
    changes = rules.changes
    assert not rules.take({"version": 2, "text": RULES + "\n[[future]]\nname = 'x'\n"})
    assert rules.version == 1 and rules.changes == changes
    assert rules.refused is not None and rules.refused.version == 2
    assert "future" in rules.refused.why
    status = rules.status()
    assert status["version"] == 1 and status["refused_version"] == 2
    assert rules.take({"version": 3, "text": RULES})  # a readable later one is taken, the refusal gone
    assert rules.refused is None and rules.version == 3


def test_rules_cleared_at_the_depot_clear_the_robots(tmp_path: Path):
    rules = AgentRules(tmp_path)
    rules.take({"version": 1, "text": RULES})
    assert rules.take({"version": 2, "text": ""})
    assert not rules.rules.triggers and not rules.rules.events


def test_a_damaged_copy_waits_for_the_depot(tmp_path: Path):
    (tmp_path / RULES_FILE).write_text("{not json")
    rules = AgentRules(tmp_path)
    assert rules.version == 0 and not rules.rules.triggers


def test_the_robot_evaluates_only_the_events_its_triggers_name(tmp_path: Path):
    rules = AgentRules(tmp_path)
    extra = '\n[[event]]\nname = "slow"\nentity = "/metrics/speed"\nwhen = "below"\nthreshold = 0.1\n'
    extra += '\n[[metric]]\nname = "distance_m"\nkind = "path_length"\nentity = "/world/robot"\n'
    rules.take({"version": 1, "text": RULES + extra})
    assert [r.name for r in rules.rules.events] == ["hard_brake"]
    assert not rules.rules.metrics
    assert rules.rules.names_entity("/metrics/brake") and not rules.rules.names_entity("/world/robot")
