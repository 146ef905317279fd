"""A pull's status follows its chunks as they are sent: the agent reports "sending" with its
counters so far (at most one report per FLEET_AGENT_PULL_PROGRESS_S), not "sending, 0 chunks" until
the depot's holding them is checked and the pull is done."""

from __future__ import annotations

import asyncio
from types import SimpleNamespace
from typing import Any

import pytest

from services.agent import reports as reports_mod
from services.agent.lanes import PullJob
from services.agent.pulls import PullSpec
from services.hot.index import HotEntry
from tests.waiting import wait_for_async

SPEC = PullSpec("pull-1", "run-1", [], [], None, None, None)


class FakeLink:
    def __init__(self) -> None:
        self.reported: list[tuple[str, int, int]] = []
        self.api = SimpleNamespace(pull_progress=self.pull_progress)

    def pull_progress(self, pull_id: str, *, state: str, chunks_sent: int, bytes_sent: int, **_: Any) -> None:
        self.reported.append((state, chunks_sent, bytes_sent))

    async def call(self, fn: Any, *args: Any, **kwargs: Any) -> Any:
        return fn(*args, **kwargs)


def test_a_pull_reports_its_chunks_as_they_are_sent(monkeypatch: pytest.MonkeyPatch):
    entries = [HotEntry("chunk", "recording", offset, 100) for offset in range(0, 500, 100)]
    monkeypatch.setattr(reports_mod, "select_pull", lambda *_: entries)
    link, jobs = FakeLink(), list[PullJob]()
    sender = SimpleNamespace(add_pull=jobs.append)
    recording = SimpleNamespace(path="run.rrd", size=500, timeline_types={})
    agent = SimpleNamespace(
        link=link,
        spool=SimpleNamespace(recording=lambda _: recording),
        sender_for=lambda _: sender,
        settings=SimpleNamespace(agent_pull_progress_s=0.05, agent_pull_poll_s=5.0),
    )

    async def scenario() -> None:
        serving = asyncio.create_task(reports_mod.Reports(agent)._serve(SPEC))  # type: ignore[arg-type]
        await wait_for_async(lambda: jobs, 10, "the pull handed to its sender")
        job: PullJob = jobs[0]
        for entry in entries[:2]:
            job.count(entry)  # sent; the depot's holding them is checked later
        await wait_for_async(lambda: ("sending", 2, 200) in link.reported, 10, "2 chunks reported sent")
        for entry in entries[2:]:
            job.count(entry)
        await wait_for_async(lambda: ("sending", 5, 500) in link.reported, 10, "5 chunks reported sent")
        job.done.set()
        await asyncio.wait_for(serving, 10)

    asyncio.run(scenario())
    assert link.reported[0] == ("sending", 0, 0) and link.reported[-1] == ("done", 5, 500), link.reported
    assert link.reported.count(("sending", 5, 500)) == 1  # reported when it changed, not every turn
