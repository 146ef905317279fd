"""The agent's bandwidth cap end to end: a robot on the real SDK logs a few MB at once into an agent
capped at 300 kB/s; the bytes that cross the link to the depot's gRPC port (counted by the proxy
between them) flow at the cap while the backlog drains, and the depot's run ends equal to the
robot's own copy."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest

from tests.services.agent.harness import AgentProcess, Link, depot_equals_copy, log_whole_run
from tests.services.ingest.live_server import LiveServer
from tests.tcp_proxy import TcpProxy
from tests.waiting import wait_for

pytestmark = [pytest.mark.sdk, pytest.mark.slow]

CAP = 300_000  # bytes per second
FRAMES = 70  # about 60 kB each: some 4.2 MB, 14 s at the cap
SAMPLE_S = 0.2
# The window measured: from when this share of the robot's bytes has crossed the link (the bucket's
# first burst and the stream's set-up long behind) to when this share has (the backlog not yet empty).
WINDOW_FROM, WINDOW_TO = 0.15, 0.80
MIN_WINDOW_S = 5.0


class ByteSampler:
    """(monotonic time, bytes forwarded to the depot) every SAMPLE_S, on a thread of its own."""

    def __init__(self, proxy: TcpProxy) -> None:
        self.proxy = proxy
        self.samples: list[tuple[float, int]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            self.samples.append((time.monotonic(), self.proxy.bytes_up))
            self._stop.wait(SAMPLE_S)

    def latest(self) -> int:
        return self.samples[-1][1] if self.samples else 0

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()

    def rate_between(self, low: int, high: int) -> tuple[float, float]:
        """(bytes per second, seconds) from the first sample past `low` bytes to the first past `high`."""
        first = next(s for s in self.samples if s[1] >= low)
        last = next(s for s in self.samples if s[1] >= high)
        seconds = last[0] - first[0]
        return ((last[1] - first[1]) / seconds if seconds > 0 else float("inf")), seconds


def test_the_link_carries_the_cap_while_a_backlog_drains(depot: LiveServer, link: Link, tmp_path: Path, rerun_bin: str):
    agent = AgentProcess(tmp_path / "spool", link, bandwidth="300k").start()
    sampler = ByteSampler(link.grpc)
    try:
        copy = tmp_path / "copy.rrd"
        # all of it logged and in the agent's spool: far ahead of the link
        log_whole_run(agent, copy, "run-capped", FRAMES)
        total = copy.stat().st_size
        assert total > 3_000_000, total
        wait_for(lambda: sampler.latest() >= WINDOW_TO * total, 40, "the backlog to mostly cross the link")
        rate, seconds = sampler.rate_between(int(WINDOW_FROM * total), int(WINDOW_TO * total))
        print(f"capped at {CAP} B/s: {rate:.0f} B/s over {seconds:.1f} s")
        assert abs(rate - CAP) <= 0.10 * CAP, f"{rate:.0f} B/s on the link against a cap of {CAP}"
        assert seconds >= MIN_WINDOW_S, f"measured over {seconds:.1f} s only: too short a window to hold the cap to 10%"
        depot_equals_copy(depot, "run-capped", copy, rerun_bin, tmp_path)
    finally:
        sampler.stop()
        agent.stop()
