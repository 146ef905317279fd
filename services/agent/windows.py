"""A trigger's window on a spooled run, and the day's byte budgets windows are sent within.

A window is what a `[[trigger]]` brings home: its include's chunks overlapping [event start -
before_s, event end + after_s] on the event's timeline (seconds as ns on timestamp and duration
timelines, steps on a sequence timeline), plus the static ones and the latest-at state at its start,
as a pull picks them. It lives in the agent's state (`pulls` table) from when it fires until its run
leaves the spool, so a restart neither loses nor repeats one, and retention keeps its run while it
is not at the depot.
"""

from __future__ import annotations

import datetime as dt
import secrets
from dataclasses import asdict, dataclass, field
from typing import Any

from core.errors import FleetError
from services.agent.pulls import PullSpec
from services.agent.state import AgentState, PullState
from services.edge.triggers import steps
from services.rules.evaluate import FoundEvent
from services.rules.triggers import TriggerRule
from services.runs.download import parse_time_value

WAITING = "waiting"  # fired; the data up to its end is not all spooled yet
SENDING = "sending"
HELD = "held"  # over a budget: it stays on the robot until a person pulls it
DONE = "done"  # the depot holds every chunk of it
FAILED = "failed"  # its run left the spool, or the depot takes no data for it
OPEN_STATES = (WAITING, SENDING, HELD)  # the robot keeps its run
DEPOT_STATE = {WAITING: "pending", SENDING: "sending", HELD: "held", DONE: "done", FAILED: "failed"}
TRIGGER_KIND = "trigger"  # the `kind` in a window's saved spec (a person's pull has none)


def new_pull_id() -> str:
    return "pull-" + secrets.token_hex(6)


def trigger_key(rule: TriggerRule) -> str:
    """What a trigger's budget is counted under: the same trigger in a later rules version keeps it."""
    return "|".join(rule.events) + ">" + "|".join(rule.include)


def window_bounds(event: FoundEvent, rule: TriggerRule) -> tuple[int, int]:
    """As the depot bounds the windows it fires (services/edge/triggers.py): steps rounded up."""
    return event.start - steps(rule.before_s, event.timeline_type), event.end + steps(rule.after_s, event.timeline_type)


@dataclass
class Window:
    pull_id: str
    run_id: str
    event: dict[str, Any]  # kind, severity, timeline, timeline_type, start, end, label
    rules_version: int
    start: int
    end: int
    include: list[str]
    priority: str  # high | normal
    budget_key: str
    budget: int | None  # the trigger's max_bytes_per_robot_day
    state: str = WAITING
    chunks_sent: int = 0
    bytes_sent: int = 0
    charged: bool = False  # its bytes were counted in a day's budget
    error: str | None = None
    reported: str | None = None  # the state the depot was last told, with its counters
    depot_pull: str | None = None  # the depot's id for it (another when the depot fired first)
    event_id: str | None = None  # the depot's id of its event
    from_depot: bool = False  # the depot's live rules fired it: a pull of the depot's, reported as pulls are
    also: list[str] = field(default_factory=list)  # the depot's pulls of the same window, told the same
    fired_at: float = 0.0
    kind: str = field(default=TRIGGER_KIND)

    @classmethod
    def fire(cls, run_id: str, found: FoundEvent, rule: TriggerRule, version: int, now: float) -> Window:
        start, end = window_bounds(found, rule)
        event = {
            "kind": found.kind,
            "severity": found.severity,
            "timeline": found.timeline,
            "timeline_type": found.timeline_type,
            "start": found.start,
            "end": found.end,
            "label": found.label,
        }
        return cls(
            new_pull_id(),
            run_id,
            event,
            version,
            start,
            end,
            list(rule.include),
            rule.priority,
            trigger_key(rule),
            rule.max_bytes_per_robot_day,
            fired_at=now,
        )

    @classmethod
    def of_pull(cls, pull: PullSpec, timeline_type: str, budget_key: str, budget: int | None, now: float) -> Window:
        """A window the depot fired (its live rules found the event in the summary) and queued as a pull."""
        start = parse_time_value("start", timeline_type, pull.start or "")
        end = parse_time_value("end", timeline_type, pull.end or "")
        event = {"kind": "", "timeline": pull.timeline, "timeline_type": timeline_type, "start": start, "end": end}
        return cls(
            pull.pull_id,
            pull.run_id,
            event,
            0,
            start,
            end,
            list(pull.include),
            pull.priority or "normal",
            budget_key,
            budget,
            depot_pull=pull.pull_id,
            event_id=pull.event_id,
            from_depot=True,
            fired_at=now,
        )

    def overlaps(self, pull: PullSpec) -> bool:
        """Whether a pull of the depot asks for (part of) this window: the same run, timeline and
        entities, and a range that meets it."""
        if pull.run_id != self.run_id or pull.timeline != self.timeline or list(pull.include) != self.include:
            return False
        try:
            timeline_type = str(self.event.get("timeline_type", "sequence"))
            start = parse_time_value("start", timeline_type, pull.start or "")
            end = parse_time_value("end", timeline_type, pull.end or "")
        except FleetError:
            return False
        return start <= self.end and end >= self.start

    @property
    def timeline(self) -> str:
        return str(self.event["timeline"])

    @property
    def key(self) -> tuple[str, str, str, int, str]:
        """One window per run, event and trigger, however often the event is found."""
        return (self.run_id, str(self.event["kind"]), self.timeline, int(self.event["start"]), self.budget_key)

    def report(self) -> dict[str, Any]:
        """What `POST /v1/runs/RUN/triggered` is told."""
        return {
            "pull_id": self.pull_id,
            "rules_version": self.rules_version,
            "event": self.event,
            "window": {
                "timeline": self.timeline,
                "start": str(self.start),
                "end": str(self.end),
                "include": self.include,
                "exclude": [],
            },
            "priority": self.priority,
            "state": DEPOT_STATE[self.state],
            "chunks_sent": self.chunks_sent,
            "bytes_sent": self.bytes_sent,
            "error": self.error,
        }

    def reported_as(self) -> str:
        return f"{self.state}:{self.chunks_sent}:{self.bytes_sent}"

    def save(self, state: AgentState) -> None:
        spec = asdict(self)
        state.save_pull(PullState(self.pull_id, self.run_id, self.state, spec, self.chunks_sent, self.bytes_sent))


def saved_windows(state: AgentState) -> dict[str, Window]:
    """The windows in the agent's state (a person's pulls there are not windows)."""
    found: dict[str, Window] = {}
    for pull in state.pulls().values():
        if pull.spec.get("kind") != TRIGGER_KIND:
            continue
        try:
            found[pull.pull_id] = Window(**pull.spec)
        except TypeError:  # written by another version of the agent: forgotten
            state.forget_pull(pull.pull_id)
    return found


class Budgets:
    """Bytes of trigger windows sent today (UTC), per trigger and in all (`agent_trigger_max_bytes_per_day`),
    kept in the agent's state so a restart does not renew them."""

    FACT = "trigger_budgets"

    def __init__(self, state: AgentState, cap: int) -> None:
        self.state, self.cap = state, cap
        saved, _ = state.facts().get(self.FACT, ({}, 0.0))
        self.day: str = str(saved.get("day", ""))
        self.spent: dict[str, int] = {str(k): int(v) for k, v in dict(saved.get("spent", {})).items()}

    def _today(self, now: dt.datetime) -> None:
        day = now.date().isoformat()
        if day != self.day:
            self.day, self.spent = day, {}

    def refusal(self, key: str, budget: int | None, nbytes: int, now: dt.datetime) -> str | None:
        """Why `nbytes` more of trigger `key` may not go today (None: they may)."""
        self._today(now)
        spent = self.spent.get(key, 0)
        if budget is not None and spent + nbytes > budget:
            return f"over budget: {nbytes} bytes would take this trigger to {spent + nbytes} of its {budget} a day"
        total = self.spent.get("*", 0)
        if self.cap and total + nbytes > self.cap:
            return (
                f"over budget: {nbytes} bytes would take the robot's trigger windows to {total + nbytes} "
                f"of agent_trigger_max_bytes_per_day {self.cap}"
            )
        return None

    def charge(self, key: str, nbytes: int, now: dt.datetime) -> None:
        self._today(now)
        self.spent[key] = self.spent.get(key, 0) + nbytes
        self.spent["*"] = self.spent.get("*", 0) + nbytes
        self.state.set_fact(self.FACT, {"day": self.day, "spent": self.spent})
