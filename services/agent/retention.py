"""The robot keeps its last day: spooled runs are deleted once the depot holds them sealed, after
`agent_retain_hours`, or sooner, oldest first, when the spool outgrows `agent_max_bytes`.

A run the depot has not confirmed is never deleted: when the spool is over its size and nothing
more can go, the agent says so loudly (a warning each time, and `fleet agent status`) and keeps
accepting data until the disk's hard limit (`agent_min_free_bytes`), where new data is refused.
The disk nearly full (free space under twice `agent_min_free_bytes`) is pressure too.
A confirmed run may still hold chunks the live rules kept on the robot (never pulled): those go
with it at its age, or under pressure after every run without such chunks, and the log names them.
A run holding a trigger's window the depot does not hold yet (waiting, sending, or held over its
budget until a person pulls it) is kept as an unconfirmed one is.
"""

from __future__ import annotations

import datetime as dt
import logging
import shutil
from collections.abc import Callable, Collection
from dataclasses import dataclass

from core.clock import utcnow
from services.agent.spool import Spool
from services.agent.state import AgentState, RunState
from services.ingest.view import HotRunView

log = logging.getLogger("fleet.agent")


@dataclass(frozen=True)
class Deletion:
    run_id: str
    bytes: int
    why: str  # "age" | "size"
    local_only_bytes: int  # of them, bytes the depot never received (kept on the robot by the live rules)


@dataclass(frozen=True)
class RetentionReport:
    deleted: list[Deletion]
    spool_bytes: int
    unconfirmed_bytes: int
    over_by: int  # bytes still to free that only unconfirmed runs hold (0: no pressure left)


def enforce(
    spool: Spool,
    state: AgentState,
    *,
    retain: dt.timedelta,
    max_bytes: int,
    now: dt.datetime | None = None,
    free_target: int = 0,
    disk_free: Callable[[], int] | None = None,
    keep: Collection[str] = (),
) -> RetentionReport:
    """Delete what may go (re-runnable: each call looks at the spool as it is). Under pressure
    (the spool over `max_bytes`, or the disk's free space under `free_target`), confirmed runs go
    oldest first until it is relieved. `keep`: runs kept whatever their age (a trigger's window in
    them the depot does not hold yet)."""
    now = now or utcnow()
    saved = state.runs()
    runs = [run for run in spool.runs() if not spool.is_open(run) and run.run_id not in keep]
    confirmed = sorted((run for run in runs if _confirmed(saved.get(run.run_id))), key=lambda run: run.last_data_at)
    deleted = [
        _delete(spool, state, run, saved[run.run_id], "age") for run in confirmed if now - run.last_data_at >= retain
    ]
    gone = {d.run_id for d in deleted}
    total = spool.size()
    free = (disk_free or (lambda: shutil.disk_usage(spool.root).free))() if free_target else 0
    need = max(total - max_bytes if max_bytes else 0, free_target - free if free_target else 0)
    # runs the depot holds whole first, then those that take robot-only chunks with them
    for run in sorted(
        (run for run in confirmed if run.run_id not in gone),
        key=lambda run: (saved[run.run_id].local_only_bytes > 0, run.last_data_at),
    ):
        if need <= 0:
            break
        deletion = _delete(spool, state, run, saved[run.run_id], "size" if total > max_bytes > 0 else "disk")
        deleted.append(deletion)
        total -= max(deletion.bytes, 0)  # -1: kept (something feeds it again)
        need -= max(deletion.bytes, 0)
    deleted = [d for d in deleted if d.bytes >= 0]
    unconfirmed = sum(run.size for run in spool.runs() if not _confirmed(saved.get(run.run_id)))
    over_by = max(need, 0)
    if over_by:
        log.warning(
            "spool %s needs %d bytes freed (agent_max_bytes %d, disk free %s, kept free: %d) and the depot has "
            "confirmed none of the %d bytes left: nothing is deleted until it does; new data is refused only "
            "when the disk's free space falls below agent_min_free_bytes",
            spool.root,
            over_by,
            max_bytes,
            free if free_target else "unchecked",
            free_target,
            unconfirmed,
        )
    return RetentionReport(deleted, total, unconfirmed, over_by)


def _confirmed(run: RunState | None) -> bool:
    return run is not None and run.confirmed


def _delete(spool: Spool, state: AgentState, run: HotRunView, saved: RunState, why: str) -> Deletion:
    size = run.size
    if not spool.remove(run.run_id):
        return Deletion(run.run_id, -1, why, 0)  # something feeds it again: kept
    state.forget_run(run.run_id)
    if saved.local_only_bytes:
        log.warning(
            "deleted run %s from the spool (%s): the depot holds what was sent; %d bytes kept on the robot "
            "only (never pulled) are gone with it",
            run.run_id,
            why,
            saved.local_only_bytes,
        )
    else:
        log.info("deleted run %s from the spool (%s): the depot holds it sealed", run.run_id, why)
    return Deletion(run.run_id, size, why, saved.local_only_bytes)
