"""Benchmark: an MCAP upload into the depot (`POST /v1/uploads`: received, checked, converted by the
Rerun CLI, filed), beside `rerun mcap convert` run by hand on the same file.

    .venv/bin/python benchmarks/mcap_import.py [--messages 200] [--width 640] [--height 480] [--noise]
                                               [--small 0] [--repeat 3] [--json]

1. A ROS 2 bag written with the real `mcap` and `mcap-ros2-support` libraries (the cached venv of
   tests/compat/mcap_venv.py): --messages messages on each of five topics (sensor_msgs/Image of
   --width x --height rgb8, PointCloud2, Imu, tf2_msgs/TFMessage, std_msgs/String), zstd chunks.
   --noise fills the images with noise (incompressible: the MCAP is as big as its pixels).
   With --small N, a second bag of N messages per topic and no images: many small messages.
2. Peer: `rerun mcap convert BAG -o OUT.rrd` of the pinned rerun-sdk, a child process: wall time,
   CPU (user + system, wait4), peak RSS (VmHWM polled every 50 ms).
3. Ours: a depot (`fleet serve`, auth off, a temporary data dir, free loopback ports), the bag
   uploaded with one streamed POST: wall time until the answer (the run filed), the depot's CPU and
   peak RSS over the upload (its process tree, the converter included: the sum of each process's
   VmHWM, an upper bound).

MCAP MB/s = the bag's size (10**6 bytes) over the wall time. Each figure is the median of --repeat
runs (each upload into a new depot: the same bag twice is "already held").
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx

ROOT = Path(__file__).resolve().parents[1]
sys.path[:] = [str(ROOT), *(p for p in sys.path if p not in (str(ROOT), str(ROOT / "benchmarks")))]

from benchmarks.codec import format_table, log  # noqa: E402
from benchmarks.export import measured  # noqa: E402
from benchmarks.ingest import FleetServer, tree_cpu_s, tree_status_kb  # noqa: E402
from services.imports.convert import cli_path  # noqa: E402
from tests.compat.bags import bag_files, write_ros2_bag  # noqa: E402

MB = 1e6


def peer(bag: Path, out: Path) -> dict[str, float]:
    """`rerun mcap convert` by hand."""
    argv = [cli_path(None), "mcap", "convert", str(bag), "-o", str(out), "--recording-id", "peer"]
    found = measured(argv, {"PATH": "/usr/bin:/bin", "RUST_LOG": "warn"})
    out.unlink(missing_ok=True)
    return {k: v for k, v in found.items() if k != "stdout"}  # type: ignore[misc]


def ours(server: FleetServer, bag: Path, run_id: str) -> dict[str, float]:
    """One streamed upload until the depot answers; its CPU and peak RSS over the upload."""
    cpu0 = tree_cpu_s(server.pid)
    peak = 0
    started = time.perf_counter()

    def pieces() -> Any:
        nonlocal peak
        with open(bag, "rb") as f:
            while piece := f.read(1 << 20):
                yield piece
                peak = max(peak, tree_status_kb(server.pid, "VmRSS"))

    answer = httpx.post(
        f"http://127.0.0.1:{server.http_port}/v1/uploads",
        content=pieces(),
        params={"run_id": run_id, "name": bag.name},
        headers={"Content-Type": "application/octet-stream"},
        timeout=httpx.Timeout(60.0, read=None),
    )
    wall = time.perf_counter() - started
    if answer.status_code != 200 or answer.json().get("already_held"):
        raise SystemExit(f"upload refused or held: {answer.status_code} {answer.text[:500]}")
    return {
        "wall_s": wall,
        "cpu_s": tree_cpu_s(server.pid) - cpu0,
        "peak_mb": max(peak, tree_status_kb(server.pid, "VmHWM")) * 1024 / MB,
        "chunks": float(answer.json()["chunks_new"]),
    }


def median(runs: list[dict[str, float]]) -> dict[str, float]:
    return {key: statistics.median(r[key] for r in runs) for key in runs[0]}


def fresh_depot_upload(bag: Path, scratch: Path, run_id: str) -> dict[str, float]:
    """One upload into a depot of its own (the same bag twice would be "already held")."""
    scratch.mkdir(parents=True, exist_ok=True)
    server = FleetServer(scratch)
    server.start()
    try:
        return ours(server, bag, run_id)
    finally:
        server.stop()


def workload(name: str, bag: Path, repeat: int, scratch: Path) -> list[dict[str, Any]]:
    size = bag.stat().st_size
    log(f"{name}: {size / MB:,.1f} MB")
    theirs = median([peer(bag, scratch / "peer.rrd") for _ in range(repeat)])
    mine = median([fresh_depot_upload(bag, scratch / f"depot-{name}-{k}", f"bench-{name}") for k in range(repeat)])
    rows = []
    for who, found in (("rerun mcap convert (by hand)", theirs), ("ours: upload, check, convert, file", mine)):
        rows.append({"workload": name, "who": who, "mcap_mb": size / MB, **found, "mb_s": size / MB / found["wall_s"]})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--messages", type=int, default=200)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--noise", action="store_true")
    parser.add_argument("--small", type=int, default=0, help="messages per topic of a bag of small messages")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="mcap-bench-") as tmp:
        scratch = Path(tmp)
        bags = {
            "images": bag_files(
                write_ros2_bag(scratch / "images", args.messages, image=(args.width, args.height), noise=args.noise)
            )[0]
        }
        if args.small:
            bags["small"] = bag_files(write_ros2_bag(scratch / "small", args.small))[0]
        rows = [row for name, bag in bags.items() for row in workload(name, bag, args.repeat, scratch)]
    if args.json:
        print(json.dumps(rows, indent=2))
        return
    headers = ["workload", "who", "MCAP MB", "wall s", "MCAP MB/s", "CPU s", "peak RSS MB"]
    table = [
        [
            r["workload"],
            r["who"],
            f"{r['mcap_mb']:,.1f}",
            f"{r['wall_s']:.2f}",
            f"{r['mb_s']:,.0f}",
            f"{r['cpu_s']:.2f}",
            f"{r['peak_mb']:,.0f}",
        ]
        for r in rows
    ]
    print(format_table(headers, table, "llrrrrr"))


if __name__ == "__main__":
    main()
