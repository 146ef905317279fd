"""Benchmark: what the robot agent (`fleet agent`) costs on the robot, next to the same robot streaming
straight to the depot.

    .venv/bin/python benchmarks/agent.py [--seconds 20] [--rate-hz 10] [--camera jpeg|raw]
                                         [--cap 500k] [--cap-seconds 8] [--cap-window 20] [--json]

A depot (`fleet serve`, auth off, a temporary data dir, free loopback ports) runs throughout. A robot
(`benchmarks/agent_robot.py`, the real SDK: a camera image, a 10,000-point lidar sweep, eight scalars,
a pose and a log line per frame, at --rate-hz for --seconds, with a FileSink copy) streams:

1. through the agent: its GrpcSink to `fleet agent` (a temporary spool, default settings, no cap),
   which forwards to the depot;
2. directly: its GrpcSink to the depot's gRPC port (the peer: no agent).

For each, measured with psutil from the robot's first frame until the depot holds every chunk of
the run (its hot file holds as many chunks as the robot's copy): CPU (user + system) of the agent,
the depot and the robot (the robot's own, over its streaming), as seconds and % of one core; the
agent's RSS sampled every 0.2 s (peak, and at the end); the forwarding lag, from the robot's last
flush until the depot holds every chunk (polled every 20 ms).

3. The cap: a new agent with FLEET_AGENT_BANDWIDTH=--cap forwards through a loopback TCP proxy that
   counts the bytes sent to the depot's gRPC port; the robot streams for --cap-seconds (more than
   the cap carries), and the rate on the link is measured over --cap-window seconds starting 1 s
   after the robot's first frame, while a backlog remains (checked: the agent's spool is ahead of the link
   at the window's end). The agent is then stopped without draining. The link carries whole gRPC
   messages, the robot's largest chunks about 0.5 MB (jpeg; 0.9 MB raw), so a window of W seconds
   reads the rate to within about one such message over W (0.5 MB over 20 s: 5 % of 500k).

MB = 10**6 bytes. Both phases share the machine's cores with the benchmark itself.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import psutil  # type: ignore[import-untyped]  # no stubs; installed with rerun-sdk (dev)

ROOT = Path(__file__).resolve().parents[1]
# Run as `python benchmarks/agent.py`: the repository first, and not this folder, whose catalog.py
# would stand in for the catalog package.
sys.path[:] = [str(ROOT), *(p for p in sys.path if p not in (str(ROOT), str(ROOT / "benchmarks")))]

from benchmarks.codec import MB, format_table, log  # noqa: E402
from benchmarks.ingest import FleetServer, Server, free_port  # noqa: E402
from services.agent.bandwidth import parse_rate  # noqa: E402
from services.rrd.frames import MESSAGE_HEADER_SIZE, STREAM_HEADER_SIZE, MessageKind, decode_message_header  # noqa: E402
from tests.tcp_proxy import TcpProxy  # noqa: E402

ROBOT = str(Path(__file__).with_name("agent_robot.py"))
RSS_SAMPLE_S = 0.2
LAG_POLL_S = 0.02
RATE_SAMPLE_S = 0.2
CAP_SKIP_S = 1.0  # the bucket's first burst and the stream's set-up, left out of the cap's window
HELD_TIMEOUT_S = 300.0


class ChunkCounter:
    """The chunks (ArrowMsg messages) of an RRD file as it grows, reading only what was added."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.offset = STREAM_HEADER_SIZE
        self.chunks = 0
        self.ended = False  # an End message: what follows is the file's footer, not messages

    def update(self) -> int:
        if self.ended:
            return self.chunks
        try:
            with open(self.path, "rb") as fh:
                fh.seek(self.offset)
                data = fh.read()
        except FileNotFoundError:
            return 0
        pos = 0
        while pos + MESSAGE_HEADER_SIZE <= len(data):
            kind, length = decode_message_header(data, pos)
            if pos + MESSAGE_HEADER_SIZE + length > len(data):
                break  # the rest of this message is still being written
            pos += MESSAGE_HEADER_SIZE + length
            if kind == MessageKind.ARROW_MSG:
                self.chunks += 1
            elif kind == MessageKind.END:
                self.ended = True
                break
        self.offset += pos
        return self.chunks


class Meter:
    """One process's CPU and, on a thread, its RSS every RSS_SAMPLE_S."""

    def __init__(self, pid: int) -> None:
        self.process = psutil.Process(pid)
        self.peak_rss = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def cpu_s(self) -> float:
        times = self.process.cpu_times()
        return float(times.user + times.system)

    def rss(self) -> int:
        return int(self.process.memory_info().rss)

    def start_sampling(self) -> None:
        def sample() -> None:
            while not self._stop.is_set():
                self.peak_rss = max(self.peak_rss, self.rss())
                self._stop.wait(RSS_SAMPLE_S)

        self._thread = threading.Thread(target=sample, daemon=True)
        self._thread.start()

    def stop_sampling(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()


class AgentServer(Server):
    """`fleet agent` on a free loopback port (the base class's `grpc_port`), forwarding to a depot."""

    def __init__(
        self, workdir: Path, depot_grpc_port: int, depot_http_port: int, bandwidth: str = "0", **settings: str
    ) -> None:
        self.name = f"agent-{workdir.name}"
        super().__init__(workdir)
        self.spool = workdir / "spool"
        self.env = {
            **os.environ,
            "FLEET_AGENT_SPOOL": str(self.spool),
            "FLEET_AGENT_LISTEN": f"127.0.0.1:{self.grpc_port}",
            "FLEET_AGENT_STATUS_ADDR": f"127.0.0.1:{free_port()}",
            "FLEET_AGENT_DEPOT": f"rerun+http://127.0.0.1:{depot_grpc_port}",
            "FLEET_AGENT_API_URL": f"http://127.0.0.1:{depot_http_port}",
            "FLEET_AGENT_BANDWIDTH": bandwidth,
            **{f"FLEET_AGENT_{key.upper()}": value for key, value in settings.items()},
        }

    @property
    def url(self) -> str:
        return f"rerun+http://127.0.0.1:{self.grpc_port}/proxy"

    def argv_env(self) -> tuple[list[str], dict[str, str]]:
        return [str(Path(sys.executable).with_name("fleet")), "agent"], self.env

    def ready(self) -> bool:
        with socket.create_connection(("127.0.0.1", self.grpc_port), timeout=1):
            return True

    def spool_bytes(self, run_id: str) -> int:
        path = self.spool / "runs" / run_id / "run.rrd"
        return path.stat().st_size if path.is_file() else 0


class RobotProcess:
    """agent_robot.py in its own process: started, told to go, its figures read."""

    def __init__(
        self,
        url: str,
        copy: Path,
        run_id: str,
        seconds: float,
        rate_hz: float,
        camera: str,
        brake_at: float | None = None,
    ) -> None:
        argv = [sys.executable, ROBOT, url, str(copy), run_id, str(seconds), str(rate_hz), camera]
        argv += [str(brake_at)] if brake_at is not None else []
        self.proc = subprocess.Popen(argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        self.expect("READY")

    def line(self) -> str:
        assert self.proc.stdout is not None
        got = self.proc.stdout.readline().strip()
        if not got:
            raise SystemExit(f"the robot ended early (exit code {self.proc.wait()})")
        return got

    def expect(self, wanted: str) -> None:
        got = self.line()
        if got != wanted:
            raise SystemExit(f"the robot said {got!r}, not {wanted!r}")

    def go(self) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write("\n")
        self.proc.stdin.flush()

    def result(self) -> dict[str, Any]:
        answer: dict[str, Any] = json.loads(self.line())
        return answer

    def finish(self) -> None:
        self.expect("DONE")
        if self.proc.wait(timeout=60) != 0:
            raise SystemExit(f"the robot exited with {self.proc.returncode}")

    def close(self) -> None:
        """Ends the robot if it still runs (the benchmark failed before it finished)."""
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


@dataclass
class Phase:
    path: str  # "agent" or "direct"
    run_bytes: int
    chunks: int
    frames: int
    late_frames: int
    stream_s: float  # the robot's first frame to its last flush
    window_s: float  # the robot's first frame to the depot holding every chunk
    lag_s: float
    robot_cpu_s: float
    depot_cpu_s: float
    agent_cpu_s: float | None = None
    agent_start_rss_mb: float | None = None  # before the robot's first frame: the idle agent
    agent_peak_rss_mb: float | None = None
    agent_end_rss_mb: float | None = None

    @property
    def mb_s(self) -> float:
        return self.run_bytes / MB / self.stream_s


def wait_until_held(copy: ChunkCounter, held: ChunkCounter) -> float:
    """Polls until the depot's hot file holds as many chunks as the robot's copy; returns when."""
    deadline = time.monotonic() + HELD_TIMEOUT_S
    while True:
        wanted = copy.update()
        if wanted > 0 and held.update() >= wanted:
            return time.monotonic()
        if time.monotonic() > deadline:
            raise SystemExit(f"the depot held {held.chunks} of {wanted} chunks after {HELD_TIMEOUT_S:g} s")
        time.sleep(LAG_POLL_S)  # polling the depot's file, bounded by the deadline


def stream_phase(
    path: str, url: str, depot: FleetServer, agent: AgentServer | None, args: argparse.Namespace, workdir: Path
) -> Phase:
    run_id = f"bench-{path}"
    copy = workdir / f"{run_id}-copy.rrd"
    depot_meter = Meter(depot.pid)
    agent_meter = Meter(agent.pid) if agent is not None else None
    robot = RobotProcess(url, copy, run_id, args.seconds, args.rate_hz, args.camera)
    try:
        return _measure_stream(path, robot, copy, depot, depot_meter, agent_meter, args)
    finally:
        robot.close()
        if agent_meter is not None:
            agent_meter.stop_sampling()


def _measure_stream(
    path: str,
    robot: RobotProcess,
    copy: Path,
    depot: FleetServer,
    depot_meter: Meter,
    agent_meter: Meter | None,
    args: argparse.Namespace,
) -> Phase:
    log(f"{path}: streaming {args.seconds:g} s at {args.rate_hz:g} Hz ...")
    agent_start_rss = agent_meter.rss() if agent_meter is not None else 0
    if agent_meter is not None:
        agent_meter.start_sampling()
    depot_cpu0 = depot_meter.cpu_s()
    agent_cpu0 = agent_meter.cpu_s() if agent_meter is not None else 0.0
    robot.go()
    figures = robot.result()
    held_at = wait_until_held(ChunkCounter(copy), ChunkCounter(depot.data_dir / "hot" / f"bench-{path}" / "run.rrd"))
    depot_cpu = depot_meter.cpu_s() - depot_cpu0
    phase = Phase(
        path=path,
        run_bytes=0,
        chunks=0,
        frames=figures["frames"],
        late_frames=figures["late"],
        stream_s=figures["flushed"] - figures["start"],
        window_s=held_at - figures["start"],
        lag_s=held_at - figures["flushed"],
        robot_cpu_s=figures["cpu_s"],
        depot_cpu_s=depot_cpu,
    )
    if agent_meter is not None:
        phase.agent_cpu_s = agent_meter.cpu_s() - agent_cpu0
        agent_meter.stop_sampling()
        end_rss = agent_meter.rss()
        phase.agent_start_rss_mb = agent_start_rss / MB
        phase.agent_peak_rss_mb = max(agent_meter.peak_rss, end_rss) / MB
        phase.agent_end_rss_mb = end_rss / MB
    robot.finish()
    phase.run_bytes = copy.stat().st_size
    phase.chunks = ChunkCounter(copy).update()
    return phase


def cap_phase(depot: FleetServer, args: argparse.Namespace, workdir: Path) -> dict[str, Any]:
    """The rate on the link to the depot under FLEET_AGENT_BANDWIDTH=--cap, while a backlog drains."""
    cap = parse_rate(args.cap)
    proxy = TcpProxy("127.0.0.1", depot.grpc_port)
    agent = AgentServer(workdir / "capped", proxy.port, depot.http_port, bandwidth=args.cap)
    run_id = "bench-capped"
    robot: RobotProcess | None = None
    try:
        agent.workdir.mkdir()
        agent.start()
        robot = RobotProcess(
            agent.url, workdir / f"{run_id}-copy.rrd", run_id, args.cap_seconds, args.rate_hz, args.camera
        )
        log(f"cap {args.cap}: streaming {args.cap_seconds:g} s at {args.rate_hz:g} Hz ...")
        robot.go()
        (begin, end) = sample_link(proxy, args.cap_window)
        backlog = agent.spool_bytes(run_id) - end[1]
        robot.result()
        robot.finish()
    finally:
        if robot is not None:
            robot.close()
        agent.stop()
        proxy.close()
    seconds = end[0] - begin[0]
    rate = (end[1] - begin[1]) / seconds
    if backlog <= 0:
        log("the backlog drained within the window: the measured rate is below what the cap allows")
    return {
        "cap_bytes_per_s": cap,
        "measured_bytes_per_s": rate,
        "ratio": rate / cap,
        "window_s": seconds,
        "backlog_at_window_end_mb": backlog / MB,
    }


def sample_link(proxy: TcpProxy, window_s: float) -> tuple[tuple[float, int], tuple[float, int]]:
    """(monotonic time, bytes forwarded) at the start and the end of a window of `window_s` seconds
    that opens CAP_SKIP_S after the robot started streaming; the counter is sampled every
    RATE_SAMPLE_S. (The agent's probes of the depot cross the link from its start, so the first byte
    does not say when the robot's data began.)"""
    time.sleep(CAP_SKIP_S)  # the bucket's first burst and the stream's set-up: a span left out, not a wait
    begin = (time.monotonic(), proxy.bytes_up)
    samples = [begin]
    while samples[-1][0] < begin[0] + window_s:
        time.sleep(RATE_SAMPLE_S)  # sampling the link's counter at intervals
        samples.append((time.monotonic(), proxy.bytes_up))
    if samples[-1][1] == begin[1]:
        raise SystemExit(f"nothing crossed the link to the depot in {window_s:g} s: see {proxy.target}")
    return begin, samples[-1]


def positive_seconds(text: str) -> float:
    value = float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"{text} is not a positive number of seconds (or hertz)")
    return value


def cap_rate(text: str) -> str:
    """A FLEET_AGENT_BANDWIDTH value that caps (not 0): the text as given, checked."""
    try:
        rate = parse_rate(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    if rate == 0:
        raise argparse.ArgumentTypeError("0 is no cap: give a rate such as 500k")
    return text


def percent(cpu_s: float | None, seconds: float) -> str:
    return "-" if cpu_s is None else f"{cpu_s:.2f} s, {100 * cpu_s / seconds:.1f} %"


def print_report(phases: list[Phase], capped: dict[str, Any], args: argparse.Namespace) -> None:
    agent = phases[0]
    print(
        f"robot: {args.seconds:g} s at {args.rate_hz:g} Hz, camera {args.camera}; {psutil.cpu_count()} CPUs, "
        f"load average {os.getloadavg()[0]:.2f} at the end; CPU over the robot's first frame to the depot "
        "holding every chunk (robot: over its streaming); % of one core"
    )
    rows = [
        ["data streamed", *(f"{p.run_bytes / MB:.1f} MB, {p.chunks} chunks, {p.mb_s:.2f} MB/s" for p in phases)],
        ["frames (late)", *(f"{p.frames} ({p.late_frames})" for p in phases)],
        ["agent CPU", percent(agent.agent_cpu_s, agent.window_s), "-"],
        [
            "agent RSS idle / peak / end",
            f"{agent.agent_start_rss_mb:.0f} / {agent.agent_peak_rss_mb:.0f} / {agent.agent_end_rss_mb:.0f} MB",
            "-",
        ],
        ["depot CPU", *(percent(p.depot_cpu_s, p.window_s) for p in phases)],
        ["robot CPU", *(percent(p.robot_cpu_s, p.stream_s) for p in phases)],
        ["lag, last flush to all held", *(f"{p.lag_s:.3f} s" for p in phases)],
    ]
    print(format_table(["", "ours: robot -> agent -> depot", "peer: robot -> depot"], rows, "lll"))
    print()
    print(
        f"cap {args.cap} ({capped['cap_bytes_per_s']:,} B/s): measured {capped['measured_bytes_per_s']:,.0f} B/s "
        f"on the link over {capped['window_s']:.1f} s ({capped['ratio']:.3f}x the cap; backlog at the window's "
        f"end {capped['backlog_at_window_end_mb']:.1f} MB)"
    )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=positive_seconds, default=20.0, help="how long the robot streams")
    parser.add_argument("--rate-hz", type=positive_seconds, default=10.0, help="frames per second")
    parser.add_argument("--camera", choices=("jpeg", "raw"), default="jpeg", help="50 kB JPEG-like or raw 320x240")
    parser.add_argument("--cap", type=cap_rate, default="500k", help="FLEET_AGENT_BANDWIDTH of the cap phase")
    parser.add_argument(
        "--cap-seconds", type=positive_seconds, default=8.0, help="how long the robot streams in the cap phase"
    )
    parser.add_argument(
        "--cap-window", type=positive_seconds, default=20.0, help="seconds over which the capped rate is measured"
    )
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)

    workdir = Path(tempfile.mkdtemp(prefix="agent-bench-"))
    depot = FleetServer(workdir)
    try:
        depot.start()
        agent = AgentServer(workdir / "agent", depot.grpc_port, depot.http_port)
        agent.workdir.mkdir()
        agent.start()
        try:
            phases = [stream_phase("agent", agent.url, depot, agent, args, workdir)]
        finally:
            agent.stop()
        direct_url = f"rerun+http://127.0.0.1:{depot.grpc_port}/proxy"
        phases.append(stream_phase("direct", direct_url, depot, None, args, workdir))
        capped = cap_phase(depot, args, workdir)
    finally:
        depot.stop()
        shutil.rmtree(workdir, ignore_errors=True)

    if args.json:
        report = {"phases": [{**asdict(p), "mb_s": p.mb_s} for p in phases], "cap": capped, "args": vars(args)}
        print(json.dumps(report, indent=2))
    else:
        print_report(phases, capped, args)


if __name__ == "__main__":
    main()
