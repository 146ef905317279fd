"""`fleet agent status`: where each spooled run stands, read from the spool and its state file, so it
answers whether the agent runs or not (a running agent writes its link and progress every few
seconds; an old heartbeat says it stopped)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from services.agent.spool import RUNS_DIR
from services.agent.state import STATE_FILE, AgentState, BagRecord, PullState
from services.agent.windows import TRIGGER_KIND
from services.hot.store import RUN_FILE

STALE_S = 10.0  # a heartbeat older than this: the agent is not running


def status_report(spool: Path) -> dict[str, Any]:
    """The agent's state as plain values (what `fleet agent status` prints, and `--json` shows)."""
    if not (spool / STATE_FILE).is_file():
        return {"spool": str(spool), "running": False, "error": f"no agent state in {spool}: is this the spool?"}
    state = AgentState(spool, readonly=True)
    try:
        facts = state.facts()
        saved = state.runs()
        pulls = state.pulls()
        bags = state.bags()
    finally:
        state.close()
    heartbeat = float(facts["agent"][1]) if "agent" in facts else 0.0
    live = facts.get("progress", ({}, 0.0))[0]
    runs: list[dict[str, Any]] = []
    for path in sorted((spool / RUNS_DIR).glob(f"*/{RUN_FILE}")):
        run_id = path.parent.name
        size = path.stat().st_size
        run = saved.get(run_id)
        progress = live.get(run_id, {})
        checked = run.checked_until if run else 0
        runs.append(
            {
                "run": run_id,
                "local_bytes": size,
                "open": bool(progress.get("open", False)),
                "sent_bytes": min(int(progress.get("sent_until", checked)), size),
                "unconfirmed_at_depot_bytes": max(size - checked, 0) if not (run and run.confirmed) else 0,
                "local_only_chunks": run.local_only_chunks if run else 0,
                "local_only_bytes": run.local_only_bytes if run else 0,
                "depot_tier": run.depot_tier if run else None,
                "confirmed": bool(run and run.confirmed),
            }
        )
    backlog = sum(max(r["local_bytes"] - r["sent_bytes"], 0) for r in runs if not r["confirmed"])
    return {
        "spool": str(spool),
        "running": time.time() - heartbeat < STALE_S,
        "heartbeat_age_s": round(time.time() - heartbeat, 1) if heartbeat else None,
        "link": facts.get("link", ({}, 0.0))[0],
        "counters": facts.get("counters", ({}, 0.0))[0],
        "retention": facts.get("retention", ({}, 0.0))[0],
        "backlog_bytes": backlog,
        "spool_bytes": sum(r["local_bytes"] for r in runs),
        "runs": runs,
        "pulls": [vars(p) for p in pulls.values() if p.spec.get("kind") != TRIGGER_KIND],
        "rules": facts.get("rules", ({}, 0.0))[0],
        "triggers": facts.get("triggers", ({}, 0.0))[0],
        "windows": [_window(p) for p in pulls.values() if p.spec.get("kind") == TRIGGER_KIND],
        "bags": _bags(bags, facts.get("bags", ({}, 0.0))[0]),
    }


def _bags(records: dict[str, BagRecord], live: dict[str, Any]) -> dict[str, Any]:
    """The watched MCAP files: how many wait, were uploaded or refused, and each refusal. The
    counts are the running agent's (it alone knows which files are still being written); with no
    heartbeat, those of the state file."""
    failed = [r for r in records.values() if r.state == "failed"]
    return {
        "pending": int(live.get("pending", 0)),
        "uploaded": int(live.get("uploaded", sum(r.state == "uploaded" for r in records.values()))),
        "failed": int(live.get("failed", len(failed))),
        "uploading": live.get("uploading"),
        "error": live.get("error"),
        "failures": [{"path": r.path, "run": r.run_id, "error": r.error} for r in sorted(failed, key=lambda r: r.path)],
    }


def _window(pull: PullState) -> dict[str, Any]:
    spec = pull.spec
    return {
        "window": pull.pull_id,
        "run": pull.run_id,
        "event": (spec.get("event") or {}).get("kind"),
        "state": pull.state,
        "chunks_sent": pull.chunks_sent,
        "bytes_sent": pull.bytes_sent,
        "error": spec.get("error"),
    }
