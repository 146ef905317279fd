"""The rules file: a valid one read into rules; a bad one refused whole, every problem named with
its line and field; regexes run by re2 (linear time: a pattern that backtracks catastrophically in
Python's `re` is harmless, one re2 cannot run is refused)."""

from __future__ import annotations

import time

import pytest

from core.errors import InvalidRulesError
from services.rules.spec import EventRule, MetricRule, RuleSet, parse_rules
from services.rules.triggers import MAX_WINDOW_S, TriggerRule

VALID = """\
# the robots' rules
[[event]]
name = "intervention"
entity = "/autonomy/engaged"
when = "falls_below"
threshold = 0.5
severity = "warn"

[[event]]
name = "stuck"
entity = "/logs/**"
when = "text"
level = "error"
match = "(?i)stuck|blocked"

[[event]]
name = "cold"
entity = "/sensors/ambient_temp"
when = "below"
threshold = 5
for_s = 2.5
timeline = "sim_time"

[[metric]]
name = "distance_m"
kind = "path_length"
entity = "/world/robot"

[[metric]]
name = "interventions"
kind = "event_count"
event = "intervention"

[[metric]]
name = "sw_version"
kind = "property"
property = "fleet.sw_version"

[[trigger]]
event = "intervention"
include = ["/camera/**", "/lidar/front"]
before_s = 10
after_s = 5
max_bytes_per_robot_day = 500_000_000
priority = "high"
"""


def problems(text: str) -> list[tuple[int | None, str]]:
    """(line, field) of each problem of a refused rules file."""
    with pytest.raises(InvalidRulesError) as refused:
        parse_rules(text)
    return [(p["line"], p["field"]) for p in refused.value.problems]  # type: ignore[misc]


def messages(text: str) -> dict[str, str]:
    with pytest.raises(InvalidRulesError) as refused:
        parse_rules(text)
    return {str(p["field"]): str(p["message"]) for p in refused.value.problems}


def test_a_valid_file_gives_its_rules_with_their_defaults():
    rules = parse_rules(VALID)
    assert rules.text == VALID
    intervention, stuck, cold = rules.events
    assert intervention == EventRule(
        "intervention", "/autonomy/engaged", "falls_below", "warn", 0.5, 0.0, None, None, "log_time", 2
    )
    assert (stuck.when, stuck.level, stuck.match, stuck.severity, stuck.line) == (
        "text",
        "ERROR",
        "(?i)stuck|blocked",
        "info",
        9,
    )
    assert stuck.pattern.search("Robot STUCK at dock") is not None
    assert stuck.pattern.search("all fine") is None
    assert (cold.threshold, cold.for_s, cold.timeline) == (5.0, 2.5, "sim_time")
    assert rules.metrics == (
        MetricRule("distance_m", "path_length", entity="/world/robot", line=24),
        MetricRule("interventions", "event_count", event="intervention", line=29),
        MetricRule("sw_version", "property", property="fleet.sw_version", line=34),
    )
    assert rules.triggers == (
        TriggerRule(("intervention",), ("/camera/**", "/lidar/front"), 10.0, 5.0, 500_000_000, "high", line=39),
    )
    (trigger,) = rules.triggers
    assert [g.fullmatch("/camera/left/rgb") is not None for g in trigger.globs] == [True]


def test_an_empty_rule_set_names_nothing():
    assert parse_rules("") == RuleSet.empty()
    assert not RuleSet.empty().names_entity("/anything")


def test_entities_named_exactly_and_by_glob():
    rules = parse_rules(
        VALID
        + """
[[event]]
name = "hot_motor"
entity = "/motors/*/current"
when = "above"
threshold = 10

[[metric]]
name = "mean_temp"
kind = "mean"
entity = "/sensors/ambient_temp"
"""
    )
    for path in ("/autonomy/engaged", "/logs", "/logs/planner", "/logs/a/b/c", "/motors/left/current", "/world/robot"):
        assert rules.names_entity(path), path
    for path in ("/autonomy", "/autonomy/engaged/x", "/logsx", "/motors/left/x/current", "/motors/current", "/world"):
        assert not rules.names_entity(path), path
    temp = rules.rules_for("/sensors/ambient_temp")
    assert [r.name for r in temp.events] == ["cold"] and temp.scalar_stats and not temp.path_length
    assert rules.rules_for("/world/robot").path_length
    assert [r.name for r in rules.rules_for("/motors/right/current").events] == ["hot_motor"]
    assert rules.rules_for("/motors/right/current") is rules.rules_for("/motors/right/current")  # matched once


def test_every_problem_is_named_with_its_line_and_field():
    text = """\
colour = "blue"
[[event]]
name = "a"
entity = "engaged"
when = "sometimes"
severity = "fatal"
extra = 1

[[event]]
name = "b"
entity = "/x"
when = "below"

[[event]]
entity = "/y"
when = "text"
level = "LOUD"
match = "("
threshold = 3

[[metric]]
name = "m"
kind = "mean"
entity = "/a/**"
event = "a"

[[metric]]
name = "v"
kind = "property"
property = "sw_version"
"""
    assert problems(text) == [
        (1, "colour"),
        (7, "event[1].extra"),
        (4, "event[1].entity"),
        (5, "event[1].when"),
        (6, "event[1].severity"),
        (9, "event[2].threshold"),
        (14, "event[3].name"),
        (19, "event[3].threshold"),
        (17, "event[3].level"),
        (18, "event[3].match"),
        (25, "metric[1].event"),
        (24, "metric[1].entity"),
        (30, "metric[2].property"),
    ]
    said = messages(text)
    assert "unknown key" in said["colour"] and "unknown key" in said["event[1].extra"]
    assert "'sometimes' is none of falls_below, rises_above, below, above, text" in said["event[1].when"]
    assert "'fatal' is none of info, warn, error" in said["event[1].severity"]
    assert "missing" in said["event[2].threshold"] and "threshold" in said["event[2].threshold"]
    assert "missing" in said["event[3].name"]
    assert "not a regex" in said["event[3].match"] and "missing )" in said["event[3].match"]
    assert "not a glob" in said["metric[1].entity"]
    assert "fleet.sw_version" in said["metric[2].property"]


def test_a_refused_file_says_every_problem_in_its_message_and_answers_422():
    with pytest.raises(InvalidRulesError) as refused:
        parse_rules('[[event]]\nname = "a"\nentity = "/x"\nwhen = "below"\nthreshold = "high"\n')
    assert refused.value.problems == [
        {"line": 5, "field": "event[1].threshold", "message": "a finite number, not 'high'"}
    ]
    assert "line 5: event[1].threshold" in str(refused.value)
    assert refused.value.to_dict()["problems"] == refused.value.problems  # type: ignore[comparison-overlap]
    assert refused.value.http_status() == 422


def test_a_syntax_error_names_its_line():
    assert problems('[[event]]\nname = "a"\nentity = /x\n') == [(3, "toml")]


def test_tables_written_otherwise_than_as_arrays_of_tables_are_refused():
    assert problems('[event]\nname = "a"\n') == [(1, "event")]
    assert problems("metric = 3\n") == [(1, "metric")]


def test_duplicate_names_are_refused_where_the_second_is():
    text = """\
[[event]]
name = "dup"
entity = "/x"
when = "text"

[[event]]
name = "dup"
entity = "/y"
when = "text"

[[metric]]
name = "m"
kind = "max"
entity = "/x"

[[metric]]
name = "m"
kind = "min"
entity = "/x"
"""
    assert problems(text) == [(7, "event[2].name"), (17, "metric[2].name")]
    assert "names event[1] too (line 2)" in messages(text)["event[2].name"]


def test_a_catastrophic_regex_is_accepted_and_runs_in_linear_time():
    rules = parse_rules('[[event]]\nname = "a"\nentity = "/logs"\nwhen = "text"\nmatch = "(a+)+$"\n')
    pattern = rules.events[0].pattern
    text = "a" * 200_000 + "!"  # Python's `re` backtracks for ages on this; re2 reads it once
    started = time.monotonic()
    assert pattern.search(text) is None
    assert pattern.search("a" * 10) is not None
    assert time.monotonic() - started < 2.0


@pytest.mark.parametrize(
    "regex",
    [
        "(",  # invalid
        "(?<=a)b",  # lookbehind: no linear-time matching
        r"(a)\1",  # backreference: no linear-time matching
        "a{1000}{1000}",  # beyond re2's size limits
    ],
)
def test_a_regex_re2_cannot_run_is_refused(regex: str):
    text = f'[[event]]\nname = "a"\nentity = "/logs"\nwhen = "text"\nmatch = \'{regex}\'\n'  # a literal string
    assert problems(text) == [(5, "event[1].match")]


def test_keys_of_another_condition_or_kind_are_problems():
    numeric = '[[event]]\nname = "a"\nentity = "/x"\nwhen = "above"\nthreshold = 1\nlevel = "ERROR"\n'
    assert problems(numeric) == [(6, "event[1].level")]
    count = '[[metric]]\nname = "n"\nkind = "event_count"\nevent = "a"\nentity = "/x"\n'
    assert problems(count) == [(5, "metric[1].entity")]


@pytest.mark.parametrize(
    ("line", "problem_field"),
    [
        ('name = "has space"', "event[1].name"),
        ('name = ""', "event[1].name"),
        ("for_s = -1", "event[1].for_s"),
        ("for_s = nan", "event[1].for_s"),
        ("timeline = 3", "event[1].timeline"),
        ('entity = "/a//b"', "event[1].entity"),
        ('entity = "/a/b**"', "event[1].entity"),
    ],
)
def test_bad_values_are_problems(line: str, problem_field: str):
    base = {"name": '"a"', "entity": '"/x"', "when": '"below"', "threshold": "1"}
    key = line.split(" = ")[0]
    body = "\n".join(f"{k} = {v}" for k, v in base.items() if k != key) + "\n" + line + "\n"
    assert [f for _, f in problems("[[event]]\n" + body)] == [problem_field]


EVENT = '[[event]]\nname = "hard_brake"\nentity = "/imu/accel"\nwhen = "above"\nthreshold = 8.0\n'


def test_a_trigger_takes_one_event_or_several_and_has_defaults():
    text = EVENT + '[[event]]\nname = "stop"\nentity = "/cmd"\nwhen = "below"\nthreshold = 0.1\n'
    rules = parse_rules(text + '[[trigger]]\nevent = ["hard_brake", "stop", "stop"]\ninclude = "/camera/**"\n')
    (trigger,) = rules.triggers
    assert (trigger.events, trigger.include, trigger.before_s, trigger.after_s) == (
        ("hard_brake", "stop"),
        ("/camera/**",),
        10.0,
        10.0,
    )
    assert (trigger.max_bytes_per_robot_day, trigger.priority) == (None, "normal")


@pytest.mark.parametrize(
    ("trigger", "field", "says"),
    [
        ('event = "hard_brak"\ninclude = "/camera/**"', "trigger[1].event", "no [[event]] rule's name in this file"),
        ('include = "/camera/**"', "trigger[1].event", "missing"),
        ('event = []\ninclude = "/camera/**"', "trigger[1].event", "a non-empty string or a list"),
        ('event = "hard_brake"', "trigger[1].include", "missing"),
        ('event = "hard_brake"\ninclude = "camera/**"', "trigger[1].include", "starts with '/'"),
        ('event = "hard_brake"\ninclude = ["/a", ""]', "trigger[1].include", "a non-empty string or a list"),
        ('event = "hard_brake"\ninclude = "/a"\nbefore_s = 3000\nafter_s = 3000', "trigger[1].after_s", "at most"),
        ('event = "hard_brake"\ninclude = "/a"\nbefore_s = -1', "trigger[1].before_s", "at least 0"),
        (
            'event = "hard_brake"\ninclude = "/a"\nmax_bytes_per_robot_day = 0',
            "trigger[1].max_bytes_per_robot_day",
            "above 0",
        ),
        (
            'event = "hard_brake"\ninclude = "/a"\nmax_bytes_per_robot_day = 1.5',
            "trigger[1].max_bytes_per_robot_day",
            "whole",
        ),
        ('event = "hard_brake"\ninclude = "/a"\npriority = "urgent"', "trigger[1].priority", "none of high, normal"),
        ('event = "hard_brake"\ninclude = "/a"\ncolour = "red"', "trigger[1].colour", "unknown key"),
    ],
)
def test_a_bad_trigger_is_refused_naming_its_field(trigger: str, field: str, says: str):
    said = messages(EVENT + "[[trigger]]\n" + trigger + "\n")
    assert says in said[field], said
    assert MAX_WINDOW_S == 3600.0  # (the window's limit the message names)
