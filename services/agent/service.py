"""`fleet agent`: the robot's local proxy and spool, and the forwarding of its runs to the depot.

The robot's SDK streams to the agent (`rerun+http://127.0.0.1:9876/proxy`) as it would to the depot;
the agent files every message into its spool first (so the SDK never sees the depot's link break)
and a sender per run forwards the run to the depot on a stream of its own, with the robot's token.
Watched folders bring the runs of robots that only write files. The state of each run's forwarding
lives in SQLite beside the spool, so a restart resumes where the last process stopped.
"""

from __future__ import annotations

import asyncio
import contextlib
import datetime as dt
import logging
import time
from collections.abc import Coroutine
from pathlib import Path
from typing import Any

import grpc

from services.agent.bagsend import BagSender, depot_client
from services.agent.bandwidth import RateSchedule, TokenBucket
from services.agent.files import FileProgress
from services.agent.link import DepotLink, DepotRefused, LinkDown, default_api_url
from services.agent.metrics import serve_metrics
from services.agent.reports import REPORT_S, Reports
from services.agent.retention import RetentionReport, enforce
from services.agent.rules import AgentRules
from services.agent.sender import Forwarding, RunSender
from services.agent.settings import AgentSettings
from services.agent.spool import Spool, store_infos
from services.agent.state import AgentState, RunState
from services.agent.triggers import TriggerObserver, Triggers
from services.agent.watch import FileWatcher
from services.ingest import grpc_handler
from services.rrd.messages import Event, StreamStart
from services.runs.download import EntityFilter
from services.startup import listen, split_addr

log = logging.getLogger("fleet.agent")

DISCOVER_S = 0.2  # how often new spooled runs are looked for
HEARTBEAT_S = 2.0
RETENTION_S = 10.0


async def run_agent(settings: AgentSettings) -> None:
    """Build the agent on the running event loop (its gRPC channel belongs to that loop) and serve."""
    await Agent(settings).serve()


class Agent:
    def __init__(self, settings: AgentSettings) -> None:
        self.settings = settings
        self.rules = AgentRules(settings.agent_spool)
        observer = TriggerObserver(self.rules)
        self.spool = Spool(settings, observer)
        self.state = AgentState(settings.agent_spool)
        token = settings.agent_token.get_secret_value() if settings.agent_token else None
        api_url = settings.agent_api_url or default_api_url(settings.agent_depot)
        self.link = DepotLink(settings.agent_depot, api_url, token, max_message_size=settings.max_message_size)
        self.schedule = RateSchedule.from_config(settings.agent_bandwidth_rules, settings.agent_bandwidth)
        self.bucket = TokenBucket(self.schedule)
        self.forwarding = Forwarding(
            self.spool,
            self.link,
            self.bucket,
            self.state,
            EntityFilter(settings.agent_live_include, settings.agent_live_exclude),
            settings.agent_check_s,
            settings.agent_stall_s,
        )
        self.senders: dict[str, asyncio.Task[None]] = {}
        self.runners: dict[str, RunSender] = {}
        # where each run's forwarding stands: read once, then kept here (senders change these objects
        # and save them); the SQLite copy is for the next start and `fleet agent status`
        self.run_states: dict[str, RunState] = self.state.runs()
        self.started_at = time.time()
        self.retention: RetentionReport | None = None
        self.reports = Reports(self)
        self.triggers = Triggers(self, observer)
        # MCAP files (rosbag2 bags) in the watched folders: uploaded whole, each once
        self.bags = (
            BagSender(
                settings.agent_watch,
                self.state,
                depot_client(api_url, token),
                bucket=self.bucket,
                idle_s=settings.agent_bag_idle_s,
                on_answer=self.link.mark_up,
            )
            if settings.agent_watch
            else None
        )
        self._tasks: set[asyncio.Task[None]] = set()

    # --- runs -----------------------------------------------------------------------------------

    def discover(self) -> None:
        """Start a sender for every spooled run that is not confirmed and has none."""
        for run in self.spool.runs():
            state = self.run_states.get(run.run_id)
            if state is None or not state.confirmed:
                self.sender_for(run.run_id)

    def sender_for(self, run_id: str) -> RunSender:
        """The run's sender, started if it is not running (a pull may need one for a confirmed run)."""
        sender = self.runners.get(run_id)
        task = self.senders.get(run_id)
        if sender is not None and task is not None and not task.done():
            return sender
        state = self.run_states.get(run_id)
        fresh = state is None
        if state is None:
            state = self.run_states[run_id] = RunState(run_id)
            self.state.save_run(state)
        new = RunSender(self.forwarding, run_id, state, fresh=fresh)
        log.info("forwarding run %s (%s)", run_id, "new" if fresh else f"from byte {state.checked_until}")
        if sender is not None:
            new.pulls = sender.pulls  # pulls given to a sender that stopped
        self.runners[run_id] = new
        self.senders[run_id] = asyncio.create_task(new.run(), name=f"forward {run_id}")
        return new

    def bucket_cap(self) -> int | None:
        return self.schedule.current()

    def keep_last_day(self) -> RetentionReport:
        """Delete the spooled runs the depot holds sealed that are old enough, or too many."""
        self.retention = enforce(
            self.spool,
            self.state,
            retain=dt.timedelta(hours=self.settings.agent_retain_hours),
            max_bytes=self.settings.agent_max_bytes,
            free_target=2 * self.settings.agent_min_free_bytes,  # "nearly full": twice the hard limit
            keep=self.triggers.protected_runs(),
        )
        for deletion in self.retention.deleted:
            self.runners.pop(deletion.run_id, None)
            self.senders.pop(deletion.run_id, None)
            self.run_states.pop(deletion.run_id, None)
            self.triggers.forget_run(deletion.run_id)
            self._background(self.reports.forget_copy(deletion.run_id))
        return self.retention

    def _background(self, work: Coroutine[Any, Any, None]) -> None:
        task = asyncio.create_task(work)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _watch_link(self) -> None:
        """Probe the depot every half `agent_stall_s`: a silent link is found even when nothing waits
        on it (data written into buffers that never drain)."""
        stall_s = self.settings.agent_stall_s
        while True:
            try:
                await self.link.probe(stall_s)
            except Exception:  # never the end of the watch
                log.exception("probing the depot failed")
            await asyncio.sleep(stall_s / 2)

    async def _report_loop(self) -> None:
        """Poll for pulls and report robot copies; a depot that does not answer is asked again later."""
        reported = 0.0
        while True:
            try:
                await self.reports.poll_pulls()
                if time.monotonic() - reported > REPORT_S:
                    reported = time.monotonic()
                    await self.reports.report_copies()
            except (LinkDown, DepotRefused) as exc:
                log.debug("pulls and reports wait for the depot: %s", exc)
            except Exception:  # never the end of the loop: said, and tried again
                log.exception("pulls and reports failed")
            await asyncio.sleep(self.settings.agent_pull_poll_s)

    async def _rules_loop(self) -> None:
        """Follow the depot's rules (the last copy is used while the depot does not answer)."""
        while True:
            try:
                self.rules.take(await self.link.call(self.link.api.rules))
            except (LinkDown, DepotRefused) as exc:
                log.debug("rules not refreshed: %s", exc)
            except Exception:  # never the end of the loop: said, and tried again
                log.exception("refreshing the rules failed")
            await asyncio.sleep(self.settings.agent_rules_poll_s)

    async def _discover_loop(self) -> None:
        beat = kept = 0.0
        while True:
            try:
                self.spool.ingest.close_idle()
                self.discover()
                if time.monotonic() - kept > RETENTION_S:
                    kept = time.monotonic()
                    self.keep_last_day()
            except Exception:  # never the end of the loop: said, and tried again
                log.exception("looking after the spool failed")
            if time.monotonic() - beat > HEARTBEAT_S:
                beat = time.monotonic()
                progress = {
                    run_id: {"sent_until": sender.sent_until, "open": self._open(run_id)}
                    for run_id, sender in self.runners.items()
                }
                await asyncio.to_thread(self._heartbeat, progress)
            await asyncio.sleep(DISCOVER_S)

    def _open(self, run_id: str) -> bool:
        run = self.spool.run(run_id)
        return run is not None and self.spool.is_open(run)

    def _heartbeat(self, progress: dict[str, Any]) -> None:
        self.state.set_fact("progress", progress)
        self.state.set_fact("agent", {"started_at": self.started_at, "listen": self.settings.agent_listen})
        self.state.set_fact(
            "link",
            {"up": self.link.up, "since": self.link.since, "error": self.link.error, "refused": self.link.refused},
        )
        self.state.set_fact("counters", dict(self.forwarding.counters))
        self.state.set_fact("rules", self.rules.status())
        self.state.set_fact("triggers", dict(self.triggers.counters))
        if self.bags is not None:
            self.state.set_fact("bags", self.bags.counts.as_dict())
        if self.retention is not None:
            self.state.set_fact(
                "retention",
                {"over_by": self.retention.over_by, "unconfirmed_bytes": self.retention.unconfirmed_bytes},
            )

    # --- watched files -----------------------------------------------------------------------------

    async def file_events(self, path: Path, events: list[Event], progress: FileProgress) -> None:
        """A watched file's new messages: filed, then where the file stands saved (a crash in
        between reads them again; their chunks are already held, so nothing is filed twice)."""
        infos = None
        if events and not isinstance(events[0], StreamStart) and not self.spool.reading(path):
            infos = await asyncio.to_thread(store_infos, path)  # resumed mid-file after a restart
        self.spool.file_events(path, events, infos)
        await asyncio.to_thread(self.state.save_file, progress.path, progress.to_dict())

    async def file_complete(self, path: Path, progress: FileProgress) -> None:
        self.spool.file_done(path)
        await asyncio.to_thread(self.state.save_file, progress.path, progress.to_dict())

    def _watcher(self) -> FileWatcher | None:
        if not self.settings.agent_watch:
            return None
        known = []
        for path, saved in self.state.file_progress().items():
            try:
                known.append(FileProgress.from_dict(saved))
            except ValueError as exc:
                log.warning("forgetting where file %s stood (%s): it is read again", path, exc)
        return FileWatcher(
            self.settings.agent_watch,
            self.file_events,
            self.file_complete,
            progress=known,
            idle_s=self.settings.agent_file_idle_s,
            max_message_size=self.settings.max_message_size,
        )

    # --- serving ----------------------------------------------------------------------------------

    async def serve(self) -> None:
        """Run until cancelled."""
        host, port = split_addr(self.settings.agent_listen)
        listen(host, port, "agent's SDK", "agent_listen").close()  # a port in use: one line, before anything
        status_host, status_port = split_addr(self.settings.agent_status_addr)
        listen(status_host, status_port, "agent's status", "agent_status_addr").close()
        recovered = self.spool.recover()
        if recovered:
            log.info("spool: %d runs recovered", len(recovered))
        server = grpc.aio.server(options=grpc_handler.server_options(self.settings.max_message_size))
        grpc_handler.add_to_server(server, grpc_handler.MessageProxy(self.spool.ingest))
        server.add_insecure_port(self.settings.agent_listen)
        await server.start()
        serve_metrics(self, status_host, status_port)
        log.info("agent listening on %s, forwarding to %s", self.settings.agent_listen, self.settings.agent_depot)
        tasks = [
            asyncio.create_task(self._discover_loop(), name="discover"),
            asyncio.create_task(self._report_loop(), name="pulls and reports"),
            asyncio.create_task(self._watch_link(), name="link watch"),
            asyncio.create_task(self._rules_loop(), name="rules"),
            asyncio.create_task(self.triggers.run(), name="triggers"),
        ]
        watcher = self._watcher()
        if watcher is not None:
            tasks.append(asyncio.create_task(watcher.run(), name="watch files"))
            log.info("watching %s for .rrd and .mcap files", ", ".join(map(str, self.settings.agent_watch)))
        if self.bags is not None:
            tasks.append(asyncio.create_task(self.bags.run(), name="upload bags"))
        try:
            await asyncio.gather(*tasks)
        finally:
            for task in [*tasks, *self.senders.values()]:
                task.cancel()
            for task in [*tasks, *self.senders.values()]:
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await task
            await server.stop(grace=2)
            await self.link.close()
            if self.bags is not None:
                await self.bags.client.aclose()
            self.spool.close()
            self.state.close()
