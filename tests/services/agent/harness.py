"""The agent and the depot as real processes for end-to-end tests, the link between them through
loopback TCP proxies the test can cut and restore, and a robot on the real SDK."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
from prometheus_client.parser import text_string_to_metric_families

from services.agent.status import status_report
from tests.services.ingest.live_server import FLEET, LiveServer
from tests.subprocess_server import ServerProcess, free_port
from tests.tcp_proxy import FORWARD, REFUSE, TcpProxy
from tests.waiting import wait_for

ROBOT = str(Path(__file__).with_name("robot.py"))


def listening(port: int) -> Callable[[], bool]:
    def check() -> bool:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1).close()
        except OSError:
            return False
        return True

    return check


class Link:
    """The robot's link to the depot: its gRPC and REST connections, each through a proxy."""

    def __init__(self, depot: LiveServer) -> None:
        self.grpc = TcpProxy("127.0.0.1", depot.grpc_port)
        self.rest = TcpProxy("127.0.0.1", depot.http_port)

    def cut(self, mode: str = REFUSE) -> None:
        """REFUSE: connections reset and refused (a router that says so); HANG: bytes stop going
        through and nothing answers (a radio out of range), which only keepalives notice."""
        self.grpc.set_mode(mode)
        self.rest.set_mode(mode)

    def restore(self) -> None:
        self.grpc.set_mode(FORWARD)
        self.rest.set_mode(FORWARD)

    def close(self) -> None:
        self.grpc.close()
        self.rest.close()


class AgentProcess:
    """`fleet agent` on a free loopback port, forwarding through `link`."""

    def __init__(self, spool: Path, link: Link, **settings: str) -> None:
        self.spool = spool
        self.port = free_port()
        self.log = spool.parent / f"{spool.name}-agent.log"
        self.status_port = free_port()
        env = {
            **os.environ,
            "FLEET_AGENT_SPOOL": str(spool),
            "FLEET_AGENT_LISTEN": f"127.0.0.1:{self.port}",
            "FLEET_AGENT_STATUS_ADDR": f"127.0.0.1:{self.status_port}",
            "FLEET_AGENT_DEPOT": f"rerun+http://127.0.0.1:{link.grpc.port}",
            "FLEET_AGENT_API_URL": f"http://127.0.0.1:{link.rest.port}",
            "FLEET_AGENT_CHECK_S": "1",
            **{f"FLEET_AGENT_{k.upper()}": v for k, v in settings.items()},
        }
        self.process = ServerProcess(
            [FLEET, "agent"], log=self.log, ready=listening(self.port), env=env, name="fleet agent"
        )

    @property
    def url(self) -> str:
        return f"rerun+http://127.0.0.1:{self.port}/proxy"

    def start(self) -> AgentProcess:
        self.process.start()
        return self

    def kill(self) -> None:
        self.process.kill()

    def stop(self) -> None:
        self.process.stop()

    def status(self) -> dict[str, Any]:
        return status_report(self.spool)

    def metric(self, name: str) -> float:
        """A counter or gauge as the running agent has it now (the status file lags by a heartbeat),
        summed over its labels."""
        text = httpx.get(f"http://127.0.0.1:{self.status_port}/metrics", timeout=10).text
        for family in text_string_to_metric_families(text):
            if family.name == name:
                return sum(sample.value for sample in family.samples if sample.name in (name, f"{name}_total"))
        raise AssertionError(f"the agent has no metric {name}")

    def spool_bytes(self, run_id: str) -> int:
        path = self.spool / "runs" / run_id / "run.rrd"
        return path.stat().st_size if path.is_file() else 0


class Robot:
    """robot.py (or another `script`) in its own process, driven over stdin/stdout."""

    def __init__(self, *args: str, script: str = ROBOT) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, script, *args],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )

    def expect(self, line: str) -> None:
        assert self.proc.stdout is not None
        got = self.proc.stdout.readline().strip()
        if got != line:
            _, err = self.proc.communicate(timeout=30)
            raise AssertionError(f"robot said {got!r}, not {line!r}: {err[-2000:]}")

    def go_on(self) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write("\n")
        self.proc.stdin.flush()

    def finish(self) -> None:
        self.proc.wait(timeout=60)
        assert self.proc.returncode == 0, self.proc.stderr.read() if self.proc.stderr else ""


def log_whole_run(agent: AgentProcess, copy: Path, run_id: str, frames: int) -> None:
    """A robot logs a run of `frames` frames in one step through the agent (and to its own `copy`),
    then ends it."""
    robot = Robot("steps", agent.url, str(copy), run_id, "1", str(frames))
    robot.expect("STEP 1")
    robot.go_on()
    robot.expect("DONE")
    robot.finish()


def depot_chunks(depot: LiveServer, run_id: str) -> int:
    return int(_depot_run(depot, run_id).get("chunks", 0))


def run_status(depot: LiveServer, run_id: str) -> str | None:
    status = _depot_run(depot, run_id).get("status")
    return None if status is None else str(status)


def _depot_run(depot: LiveServer, run_id: str) -> dict[str, Any]:
    """The depot's view of a run, or {} while it has none to give; the tests poll it, so an answer
    slower than 10 s (a machine loaded by the whole suite) counts as "not yet" like a 404."""
    try:
        answer = httpx.get(f"{depot.url}/v1/runs/{run_id}", headers=depot.headers, timeout=10)
    except httpx.TimeoutException:
        return {}
    return dict(answer.json()) if answer.status_code == 200 else {}


def same_recording(rerun_bin: str, a: Path, b: Path) -> tuple[bool, str]:
    done = subprocess.run(
        [rerun_bin, "rrd", "compare", "--unordered", str(a), str(b)], capture_output=True, text=True, timeout=120
    )
    return done.returncode == 0, done.stderr[-2000:] + done.stdout[-2000:]


def download(depot: LiveServer, run_id: str, to: Path) -> Path:
    with httpx.stream("GET", f"{depot.url}/v1/runs/{run_id}/recording.rrd", headers=depot.headers, timeout=60) as r:
        if r.is_error:
            r.read()  # the refusal's reason, for whoever reports it
        r.raise_for_status()
        with open(to, "wb") as fh:
            for piece in r.iter_bytes():
                fh.write(piece)
    return to


def depot_equals_copy(depot: LiveServer, run_id: str, copy: Path, rerun_bin: str, tmp_path: Path) -> None:
    served = tmp_path / f"{run_id}-served.rrd"

    def same() -> bool:
        if depot_chunks(depot, run_id) == 0:
            return False
        download(depot, run_id, served)
        return same_recording(rerun_bin, copy, served)[0]

    try:
        wait_for(same, 90, f"the depot's {run_id} to equal the robot's copy")
    except AssertionError:
        raise AssertionError(same_recording(rerun_bin, copy, served)[1]) from None
    # the agent ends its stream once the robot's has ended: then the depot has counted what it got
    wait_for(lambda: run_status(depot, run_id) == "closed", 60, f"the depot to close {run_id}")
