"""`robot.silent`: a robot whose live run has sent nothing for `silent_after_s` is told of, once per
silence (the occurrence is the run and the time of its last data: data that comes and stops again
makes a new one).

A run counts as live while ingest holds it live, while a stream still feeds it, or when it was
closed for being idle (`close_after_s`: a robot that stops sending is closed that way; one that
ends its stream is not silent)."""

from __future__ import annotations

import datetime as dt
from collections.abc import Iterable

from catalog import webhooks as rows
from catalog.db import session_scope
from catalog.webhooks import ROBOT_SILENT
from core.clock import iso_utc
from core.states import RunStatus
from services.ingest.view import HotRunView
from services.webhooks.service import Webhooks


def silent_pass(hooks: Webhooks, hot_runs: Iterable[HotRunView]) -> int:
    """Enqueue `robot.silent` for each silent run of `hot_runs` (ingest's `hot_runs()`); how many
    deliveries that added (a silence told already adds none)."""
    now = hooks.clock()
    silent_after = dt.timedelta(seconds=hooks.settings.silent_after_s)
    close_after = dt.timedelta(seconds=hooks.settings.close_after_s)
    silent = [run for run in hot_runs if _live(run, close_after) and now - run.last_data_at >= silent_after]
    if not silent:
        return 0
    added = 0
    with session_scope(hooks.catalog, write=True) as session:
        for run in silent:
            payload = {
                "run_id": run.run_id,
                "robot_id": run.robot_id or hooks.default_robot,
                "application_id": run.application_id,
                "last_data_at": iso_utc(run.last_data_at),
                "silent_s": round((now - run.last_data_at).total_seconds(), 3),
            }
            occurrence_id = f"{run.run_id}@{run.last_data_at.astimezone(dt.UTC):%Y%m%dT%H%M%S.%fZ}"
            added += rows.enqueue(session, ROBOT_SILENT, occurrence_id, payload, now=now)
    return added


def _live(run: HotRunView, close_after: dt.timedelta) -> bool:
    if run.status == RunStatus.LIVE or run.live_sources > 0:
        return True
    return run.ended_at is not None and run.ended_at - run.last_data_at >= close_after
