"""`fleet rules apply|show|history`, `fleet runs annotate|tag|untag` and `fleet events
ls|view|pull` against a real `fleet serve` with auth on: the admin token found beside the service, a
read token refused on writes in one line, an event's signed viewer link opened with no header, and
the events whose window is still on the robot listed and pulled."""

from __future__ import annotations

import json
import os
import shlex
import subprocess
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from tests.services.ingest.live_server import FLEET, LiveServer
from tests.services.rrd.recordings import Recording

pytestmark = pytest.mark.sdk

RULES = """\
[[event]]
name = "slow"
entity = "/robot/speed"
when = "below"
threshold = 0.1
"""
BAD = """\
[[event]]
name = "slow"
entity = "/robot/speed"
when = "below"
threshold = "fast"
colour = "red"
"""


@pytest.fixture(scope="module")
def depot(tmp_path_factory: pytest.TempPathFactory, recordings: dict[str, Recording]) -> Iterator[LiveServer]:
    """A depot with auth on holding the `points` recording."""
    live = LiveServer(tmp_path_factory.mktemp("cli-corpus") / "fleet-data", auth="on", auth_cache_s="0").start()
    try:
        uploaded = httpx.post(
            f"{live.url}/v1/uploads", content=recordings["points"].data, headers=live.headers, timeout=60
        )
        assert uploaded.status_code == 200, uploaded.text
        yield live
    finally:
        live.stop()


@pytest.fixture
def run_id(recordings: dict[str, Recording]) -> str:
    return str(recordings["points"].recordings[0]["recording_id"])


def fleet(live: LiveServer, *args: str, token: str | None = None) -> subprocess.CompletedProcess[str]:
    """`fleet ARGS` with the admin token found in the data dir, or `token` (FLEET_TOKEN)."""
    env = {k: v for k, v in os.environ.items() if k not in ("FLEET_TOKEN", "FLEET_DATA_DIR")}
    env = {**env, "FLEET_API_URL": live.url, "FLEET_DATA_DIR": str(live.data_dir)}
    if token is not None:
        env["FLEET_TOKEN"] = token
    return subprocess.run([FLEET, *args], env=env, capture_output=True, text=True, timeout=120)


def admin_name(live: LiveServer) -> str:
    return str(httpx.get(f"{live.url}/v1/whoami", headers=live.headers, timeout=10).json()["subject"])


def read_token(live: LiveServer) -> str:
    made = httpx.post(f"{live.url}/v1/tokens", json={"scopes": ["read"], "name": "rita"}, headers=live.headers)
    assert made.status_code == 201, made.status_code
    return str(made.json()["token"])


def test_rules_apply_show_history(depot: LiveServer, tmp_path: Path):
    good, bad = tmp_path / "rules.toml", tmp_path / "bad.toml"
    good.write_text(RULES)
    bad.write_text(BAD)
    refused = fleet(depot, "rules", "apply", str(bad))
    assert refused.returncode == 1 and refused.stdout == ""
    lines = refused.stderr.strip().splitlines()
    assert lines[0] == f"{bad}: 2 problem(s), nothing was applied:"
    assert sorted(line.split(": ")[0].strip() for line in lines[1:]) == [f"{bad}:5", f"{bad}:6"], lines
    assert "threshold" in refused.stderr and "colour" in refused.stderr
    assert "no rules applied yet" in fleet(depot, "rules", "show").stdout

    applied = fleet(depot, "rules", "apply", str(good))
    assert applied.returncode == 0, applied.stderr
    who = admin_name(depot)
    assert applied.stdout.strip() == f"rules version 1 applied by {who} (1 event rule(s), 0 metric rule(s))"
    again = fleet(depot, "rules", "apply", str(good))
    assert "unchanged: rules version 1" in again.stdout
    shown = fleet(depot, "rules", "show")
    assert shown.stdout.startswith(f"# rules version 1, applied by {who} at ") and RULES in shown.stdout
    history = json.loads(fleet(depot, "rules", "history", "--json").stdout)
    assert [(v["version"], v["created_by"]) for v in history] == [(1, who)] and history[0]["created_at"]
    assert who in fleet(depot, "rules", "history").stdout

    as_reader = fleet(depot, "rules", "apply", str(good), token=read_token(depot))
    assert as_reader.returncode == 1 and "needs the 'write' scope" in as_reader.stderr
    assert len(as_reader.stderr.strip().splitlines()) == 1


def test_annotate_then_find_and_open_the_event(depot: LiveServer, run_id: str):
    made = fleet(
        depot, "runs", "annotate", run_id, "--timeline", "frame", "--start", "102", "--end", "103",
        "--label", "points jump", "--severity", "warn", "--json",
    )  # fmt: skip
    assert made.returncode == 0, made.stderr
    event = json.loads(made.stdout)
    assert (event["run_id"], event["start"], event["end"], event["severity"]) == (run_id, 102, 103, "warn")
    assert event["source"] == admin_name(depot)

    listed = json.loads(fleet(depot, "events", "ls", "--run", run_id, "--severity", "warn", "--json").stdout)
    assert event["id"] in [e["id"] for e in listed["events"]]
    assert json.loads(fleet(depot, "events", "ls", "--kind", "no-such-kind", "--json").stdout)["events"] == []
    source = json.loads(fleet(depot, "events", "ls", "--source", event["source"], "--json").stdout)
    assert event["id"] in [e["id"] for e in source["events"]]
    table = fleet(depot, "events", "ls")
    assert table.returncode == 0 and event["id"] in table.stdout and "points jump" in table.stdout

    bad = fleet(depot, "runs", "annotate", run_id, "--timeline", "frame", "--start", "103", "--end", "102")
    assert bad.returncode == 1 and "before the start" in bad.stderr
    bad_time = fleet(depot, "runs", "annotate", run_id, "--timeline", "log_time", "--start", "soon")
    assert bad_time.returncode == 1 and "parameter 'start'" in bad_time.stderr

    viewed = fleet(depot, "events", "view", event["id"])
    assert viewed.returncode == 0, viewed.stderr
    exe, url = shlex.split(viewed.stdout)
    assert Path(exe).name == "rerun" and f"/v1/runs/{run_id}/recording.rrd?" in url and "sig=" in url
    opened = httpx.get(url, timeout=60)  # no header: the signed link is the grant
    assert opened.status_code == 200 and opened.content[:4] == b"RRF2"
    missing = fleet(depot, "events", "view", "ev-0000000000000000")
    assert missing.returncode == 1 and "no event" in missing.stderr


def test_tag_and_untag(depot: LiveServer, run_id: str):
    tagged = fleet(depot, "runs", "tag", run_id, "night-shift", "dock-2")
    assert tagged.returncode == 0, tagged.stderr
    who = admin_name(depot)
    assert f"{run_id}  night-shift  added by {who}" in tagged.stdout and "dock-2" in tagged.stdout
    untagged = fleet(depot, "runs", "untag", run_id, "dock-2")
    assert untagged.returncode == 0 and "dock-2" not in untagged.stdout and "night-shift" in untagged.stdout
    bad = fleet(depot, "runs", "tag", run_id, "two words")
    assert bad.returncode == 1 and "parameter 'tags'" in bad.stderr
    unknown = fleet(depot, "runs", "tag", "no-such-run", "x")
    assert unknown.returncode == 1 and "no run 'no-such-run'" in unknown.stderr
    as_reader = fleet(depot, "runs", "untag", run_id, "night-shift", token=read_token(depot))
    assert as_reader.returncode == 1 and "needs the 'write' scope" in as_reader.stderr


def test_events_waiting_for_their_window_and_pulling_one(depot: LiveServer, run_id: str):
    body = {
        "pull_id": "pull-00000000c11a",
        "rules_version": 1,
        "event": {"kind": "slow", "severity": "warn", "timeline": "frame", "timeline_type": "sequence",
                  "start": 120, "end": 121},
        "window": {"timeline": "frame", "start": "110", "end": "126", "include": ["/points/**"]},
        "priority": "normal", "state": "held", "error": "over budget: 0 bytes left today",
    }  # fmt: skip
    reported = httpx.post(f"{depot.url}/v1/runs/{run_id}/triggered", json=body, headers=depot.headers, timeout=30)
    assert reported.status_code == 201, reported.text
    event_id = reported.json()["event"]["id"]
    table = fleet(depot, "events", "ls", "--pending")
    assert table.returncode == 0 and event_id in table.stdout and "held on robot: over budget" in table.stdout
    waiting = json.loads(fleet(depot, "events", "ls", "--pending", "--json").stdout)["events"]
    assert [e["id"] for e in waiting] == [event_id]  # the annotations and others: none waits for a window

    pulled = fleet(depot, "events", "pull", event_id)
    assert pulled.returncode == 0, pulled.stderr
    pull_id = pulled.stdout.split(":")[0]
    assert pulled.stdout.startswith("pull-") and "pending" in pulled.stdout and "frame 110..126" in pulled.stdout
    again = json.loads(fleet(depot, "events", "pull", event_id, "--json").stdout)
    assert again["id"] == pull_id and (again["origin"], again["event_id"]) == ("person", event_id)
    shown = json.loads(fleet(depot, "events", "view", event_id, "--json").stdout)
    assert shown["data"]["state"] == "pending" and shown["data"]["pulls"][0]["id"] == pull_id

    made = fleet(depot, "runs", "annotate", run_id, "--timeline", "frame", "--start", "5", "--json")
    annotation = json.loads(made.stdout)["id"]
    refused = fleet(depot, "events", "pull", annotation)
    assert refused.returncode == 1 and "pulled by no trigger" in refused.stderr
    as_reader = fleet(depot, "events", "pull", event_id, token=read_token(depot))
    assert as_reader.returncode == 1 and "needs the 'write' scope" in as_reader.stderr
