"""What the agent tells the depot besides the data: pulls it takes on and finishes, and what it holds
of each run (so the run's page says what is on the robot only, pending, or held)."""

from __future__ import annotations

import asyncio
import contextlib
import datetime as dt
import logging
from typing import TYPE_CHECKING, Any

from services.agent.lanes import PullJob
from services.agent.link import DepotRefused, LinkDown
from services.agent.pulls import PullRefused, PullSpec, select_pull
from services.agent.windows import TRIGGER_KIND as TRIGGER

if TYPE_CHECKING:
    from services.agent.service import Agent

log = logging.getLogger("fleet.agent")

REPORT_S = 15.0  # how often changed robot copies are reported


class Reports:
    def __init__(self, agent: Agent) -> None:
        self.agent = agent
        self.taken: dict[str, asyncio.Task[None]] = {}  # pull id -> its task
        self.reported: dict[str, tuple[int, int, int]] = {}  # run -> what was last reported

    # --- pulls ----------------------------------------------------------------------------------

    async def poll_pulls(self) -> None:
        """Take on the depot's pending pulls for this robot's runs (runs not in the spool: failed)."""
        link = self.agent.link
        pending: list[dict[str, Any]] = await link.call(link.api.pulls, state="pending")
        sending: list[dict[str, Any]] = await link.call(link.api.pulls, state="sending")
        for pull in [*pending, *sending]:  # sending: taken by this robot before a restart
            spec = PullSpec.of(pull)
            if spec.origin == TRIGGER and self.agent.spool.run(spec.run_id) is not None:
                why = self.agent.triggers.take_depot_pull(spec)  # a window the depot's live rules fired
                if why is not None:
                    await self._progress(spec, "failed", error=why)
                continue
            task = self.taken.get(spec.pull_id)
            if task is not None and not task.done():
                continue
            if self.agent.spool.run(spec.run_id) is None:
                if pull.get("robot_id") not in self.robots():
                    continue  # a depot without auth lists every robot's pulls: this one is another's
                await self._progress(spec, "failed", error=f"the robot no longer holds run {spec.run_id}")
                continue
            self.taken[spec.pull_id] = asyncio.create_task(self._serve(spec), name=f"pull {spec.pull_id}")
        if self.agent.triggers.held_pulls():  # a person may have dismissed a window held over budget
            cancelled: list[dict[str, Any]] = await link.call(link.api.pulls, state="cancelled")
            self.agent.triggers.dismissed({str(p["id"]) for p in cancelled})

    def robots(self) -> set[str]:
        """The robots whose runs this agent holds or has held (remembered across restarts)."""
        known, _ = self.agent.state.facts().get("robots", ([], 0.0))
        robots = set(known) | {run.robot_id for run in self.agent.spool.runs() if run.robot_id}
        if robots != set(known):
            self.agent.state.set_fact("robots", sorted(robots))
        return robots

    async def _serve(self, spec: PullSpec) -> None:
        recording = self.agent.spool.recording(spec.run_id)
        if recording is None:
            return
        try:
            entries = await asyncio.to_thread(
                select_pull, spec, recording.path, recording.size, recording.timeline_types
            )
        except PullRefused as exc:
            await self._progress(spec, "failed", error=str(exc))
            return
        job = PullJob(spec.pull_id, entries)
        await self._progress(spec, "sending")
        self.agent.sender_for(spec.run_id).add_pull(job)
        log.info("pull %s of run %s: %d chunks asked for", spec.pull_id, spec.run_id, len(entries))
        await self._follow(spec, job)
        await self._progress(spec, "done", chunks=job.chunks_sent, nbytes=job.bytes_sent)
        log.info("pull %s done: %d chunks, %d bytes sent", spec.pull_id, job.chunks_sent, job.bytes_sent)
        if spec.event_id is not None:
            self.agent.triggers.pulled(spec.event_id)

    async def _follow(self, spec: PullSpec, job: PullJob) -> None:
        """Until the job is done (its chunks sent and the depot's holding them checked, which may take
        a check interval), report its counters as they grow, so the pull's status says what has
        arrived rather than "sending, 0 chunks"; at most one report per FLEET_AGENT_PULL_PROGRESS_S."""
        link = self.agent.link
        reported = (0, 0)
        while not job.done.is_set():
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(job.done.wait(), self.agent.settings.agent_pull_progress_s)
            now = (job.chunks_sent, job.bytes_sent)
            if job.done.is_set() or now == reported:
                continue
            try:
                await link.call(
                    link.api.pull_progress, spec.pull_id, state="sending", chunks_sent=now[0], bytes_sent=now[1]
                )
            except LinkDown:
                continue  # told at a later turn, or by the "done" report
            except DepotRefused as exc:  # cancelled at the depot, say: no more reports until it is done
                log.warning("the depot refused progress of pull %s (sending): %s", spec.pull_id, exc)
                await job.done.wait()
                return
            reported = now

    async def _progress(
        self, spec: PullSpec, state: str, *, chunks: int = 0, nbytes: int = 0, error: str | None = None
    ) -> None:
        link = self.agent.link
        for _ in range(10):  # a link that is down now: retried, the pull stays where it was at the depot
            try:
                await link.call(
                    link.api.pull_progress,
                    spec.pull_id,
                    state=state,
                    chunks_sent=chunks,
                    bytes_sent=nbytes,
                    error=error,
                )
                return
            except LinkDown:
                await asyncio.sleep(self.agent.settings.agent_pull_poll_s)
            except DepotRefused as exc:
                log.warning("the depot refused progress of pull %s (%s): %s", spec.pull_id, state, exc)
                return

    # --- robot copies ----------------------------------------------------------------------------

    async def report_copies(self) -> None:
        """Report each run's copy on the robot when it changed."""
        agent = self.agent
        link = agent.link
        retain = dt.timedelta(hours=agent.settings.agent_retain_hours)
        for run in agent.spool.runs():
            sender = agent.runners.get(run.run_id)
            state = agent.run_states.get(run.run_id)
            if state is None or (sender is not None and not sender.learned):
                continue  # a starting sender has yet to ask the depot what is on the robot only
            figures = (run.size, state.local_only_chunks, state.local_only_bytes)
            if self.reported.get(run.run_id) == figures:
                continue
            entities = sorted(sender.local_only_entities) if sender is not None else []
            try:
                await link.call(
                    link.api.report_robot_copy,
                    run.run_id,
                    chunks=max(run.chunks, state.local_only_chunks),
                    bytes=run.size,
                    local_only_chunks=state.local_only_chunks,
                    local_only_bytes=state.local_only_bytes,
                    local_only_entities=entities,
                    keeps_until=(run.last_data_at + retain).isoformat(),
                )
            except DepotRefused as exc:  # not in the catalog yet (the depot saves runs every few seconds)
                log.info("robot copy of %s not reported yet: %s", run.run_id, exc)
                continue
            self.reported[run.run_id] = figures

    async def forget_copy(self, run_id: str) -> None:
        link = self.agent.link
        self.reported.pop(run_id, None)
        try:
            await link.call(link.api.forget_robot_copy, run_id)
        except (LinkDown, DepotRefused) as exc:
            log.info("the depot was not told that run %s left the robot (%s)", run_id, exc)
