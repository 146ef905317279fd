"""Benchmark: a trigger on the robot, from a hard brake to its window held at the depot, and what
evaluating the rules costs the agent.

    .venv/bin/python benchmarks/triggers.py [--seconds 30] [--brake-at 15] [--rate-hz 10] [--camera jpeg|raw]
                                            [--repeat 2] [--json]

A depot (`fleet serve`, auth off, a temporary data dir, free loopback ports) and, per phase, a new
agent in summary mode (`FLEET_AGENT_LIVE_INCLUDE=/metrics/**`: the camera and the lidar stay on the
robot) run on this machine. The robot (`benchmarks/agent_robot.py`, the real SDK: a camera image, a
10,000-point lidar sweep, nine scalars, a pose and a log line per frame, at --rate-hz for --seconds
in real time) brakes hard once, at --brake-at seconds (`/metrics/brake` spikes).

1. Peer: no rules at the depot (an empty rules file applied). The agent forwards the summary only.
2. Rules: the depot holds a `hard_brake` event rule (`/metrics/brake` rises above 5, on log_time) and
   a `[[trigger]]` bringing `/world/robot/camera` and `/world/robot/lidar` home for 10 s before to
   5 s after it, priority high. The agent fetches them, evaluates them over everything it spools,
   and sends the window when the brake is found and its last 5 s are spooled.

Measured per phase: the agent's CPU (user + system, psutil) from the robot's first frame to its
last flush, in seconds and % of one core; for the rules phase, the time from the brake (the robot's
wall clock when it logged the spike) until the depot's event says its window is held (`data.state`,
polled every 50 ms), and that time less the 5 s after the brake that the window must wait for.
The phases alternate --repeat times; the figures are each phase's median.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import httpx

ROOT = Path(__file__).resolve().parents[1]
sys.path[:] = [str(ROOT), *(p for p in sys.path if p not in (str(ROOT), str(ROOT / "benchmarks")))]

from benchmarks.agent import AgentServer, Meter, RobotProcess, positive_seconds  # noqa: E402
from benchmarks.codec import format_table, log  # noqa: E402
from benchmarks.ingest import FleetServer  # noqa: E402

AFTER_S = 5
RULES = f"""
[[event]]
name = "hard_brake"
entity = "/metrics/brake"
when = "rises_above"
threshold = 5.0
severity = "warn"

[[trigger]]
event = "hard_brake"
include = ["/world/robot/camera", "/world/robot/lidar"]
before_s = 10
after_s = {AFTER_S}
priority = "high"
"""
POLL_S = 0.05
HELD_TIMEOUT_S = 120.0


class HeldWatch:
    """On a thread from the robot's start: when the depot's hard_brake event of the run first says
    its window is held (wall clock)."""

    def __init__(self, depot: FleetServer, run_id: str) -> None:
        self.depot, self.run_id = depot, run_id
        self.at: float | None = None
        self.thread = threading.Thread(target=self._watch, daemon=True)
        self.thread.start()

    def _watch(self) -> None:
        deadline = time.monotonic() + HELD_TIMEOUT_S
        with httpx.Client(base_url=f"http://127.0.0.1:{self.depot.http_port}", timeout=10) as client:
            while time.monotonic() < deadline:
                answer = client.get(f"/v1/runs/{self.run_id}/events")
                if answer.status_code == 200:
                    for event in answer.json()["events"]:
                        if event["kind"] == "hard_brake" and (event.get("data") or {}).get("state") == "held":
                            self.at = time.time()
                            return
                time.sleep(POLL_S)  # polling the depot, bounded by the deadline

    def result(self) -> float:
        self.thread.join()
        if self.at is None:
            raise SystemExit(f"the brake's window was not held at the depot after {HELD_TIMEOUT_S:g} s")
        return self.at


def set_rules(depot: FleetServer, text: str) -> None:
    httpx.put(
        f"http://127.0.0.1:{depot.http_port}/v1/rules", content=text, headers={"Content-Type": "text/plain"}, timeout=10
    ).raise_for_status()


def phase(name: str, depot: FleetServer, args: argparse.Namespace, workdir: Path, turn: int) -> dict[str, Any]:
    agent = AgentServer(
        workdir / f"agent-{name}-{turn}",
        depot.grpc_port,
        depot.http_port,
        live_include="/metrics/**",
        rules_poll_s="0.5",
        pull_poll_s="0.5",
    )
    agent.workdir.mkdir()
    agent.start()
    try:
        time.sleep(2)  # the agent's first polls of the rules (every 0.5 s): it runs them before the robot starts
        run_id = f"bench-{name}-{turn}"
        meter = Meter(agent.pid)
        robot = RobotProcess(
            agent.url,
            workdir / f"{run_id}.rrd",
            run_id,
            args.seconds,
            args.rate_hz,
            args.camera,
            args.brake_at if name == "rules" else None,
        )
        try:
            cpu0 = meter.cpu_s()
            log(f"{name} #{turn + 1}: streaming {args.seconds:g} s at {args.rate_hz:g} Hz ...")
            watch = HeldWatch(depot, run_id) if name == "rules" else None
            robot.go()
            figures = robot.result()
            cpu = meter.cpu_s() - cpu0
            stream_s = figures["flushed"] - figures["start"]
            result = {"phase": name, "agent_cpu_s": cpu, "agent_cpu_pct": 100 * cpu / stream_s}
            if watch is not None:
                latency = watch.result() - float(figures["brake_wall"])
                result |= {"brake_to_held_s": latency, "after_window_end_s": latency - AFTER_S}
            robot.finish()
            return result
        finally:
            robot.close()
    finally:
        agent.stop()


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=positive_seconds, default=30.0)
    parser.add_argument("--brake-at", type=positive_seconds, default=15.0)
    parser.add_argument("--rate-hz", type=positive_seconds, default=10.0)
    parser.add_argument("--camera", choices=("jpeg", "raw"), default="jpeg")
    parser.add_argument("--repeat", type=int, default=2)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    if args.brake_at + AFTER_S >= args.seconds:
        parser.error(f"--brake-at must leave the window's {AFTER_S} s after it within --seconds")
    with tempfile.TemporaryDirectory(prefix="fleet-triggers-bench-") as tmp:
        workdir = Path(tmp)
        depot = FleetServer(workdir)
        depot.start()
        try:
            results = []
            for turn in range(args.repeat):
                set_rules(depot, "")  # the peer: an agent with no rules to run
                results.append(phase("peer", depot, args, workdir, turn))
                set_rules(depot, RULES)
                results.append(phase("rules", depot, args, workdir, turn))
        finally:
            depot.stop()
    report(results, args)


def report(results: list[dict[str, Any]], args: argparse.Namespace) -> None:
    def median(name: str, key: str) -> float:
        return float(statistics.median(float(r[key]) for r in results if r["phase"] == name))

    summary = {
        "agent_cpu_pct_peer": median("peer", "agent_cpu_pct"),
        "agent_cpu_pct_rules": median("rules", "agent_cpu_pct"),
        "brake_to_held_s": median("rules", "brake_to_held_s"),
        "after_window_end_s": median("rules", "after_window_end_s"),
        "runs": results,
    }
    if args.json:
        print(json.dumps(summary, indent=2))
        return
    rows = [
        ["agent CPU, % of one core", f"{summary['agent_cpu_pct_rules']:.1f}", f"{summary['agent_cpu_pct_peer']:.1f}"],
        ["brake -> window held at the depot, s", f"{summary['brake_to_held_s']:.2f}", "-"],
        [f"  of which after the window's end (+{AFTER_S} s), s", f"{summary['after_window_end_s']:.2f}", "-"],
    ]
    print(format_table(["", "agent with triggers", "agent, summary only (peer)"], rows, "lrr"))


if __name__ == "__main__":
    main()
