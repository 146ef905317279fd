"""Triggers on the robot: the rules' event rules evaluated over everything the spool takes (streamed
or read from watched files, whatever the live rules send), and, when an event a `[[trigger]]` names
is found, its window sent to the depot by itself and the event reported.

`TriggerObserver` is the spool's chunk observer: on ingest's thread it only notes each run's newest
time per timeline and queues the chunks the rules read. `Triggers.tick` (every TICK_S, evaluation on
a worker thread) feeds them to a `RunEvaluator` per run, fires a window for each new event a trigger
names, starts a window once the spool holds its data to its end (or its run ended), within the day's
budgets, and tells the depot where each window stands (`POST /v1/runs/RUN/triggered`).
"""

from __future__ import annotations

import asyncio
import collections
import logging
import time
from typing import TYPE_CHECKING, Any

from core.clock import utcnow
from core.errors import FleetError
from services.agent.bandwidth import Priority
from services.agent.lanes import PullJob
from services.agent.link import DepotRefused, LinkDown
from services.agent.pulls import PullRefused, PullSpec, select_pull
from services.agent.rules import AgentRules
from services.agent.windows import (
    DEPOT_STATE,
    DONE,
    FAILED,
    HELD,
    OPEN_STATES,
    SENDING,
    WAITING,
    Budgets,
    Window,
    saved_windows,
    trigger_key,
)
from services.hot.index import HotEntry
from services.rrd.chunk import ChunkMeta
from services.rrd.messages import ArrowMessage
from services.rules.evaluate import FoundEvent, RunEvaluator

if TYPE_CHECKING:
    from services.agent.service import Agent

log = logging.getLogger("fleet.agent")

TICK_S = 0.25
MAX_QUEUED = 100_000  # chunks waiting for evaluation; past it they are dropped (and counted)
MAX_EVENTS = 10_000  # per run, as the depot's default FLEET_MAX_EVENTS_PER_RUN
REPORT_EVERY_S = 1.0  # a sending window's counters, at most this often


class TriggerObserver:
    """The spool's `ChunkObserver` (services/rules/observe.py): cheap, never blocks ingest."""

    def __init__(self, rules: AgentRules) -> None:
        self.rules = rules
        self.queue: collections.deque[tuple[str, ArrowMessage, ChunkMeta]] = collections.deque()
        self.newest: dict[str, dict[str, int]] = {}  # run -> timeline -> newest time spooled
        self.dropped = 0

    def wants(self, entity_path: str) -> bool:
        return bool(self.rules.rules.triggers)

    def chunk(self, run_id: str, robot_id: str, msg: ArrowMessage, meta: ChunkMeta) -> None:
        if meta.is_static:
            return
        newest = self.newest.setdefault(run_id, {})
        for timeline in meta.timelines:
            if timeline.range.max > newest.get(timeline.name, timeline.range.max - 1):
                newest[timeline.name] = timeline.range.max
        if self.rules.rules.names_entity(meta.entity_path):
            if len(self.queue) >= MAX_QUEUED:
                self.dropped += 1
                return
            self.queue.append((run_id, msg, meta))

    def started(self, run_id: str, robot_id: str) -> None:
        self.newest.setdefault(run_id, {})


class Triggers:
    def __init__(self, agent: Agent, observer: TriggerObserver) -> None:
        self.agent = agent
        self.observer = observer
        self.rules = observer.rules
        self.evaluators: dict[str, tuple[int, RunEvaluator]] = {}  # run -> (rules' change count, evaluator)
        self.windows = saved_windows(agent.state)
        self.keys = {w.key for w in self.windows.values()}
        self.jobs: dict[str, PullJob] = {}
        self.budgets = Budgets(agent.state, agent.settings.agent_trigger_max_bytes_per_day)
        self.counters = {"fired": 0, "over_budget": 0, "bytes_sent": 0}
        self.reported_at: dict[str, float] = {}
        for window in self.windows.values():
            if window.state == SENDING:
                window.state = WAITING  # its job died with the last process: planned again (not charged again)

    def protected_runs(self) -> set[str]:
        """Runs with a window the depot does not hold yet: retention keeps them."""
        return {w.run_id for w in self.windows.values() if w.state in OPEN_STATES}

    def take_depot_pull(self, pull: PullSpec) -> str | None:
        """A window the depot's live rules fired, queued as a pull: a window this agent fired already
        answers it (told the same progress); else it is served as a window of its own, when the spool
        holds its data to its end and within the day's budgets. Why it cannot be served, if it cannot."""
        if pull.pull_id in self.windows:
            return None
        for window in self.windows.values():
            if window.from_depot:
                continue
            same_event = pull.event_id is not None and pull.event_id == window.event_id
            if pull.pull_id == window.depot_pull or same_event or window.overlaps(pull):
                if pull.pull_id not in (window.depot_pull, *window.also):
                    window.also.append(pull.pull_id)
                    window.reported = None  # the new pull is told where the window stands
                    window.save(self.agent.state)
                return None
        recording = self.agent.spool.recording(pull.run_id)
        kind = recording.timeline_types.get(pull.timeline or "") if recording is not None else None
        if kind is None:
            return f"run {pull.run_id} has no timeline {pull.timeline!r} on the robot"
        try:
            window = Window.of_pull(pull, kind, *self.budget_of(list(pull.include)), time.time())
        except FleetError as exc:  # a window bound it cannot read
            return str(exc)
        self.windows[window.pull_id] = window
        window.save(self.agent.state)
        log.info("trigger window %s of run %s: fired by the depot", window.pull_id, window.run_id)
        return None

    # --- the loop -------------------------------------------------------------------------------

    async def run(self) -> None:
        while True:
            try:
                await self.tick()
            except Exception:  # never the end of the loop: said, and tried again
                log.exception("evaluating triggers failed")
            await asyncio.sleep(TICK_S)

    async def tick(self) -> None:
        found = await asyncio.to_thread(self._evaluate)
        for run_id, event in found:
            self._fire(run_id, event)
        for window in list(self.windows.values()):
            if window.state == WAITING and self._ready(window):
                await self._start(window)
            elif window.state == SENDING:
                self._follow(window)
        await self._report()

    # --- finding events -----------------------------------------------------------------------------

    def _evaluate(self) -> list[tuple[str, FoundEvent]]:
        """Feed the queued chunks to their runs' evaluators; the events found since the last tick,
        and those an ended run's evaluation closes."""
        queue = self.observer.queue
        touched: set[str] = set()
        while queue:
            run_id, msg, meta = queue.popleft()
            self._evaluator(run_id).add(msg, meta)
            touched.add(run_id)
        found = [(run_id, e) for run_id in touched for e in self._evaluator(run_id).take_closed()]
        for run_id in list(self.evaluators):
            run = self.agent.spool.run(run_id)
            if run is None or not self.agent.spool.is_open(run):  # ended: what its evaluation still held
                held = self.evaluators.pop(run_id, None)
                found += [(run_id, e) for e in held[1].finish({}).events] if held is not None else []
        return found

    def _evaluator(self, run_id: str) -> RunEvaluator:
        held = self.evaluators.get(run_id)
        if held is None or held[0] != self.rules.changes:  # new rules: evaluated from here on
            held = self.evaluators[run_id] = (self.rules.changes, RunEvaluator(self.rules.rules, max_events=MAX_EVENTS))
        return held[1]

    def _fire(self, run_id: str, event: FoundEvent) -> None:
        for rule in self.rules.rules.triggers:
            if event.kind not in rule.events:
                continue
            window = Window.fire(run_id, event, rule, self.rules.version, time.time())
            if window.key in self.keys:
                continue  # found again (its run's evaluation closed it at its end)
            self.keys.add(window.key)
            self.windows[window.pull_id] = window
            window.save(self.agent.state)
            self.counters["fired"] += 1
            log.info(
                "trigger fired on run %s: %s at %s %d; window %s (%s)",
                run_id,
                event.kind,
                event.timeline,
                event.start,
                window.pull_id,
                ", ".join(rule.include),
            )

    # --- sending windows ----------------------------------------------------------------------------

    def _ready(self, window: Window) -> bool:
        """The spool holds the window's data to its end, or no more will come."""
        run = self.agent.spool.run(window.run_id)
        if run is None or not self.agent.spool.is_open(run):
            return True
        return self.observer.newest.get(window.run_id, {}).get(window.timeline, window.end - 1) >= window.end

    async def _start(self, window: Window) -> None:
        recording = self.agent.spool.recording(window.run_id)
        if recording is None:
            self._end(window, FAILED, f"the robot no longer holds run {window.run_id}")
            return
        spec = PullSpec(
            window.pull_id, window.run_id, window.include, [], window.timeline, str(window.start), str(window.end)
        )
        try:
            entries = await asyncio.to_thread(
                select_pull, spec, recording.path, recording.size, recording.timeline_types
            )
        except PullRefused as exc:
            self._end(window, FAILED, str(exc))
            return
        try:
            refusal = None if window.charged else await self._charge(window, entries)
        except LinkDown:
            return  # what the depot lacks is not known: the window waits for the link
        if refusal is not None:
            self.counters["over_budget"] += 1
            log.warning("trigger window %s of run %s stays on the robot: %s", window.pull_id, window.run_id, refusal)
            self._end(window, HELD, refusal)
            return
        job = PullJob(window.pull_id, entries, Priority.TRIGGER if window.priority == "high" else Priority.PULL)
        self.jobs[window.pull_id] = job
        window.state = SENDING
        window.save(self.agent.state)
        self.agent.sender_for(window.run_id).add_pull(job)

    async def _charge(self, window: Window, entries: list[HotEntry]) -> str | None:
        """Count the window in the day's budgets; why not, if it does not fit."""
        refusal = await self.charge(window.run_id, entries, window.budget_key, window.budget)
        window.charged = refusal is None
        return refusal

    async def charge(self, run_id: str, entries: list[HotEntry], key: str, budget: int | None) -> str | None:
        """Count the bytes of `entries` the depot lacks (and no window being sent holds) under budget
        `key`, if they fit today; else why not. LinkDown: what the depot lacks is not known."""
        held = await self.agent.link.held(run_id, [e.meta.chunk_id for e in entries if e.meta is not None])
        sending = {e.meta.chunk_id for job in self._sending() for e in job.entries if e.meta is not None}
        nbytes = sum(
            e.length
            for e in entries
            if e.meta is not None and e.meta.chunk_id in held.missing and e.meta.chunk_id not in sending
        )
        now = utcnow()
        refusal = self.budgets.refusal(key, budget, nbytes, now)
        if refusal is None:
            self.budgets.charge(key, nbytes, now)
        return refusal

    def _sending(self) -> list[PullJob]:
        return [job for job in self.jobs.values() if not job.done.is_set()]

    def budget_of(self, include: list[str]) -> tuple[str, int | None]:
        """The budget of the running rules' trigger that brings `include` home (a window the depot
        asked for names no trigger: the trigger with the same include; none: only the robot's cap)."""
        for rule in self.rules.rules.triggers:
            if list(rule.include) == include:
                return trigger_key(rule), rule.max_bytes_per_robot_day
        return "depot", None

    def _follow(self, window: Window) -> None:
        job = self.jobs.get(window.pull_id)
        if job is None:
            window.state = WAITING  # planned again at the next tick
            return
        window.chunks_sent, window.bytes_sent = job.chunks_sent, job.bytes_sent
        if job.done.is_set():
            self.jobs.pop(window.pull_id)
            self.counters["bytes_sent"] += job.bytes_sent
            if job.error:
                self._end(window, FAILED, job.error)
            else:
                log.info(
                    "trigger window %s of run %s is at the depot (%d chunks, %d bytes sent)",
                    window.pull_id,
                    window.run_id,
                    job.chunks_sent,
                    job.bytes_sent,
                )
                self._end(window, DONE, None)

    def held_pulls(self) -> set[str]:
        """The depot's ids of the windows held on the robot over their budget."""
        return {w.depot_pull or w.pull_id for w in self.windows.values() if w.state == HELD}

    def dismissed(self, cancelled: set[str]) -> None:
        """Held windows a person cancelled at the depot: no longer kept for (retention may take their run)."""
        for window in self.windows.values():
            if window.state == HELD and (window.depot_pull or window.pull_id) in cancelled:
                log.info("trigger window %s of run %s: dismissed at the depot", window.pull_id, window.run_id)
                self._end(window, FAILED, "dismissed at the depot (its pull was cancelled)")
                window.reported = window.reported_as()  # nothing to tell: the depot cancelled it
                window.save(self.agent.state)

    def pulled(self, event_id: str) -> None:
        """A pull of an event's window is done (a person's, of a window held over budget): the
        depot holds it, so its run is no longer kept for it."""
        for window in self.windows.values():
            if window.event_id == event_id and window.state in (WAITING, HELD):
                self._end(window, DONE, None)

    def _end(self, window: Window, state: str, error: str | None) -> None:
        window.state, window.error = state, error
        window.save(self.agent.state)

    def forget_run(self, run_id: str) -> None:
        """The run left the spool: its windows go with it (a held one only once the depot has it, or
        a person released it: retention keeps its run until then)."""
        for window in [w for w in self.windows.values() if w.run_id == run_id]:
            self.windows.pop(window.pull_id)
            self.keys.discard(window.key)
            self.agent.state.forget_pull(window.pull_id)
        self.observer.newest.pop(run_id, None)
        self.evaluators.pop(run_id, None)

    # --- telling the depot ------------------------------------------------------------------------

    async def _report(self) -> None:
        for window in list(self.windows.values()):
            if window.reported == window.reported_as():
                continue
            if (
                window.state == SENDING
                and time.monotonic() - self.reported_at.get(window.pull_id, 0.0) < REPORT_EVERY_S
            ):
                continue
            try:
                await self._tell(window)
            except LinkDown:
                return  # all wait for the link
            except DepotRefused as exc:  # the run is not in the catalog yet, say: told later
                log.debug("trigger window %s not reported yet: %s", window.pull_id, exc)
                continue
            self.reported_at[window.pull_id] = time.monotonic()
            window.reported = window.reported_as()
            window.save(self.agent.state)

    async def _tell(self, window: Window) -> None:
        """A window fired here: the first report files the event and the window (the depot answers
        with its own pull when it fired first: progress then goes to that one). A window the depot
        fired: its pull's progress. Other pulls of the same window the depot queued: told the same."""
        link = self.agent.link
        targets = [window.depot_pull or window.pull_id]
        if not window.from_depot and window.depot_pull in (None, window.pull_id):
            answer: dict[str, Any] = await link.call(link.api.report_triggered, window.run_id, window.report())
            window.depot_pull = str((answer.get("pull") or {}).get("id") or window.pull_id)
            window.event_id = (answer.get("event") or {}).get("id") or window.event_id
            targets = [] if window.depot_pull == window.pull_id else [window.depot_pull]  # the report moved ours
        if window.state == WAITING:
            return
        for pull_id in [*targets, *window.also]:
            try:
                await link.call(
                    link.api.pull_progress,
                    pull_id,
                    state=DEPOT_STATE[window.state],
                    chunks_sent=window.chunks_sent if pull_id == window.depot_pull else 0,
                    bytes_sent=window.bytes_sent if pull_id == window.depot_pull else 0,
                    error=window.error,
                )
            except DepotRefused as exc:  # done or cancelled there already: nothing more to tell
                log.info("the depot took no more reports of pull %s: %s", pull_id, exc)
