"""Triggers end to end, with auth on as robots run: a robot in summary mode (only /metrics/** live)
drives three minutes at 10 Hz with a camera and a lidar and brakes hard twice. The agent, holding the
depot's rules, finds the first brake on the robot while its uplink is cut, and sends that window's
camera and lidar chunks (with the latest-at state at its start) once the link is back; the second
brake's window is over the trigger's daily budget and stays on the robot, reported. The depot ends up
with exactly the summary and the first window, each chunk once; a person's pull of the first window
afterwards sends nothing, and of the second brings it home."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from services.runs.download import EntityFilter
from services.runs.latest_at import ChunkEntry, select_chunks
from tests.services.agent.harness import AgentProcess, Link, Robot, download, run_status
from tests.services.agent.test_agent_auth import ingest_token
from tests.services.agent.test_summary_pull import recording_chunks
from tests.services.ingest.live_server import LiveServer
from tests.waiting import wait_for

pytestmark = [pytest.mark.sdk, pytest.mark.slow]

ROBOT = str(Path(__file__).with_name("brake_robot.py"))
RUN = "run-brakes"
FRAMES = 1800  # three minutes at 10 Hz
BRAKES = (900, 1500)
WINDOW = ["/camera/**", "/lidar/**"]
BUDGET = 1_000_000  # one window of this drive (about 700 kB) fits in a day, not two
RULES = f"""
[[event]]
name = "hard_brake"
entity = "/metrics/brake"
when = "rises_above"
threshold = 5.0
timeline = "sim_time"
severity = "warn"

[[trigger]]
event = "hard_brake"
include = {WINDOW!r}
before_s = 10
after_s = 5
max_bytes_per_robot_day = {BUDGET}
priority = "high"
""".replace("'", '"')


@pytest.fixture
def depot(tmp_path: Path) -> Iterator[LiveServer]:
    server = LiveServer(tmp_path / "depot", auth="on").start()
    yield server
    server.stop()


def brake_robot(url: str, copy: Path, pauses: tuple[int, ...]) -> Robot:
    brakes, stops = ",".join(map(str, BRAKES)), ",".join(map(str, pauses))
    return Robot(url, str(copy), RUN, str(FRAMES), brakes, stops, script=ROBOT)


def events(depot: LiveServer) -> list[dict[str, Any]]:
    answer = httpx.get(f"{depot.url}/v1/runs/{RUN}/events", headers=depot.headers, timeout=10)
    if answer.status_code == 404:
        return []
    answer.raise_for_status()
    return sorted((e for e in answer.json()["events"] if e["kind"] == "hard_brake"), key=lambda e: e["start"])


def data_state(depot: LiveServer, index: int) -> str | None:
    found = events(depot)
    if len(found) <= index or found[index].get("data") is None:
        return None
    return str(found[index]["data"]["state"])


def window_chunks(copy: Path, event: dict[str, Any]) -> set[bytes]:
    """The camera and lidar chunks a window around `event` holds: overlapping [start - 10 s, end + 5 s]
    on sim_time, and per entity and component the newest before its start."""
    chunks = recording_chunks(copy)
    wanted = EntityFilter(WINDOW)
    entries = [ChunkEntry.of_meta(meta, True, "sim_time") for _, (entity, meta) in chunks.items() if wanted(entity)]
    bounds = (int(event["start"]) - 10 * 10**9, int(event["end"]) + 5 * 10**9)
    keep, _ = select_chunks(entries, bounds, True, lambda unknown: unknown)
    return keep


def pull_event(depot: LiveServer, event_id: str) -> dict[str, Any]:
    answer = httpx.post(f"{depot.url}/v1/events/{event_id}/pull", headers=depot.headers, timeout=10)
    assert answer.status_code in (200, 202), answer.text
    pull_id = answer.json()["pull"]["id"]

    def done() -> dict[str, Any] | None:
        pulls = httpx.get(f"{depot.url}/v1/runs/{RUN}/pulls", headers=depot.headers, timeout=10).json()["pulls"]
        pull: dict[str, Any] = next(p for p in pulls if p["id"] == pull_id)
        assert pull["state"] not in ("failed", "cancelled"), pull
        return pull if pull["state"] == "done" else None

    return wait_for(done, 90, f"the pull of event {event_id}")


def test_a_hard_brake_brings_its_window_home(depot: LiveServer, tmp_path: Path):
    applied = httpx.put(
        f"{depot.url}/v1/rules", content=RULES, headers={**depot.headers, "Content-Type": "text/plain"}, timeout=10
    )
    assert applied.status_code in (200, 201), applied.text
    link = Link(depot)
    agent = AgentProcess(
        tmp_path / "spool",
        link,
        token=ingest_token(depot, "robot-agent"),
        live_include="/metrics/**",
        rules_poll_s="0.5",
        pull_poll_s="0.5",
        # a check sends again what the depot does not hold of what was written before the previous
        # one: at 1 s, a busy machine's chunks still on their way are sent twice (stored once)
        check_s="5",
    ).start()
    copy = tmp_path / "copy.rrd"
    try:
        wait_for(lambda: agent.status().get("rules", {}).get("version") == 1, 30, "the agent to hold the rules")
        robot = brake_robot(agent.url, copy, pauses=(BRAKES[0] - 10, BRAKES[0] + 100, BRAKES[1] - 10))
        robot.expect(f"AT {BRAKES[0] - 10}")
        link.cut()  # the uplink is lost just before the first brake
        robot.go_on()
        robot.expect(f"AT {BRAKES[0] + 100}")  # the window's end (5 s after the brake) is spooled
        wait_for(
            lambda: any(w["state"] == "waiting" for w in agent.status()["windows"]), 30, "the robot to fire the window"
        )
        assert events(depot) == []  # nothing of it could reach the depot
        link.restore()
        wait_for(lambda: data_state(depot, 0) == "held", 90, "the first window at the depot after reconnection")
        robot.go_on()
        robot.expect(f"AT {BRAKES[1] - 10}")
        robot.go_on()
        robot.expect("DONE")
        assert robot.proc.wait(60) == 0
        wait_for(
            lambda: data_state(depot, 1) == "held on robot: over budget", 90, "the second window held: over budget"
        )
        assert agent.metric("fleet_agent_trigger_windows_over_budget") == 1
        pending = httpx.get(
            f"{depot.url}/v1/events", params={"pending": "true"}, headers=depot.headers, timeout=10
        ).json()["events"]
        first, second = events(depot)
        assert [e["id"] for e in pending] == [second["id"]]
        assert first["source"] == "robot" or first["source"].startswith("rule hard_brake@")

        wait_for(lambda: run_status(depot, RUN) == "closed", 60, "the run to close at the depot")
        chunks = recording_chunks(copy)
        summary = {cid for cid, (entity, _) in chunks.items() if EntityFilter(["/metrics/**"])(entity)}
        window = window_chunks(copy, first)
        assert window and window <= set(chunks)
        served = set(recording_chunks(download(depot, RUN, tmp_path / "served.rrd")))
        assert served == summary | window  # the first window, none elsewhere
        assert depot.metric("fleet_ingest_chunks_duplicate_total") == 0  # each chunk once

        again = pull_event(depot, first["id"])  # a person pulls the same window: nothing is sent twice
        assert again["chunks_sent"] == 0
        held = pull_event(depot, second["id"])  # and the one held over budget comes home on request
        assert held["chunks_sent"] > 0
        wait_for(lambda: data_state(depot, 1) == "held", 30, "the second window's data state")
        served = set(recording_chunks(download(depot, RUN, tmp_path / "served-2.rrd")))
        assert served == summary | window | window_chunks(copy, second)
        assert depot.metric("fleet_ingest_chunks_duplicate_total") == 0
        assert agent.metric("fleet_agent_triggers_fired") == 2
    finally:
        agent.stop()
        link.close()
