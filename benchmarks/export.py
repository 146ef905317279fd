"""Benchmark: a dataset version exported as LeRobot v3.0 (`fleet datasets export`), beside LeRobot's own
writer making the same dataset.

    .venv/bin/python benchmarks/export.py [--runs 2] [--seconds 60] [--fps 30] [--width 640] [--height 480]
                                          [--image jpeg|raw] [--codec h264] [--no-peer] [--json]

1. --runs recordings logged with the real rerun-sdk (`benchmarks/export_frames.py`): each --seconds of a
   camera (`/camera/front`, --width x --height, 30 Hz, a JPEG `EncodedImage` or a raw RGB `Image`), 7
   joints (`/joints`) and 7 commands (`/cmd`) as Scalars at 100 Hz, on a `sim_time` timestamp timeline.
2. A depot (`fleet serve`, auth off, a temporary data dir, free loopback ports): each recording uploaded
   and promoted to the warm tier, then a snapshot `bench` of the runs (an episode per whole run) at
   --fps on `sim_time`.
3. Ours: `fleet datasets export bench@1 --to DIR --observation /joints --action /cmd --camera
   /camera/front=observation.images.front --video-codec CODEC`, a child process: each episode
   downloaded from the depot as its chunks, sampled, its images decoded and encoded to MP4. Its wall
   time, CPU (user + system, wait4) and peak RSS (its VmHWM, polled every 50 ms); frames/s; source MB/s (the
   snapshot's bytes over the wall time).
4. Peer: LeRobot's own writer (`LeRobotDataset.create`, `add_frame`, `save_episode`, `finalize`,
   the same codec) in the cached lerobot venv (`tests/compat/lerobot_venv.py`), given the same frames
   and values from the same formulas, in memory: no download, no decoding. Its wall time, CPU and
   peak RSS.

MB = 10**6 bytes. Peak RSS stays flat as --seconds grows when memory is bounded by the slice, not
the episode: run it at two lengths to see.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:] = [str(ROOT), *(p for p in sys.path if p not in (str(ROOT), str(ROOT / "benchmarks")))]

from benchmarks import export_frames as frames  # noqa: E402
from benchmarks.codec import format_table, log  # noqa: E402
from benchmarks.ingest import FleetServer  # noqa: E402

S = 1_000_000_000
START = 1_790_000_000 * S
MB = 1e6


def record(path: Path, run: int, args: argparse.Namespace) -> None:
    import rerun as rr
    from PIL import Image

    rec = rr.RecordingStream("export_bench", recording_id=f"bench-{run}")
    rec.save(str(path))
    rec.send_property("fleet", rr.AnyValues(robot_id="bench-robot"))
    for tick in range(int(args.seconds * frames.SCALAR_HZ)):
        rec.set_time("sim_time", timestamp=np.datetime64(START + tick * S // frames.SCALAR_HZ, "ns"))
        rec.log("/joints", rr.Scalars(frames.joints(run, tick)))
        rec.log("/cmd", rr.Scalars(frames.command(run, tick)))
        if tick * frames.CAMERA_HZ % frames.SCALAR_HZ == 0:
            pixels = frames.image(tick * frames.CAMERA_HZ // frames.SCALAR_HZ, args.width, args.height)
            if args.image == "raw":
                rec.log("/camera/front", rr.Image(pixels))
            else:
                jpeg = io.BytesIO()
                Image.fromarray(pixels).save(jpeg, format="JPEG", quality=90)
                rec.log("/camera/front", rr.EncodedImage(contents=jpeg.getvalue(), media_type="image/jpeg"))
    rec.flush()
    rec.disconnect()


def measured(argv: list[str], env: dict[str, str]) -> dict[str, float]:
    """Run a child to its end: wall s, CPU s (user + system, from wait4) and peak RSS (MB: its VmHWM,
    read until it exits; wait4's ru_maxrss would count this process's pages, kept across exec)."""
    started = time.perf_counter()
    child = subprocess.Popen(argv, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    held: dict[str, bytes] = {}
    peak_kb = 0
    stop = threading.Event()

    def drain(name: str, pipe: Any) -> None:
        held[name] = pipe.read()

    def watch() -> None:
        nonlocal peak_kb
        while not stop.wait(0.05):
            with contextlib.suppress(OSError, ValueError):
                peak_kb = max(peak_kb, status_kb(child.pid, "VmHWM"))

    threads = [
        threading.Thread(target=drain, args=("out", child.stdout), daemon=True),
        threading.Thread(target=drain, args=("err", child.stderr), daemon=True),
        threading.Thread(target=watch, daemon=True),
    ]
    for thread in threads:
        thread.start()
    _, status, usage = os.wait4(child.pid, 0)
    wall = time.perf_counter() - started
    child.returncode = os.waitstatus_to_exitcode(status)
    stop.set()
    for thread in threads:
        thread.join()
    if child.returncode != 0:
        raise SystemExit(f"{argv[0]} failed ({child.returncode}):\n{held['err'].decode(errors='replace')[-3000:]}")
    return {
        "wall_s": wall,
        "cpu_s": usage.ru_utime + usage.ru_stime,
        "peak_mb": peak_kb * 1024 / MB,
        "stdout": held["out"].decode(errors="replace"),  # type: ignore[dict-item]
    }


def status_kb(pid: int, field: str) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise ValueError(field)


def ours(depot: FleetServer, out: Path, args: argparse.Namespace) -> dict[str, Any]:
    argv = depot.fleet(
        "datasets", "export", "bench@1", "--to", str(out), "--observation", "/joints", "--action", "/cmd",
        "--camera", "/camera/front=observation.images.front", "--video-codec", args.codec, "--json",
    )  # fmt: skip
    env = {**os.environ, "FLEET_API_URL": f"http://127.0.0.1:{depot.http_port}"}
    found = measured(argv, env)
    report = json.loads(str(found.pop("stdout")))
    return {**found, "frames": report["info"]["total_frames"], "episodes": report["info"]["total_episodes"]}


def peer(out: Path, episodes: int, frames_each: int, args: argparse.Namespace) -> dict[str, Any]:
    from tests.compat.lerobot_venv import lerobot_python

    argv = [
        str(lerobot_python()), str(ROOT / "benchmarks" / "export_peer.py"), str(out), str(episodes),
        str(frames_each), str(args.fps), str(args.width), str(args.height), args.codec,
    ]  # fmt: skip
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "HF_HOME": str(out.parent / "hf-home")}
    found = measured(argv, env)
    inner = json.loads(str(found.pop("stdout")).strip().splitlines()[-1])
    return {**found, "frames": episodes * frames_each, "episodes": episodes, "inner_wall_s": inner["wall_s"]}


def size_mb(folder: Path) -> float:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file() and ".export" not in p.parts) / MB


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=2)
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--fps", type=int, default=30)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--image", choices=("jpeg", "raw"), default="jpeg")
    parser.add_argument("--codec", choices=("h264", "av1"), default="h264")
    parser.add_argument("--no-peer", action="store_true")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="export-bench-") as folder:
        work = Path(folder)
        log(f"logging {args.runs} runs of {args.seconds:g} s ({args.image} {args.width}x{args.height} at 30 Hz) ...")
        paths = []
        for run in range(args.runs):
            paths.append(work / f"bench-{run}.rrd")
            record(paths[-1], run, args)
        depot = FleetServer(work)
        depot.start()
        try:
            api = f"http://127.0.0.1:{depot.http_port}"
            with httpx.Client(base_url=api, timeout=600) as client:
                for path in paths:
                    client.post("/v1/uploads", content=path.read_bytes()).raise_for_status()
                    client.post(f"/v1/runs/{path.stem}/promote").raise_for_status()
                made = (
                    client.post("/v1/datasets", json={"name": "bench", "timeline": "sim_time", "fps": args.fps})
                    .raise_for_status()
                    .json()
                )
            log(f"snapshot bench@1: {made['episodes']} episodes, {made['bytes'] / MB:,.1f} MB; exporting ...")
            mine = ours(depot, work / "ours", args)
        finally:
            depot.stop()
        mine["source_mb"], mine["output_mb"] = made["bytes"] / MB, size_mb(work / "ours")
        results = [{"side": "ours", **mine}]
        if not args.no_peer:
            log("peer: LeRobot's own writer ...")
            theirs = peer(work / "peer", mine["episodes"], mine["frames"] // max(mine["episodes"], 1), args)
            results.append({"side": "lerobot writer", **theirs, "output_mb": size_mb(work / "peer")})
    if args.json:
        print(json.dumps({"args": vars(args), "results": results}, indent=2))
        return
    rows = [
        [
            r["side"],
            str(r["episodes"]),
            f"{r['frames']:,}",
            f"{r['wall_s']:.1f}",
            f"{r['frames'] / r['wall_s']:,.0f}",
            f"{r['source_mb'] / r['wall_s']:,.1f}" if "source_mb" in r else "-",
            f"{r['output_mb']:,.1f}",
            f"{r['cpu_s']:.1f}",
            f"{r['peak_mb']:,.0f}",
        ]
        for r in results
    ]
    headers = ["side", "episodes", "frames", "wall s", "frames/s", "source MB/s", "out MB", "CPU s", "peak RSS MB"]
    print(format_table(headers, rows, "lrrrrrrrr"))


if __name__ == "__main__":
    main()
