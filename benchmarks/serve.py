"""Benchmark: serving a run as .rrd over HTTP, next to `rerun rrd filter` on the same local file.

    .venv/bin/python benchmarks/serve.py [--repeat 5] [--json] [--tier hot|warm]

`--tier warm` serves the run from the warm tier in a real S3 server instead, beside the store's own
GET (benchmarks/serve_warm.py says how).

Uploads benchmarks/data/big.rrd (>= 200 MB, made by benchmarks/codec.py) into a fresh `fleet serve`,
then times `GET /v1/runs/RUN/recording.rrd` whole and filtered to one entity (time to first byte,
MB/s over the run's size), and `rerun rrd filter` doing the same selection on the local file (the
whole file, and with the other entities dropped). Each download is timed with two clients that
read the body and drop it: httpx (Python) and curl (native); on a 2-core machine the Python
client's own work competes with the server's, so curl shows more of what the server can send. A
third figure is the download's body produced in this process from the server's hot files, with no
HTTP: what serving costs by itself. Target: >= 2x `rerun rrd filter` throughput over HTTP, first
byte < 50 ms (httpx's first piece of the body). MB = 10**6 bytes; best of --repeat.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from functools import partial
from pathlib import Path
from typing import Any, cast

import httpx

ROOT = Path(__file__).resolve().parents[1]
# Run as `python benchmarks/serve.py`: the repository first, and not this folder, whose catalog.py
# would stand in for the catalog package.
sys.path[:] = [str(ROOT), *(p for p in sys.path if p not in (str(ROOT), str(ROOT / "benchmarks")))]

from benchmarks import serve_warm  # noqa: E402
from benchmarks.codec import MB, ensure_recording, find_rerun_binary, format_table, log  # noqa: E402
from benchmarks.ingest import FleetServer  # noqa: E402
from services.hot.read import HotRecording  # noqa: E402
from services.hot.store import Changes  # noqa: E402
from services.rrd.footer import summarize_from_footer  # noqa: E402
from services.runs.recording import RecordingQuery, recording_download  # noqa: E402

TTFB_TARGET_S = 0.050
RATIO_TARGET = 2.0


def _pieces(path: Path) -> Iterator[bytes]:
    with open(path, "rb") as fh:
        while piece := fh.read(1 << 20):
            yield piece


def time_download(url: str, params: dict[str, str]) -> tuple[float, float, int]:
    """(seconds to the first byte, seconds to the last, bytes) of one streamed GET."""
    start = time.perf_counter()
    first = None
    size = 0
    with httpx.stream("GET", url, params=params, timeout=600) as response:
        response.raise_for_status()
        for piece in response.iter_raw():
            if first is None:
                first = time.perf_counter() - start
            size += len(piece)
    return first or 0.0, time.perf_counter() - start, size


def time_curl(curl: str, url: str, params: dict[str, str]) -> tuple[float | None, float, int]:
    """(None, seconds to the last byte, bytes) of one GET by curl, the body dropped as httpx's is.
    curl's own "first byte" is the response's headers, which a streamed body sends before its first
    piece, so it is not reported."""
    start = time.perf_counter()
    done = subprocess.run(
        [curl, "-sSf", "-o", os.devnull, "-w", "%{size_download}", str(httpx.URL(url, params=params))],
        check=True,
        capture_output=True,
        text=True,
    )
    return None, time.perf_counter() - start, int(done.stdout)


class _OneHotRun:
    """The server's hot run, as the download service finds it (what ingest's read-only view answers)."""

    def __init__(self, hot: HotRecording) -> None:
        self.hot = hot

    def hot_recording(self, run_id: str) -> HotRecording | None:
        return self.hot if run_id == self.hot.path.parent.name else None


def time_in_process(run_file: Path, run_id: str, params: dict[str, str]) -> tuple[float | None, float, int]:
    """(None, seconds, bytes) of producing one download's body in this process, from the run's hot
    files the server wrote (read only): what serving costs without HTTP, client or sockets."""
    size = run_file.stat().st_size
    hot = HotRecording(run_file, size, {}, lambda: (size, False), Changes())
    query = RecordingQuery(include=[params["include"]] if "include" in params else [])
    start = time.perf_counter()
    no_catalog, no_warm = cast(Any, None), cast(Any, None)  # a hot run: neither is asked
    body = recording_download(_OneHotRun(hot), no_catalog, no_warm, run_id, query).body
    assert isinstance(body, Iterator)
    out = sum(len(piece) for piece in body)
    return None, time.perf_counter() - start, out


def time_filter(rerun_bin: str, source: Path, drop: list[str], out: Path) -> tuple[float, int]:
    args = [rerun_bin, "rrd", "filter", str(source), "-o", str(out)]
    for entity in drop:
        args += ["--drop-entity", entity]
    start = time.perf_counter()
    subprocess.run(args, check=True, capture_output=True)
    return time.perf_counter() - start, out.stat().st_size


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data-dir", type=Path, default=ROOT / "benchmarks" / "data")
    parser.add_argument("--big-mb", type=float, default=220)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--rerun", help="the rerun executable (default: the native binary of rerun-sdk)")
    parser.add_argument("--json", action="store_true")
    serve_warm.add_arguments(parser)
    args = parser.parse_args(argv)

    info = ensure_recording(
        args.data_dir.resolve(), "big.rrd", {"kind": "big", "big_mb": args.big_mb}, ["gen-big", str(args.big_mb)]
    )
    source = args.data_dir.resolve() / "big.rrd"
    run_size = source.stat().st_size
    summary = summarize_from_footer(str(source))
    assert summary is not None, "big.rrd has no footer"
    store = next(s for s in summary.stores.values() if s.store_id.kind.name == "RECORDING")
    run_id = store.store_id.recording_id
    entities = sorted(e.path for e in store.entities.values() if not e.path.startswith("/__properties"))
    chosen = max(entities, key=lambda p: store.entities[p].bytes)  # the heaviest entity
    others = [p for p in store.entities if p != chosen]
    if args.tier == "warm":
        warm = serve_warm.run_warm(source, run_id, chosen, args.repeat)
        if args.json:
            print(json.dumps(warm, indent=2))
        else:
            serve_warm.print_warm(warm, args.repeat)
        return
    rerun_bin, _ = find_rerun_binary(args.rerun)
    curl = shutil.which("curl")
    if curl is None:
        log("curl not found: downloads are timed with httpx only")

    workdir = Path(tempfile.mkdtemp(prefix="serve-bench-"))
    server = FleetServer(workdir)
    results: dict[str, Any] = {"run_bytes": run_size, "chunks": info["chunks"], "entity": chosen}
    try:
        server.start()
        log(f"uploading {source} ({run_size / MB:.1f} MB) ...")
        answer = httpx.post(
            f"http://127.0.0.1:{server.http_port}/v1/uploads", content=_pieces(source), timeout=600
        ).json()
        assert answer["runs"] == [run_id], answer
        url = f"http://127.0.0.1:{server.http_port}/v1/runs/{run_id}/recording.rrd"
        run_file = server.data_dir / "hot" / run_id / "run.rrd"
        for name, params in (("full", {}), ("entity", {"include": chosen})):
            clients: dict[str, Callable[[], tuple[float | None, float, int]]] = {
                "ours": partial(time_download, url, params)
            }
            if curl is not None:
                clients["ours_curl"] = partial(time_curl, curl, url, params)
            clients["in_process"] = partial(time_in_process, run_file, run_id, params)
            for client, timed in clients.items():
                runs = [timed() for _ in range(args.repeat)]
                firsts = [r[0] for r in runs if r[0] is not None]
                total = min(r[1] for r in runs)
                results[f"{client}_{name}"] = {
                    "ttfb_s": min(firsts) if firsts else None,
                    "seconds": total,
                    "bytes_out": runs[0][2],
                    "mb_s": run_size / MB / total,
                }
        for name, drop in (("full", []), ("entity", others)):
            out = workdir / f"filtered-{name}.rrd"
            runs2 = [time_filter(rerun_bin, source, drop, out) for _ in range(args.repeat)]
            total = min(r[0] for r in runs2)
            results[f"rerun_{name}"] = {"seconds": total, "bytes_out": runs2[0][1], "mb_s": run_size / MB / total}
    finally:
        server.stop()
        shutil.rmtree(workdir, ignore_errors=True)

    if args.json:
        print(json.dumps(results, indent=2))
        return
    print(
        f"run: {run_size / MB:.1f} MB, {info['chunks']} chunks; entity filter: include={chosen}; best of "
        f"{args.repeat}; MB/s over the run's size; rerun rrd filter on the local file; load average "
        f"{os.getloadavg()[0]:.2f} at the end"
    )
    rows = []
    for name in ("full", "entity"):
        peer = results[f"rerun_{name}"]
        first_byte = results[f"ours_{name}"]["ttfb_s"]  # httpx's: the first piece of the body
        for client, label in (("ours", "httpx"), ("ours_curl", "curl"), ("in_process", "no HTTP")):
            ours = results.get(f"{client}_{name}")
            if ours is None:
                continue
            ratio = ours["mb_s"] / peer["mb_s"]
            met = ratio >= RATIO_TARGET and first_byte < TTFB_TARGET_S
            rows.append(
                [
                    name,
                    label,
                    f"{ours['ttfb_s'] * 1000:.1f}" if ours["ttfb_s"] is not None else "-",
                    f"{ours['mb_s']:.0f}",
                    f"{ours['bytes_out'] / MB:.1f}",
                    f"{peer['mb_s']:.0f}",
                    f"{peer['bytes_out'] / MB:.1f}",
                    f"{ratio:.2f}x",
                    "-" if client == "in_process" else "met" if met else "MISSED",
                ]
            )
    print(
        format_table(
            [
                "download",
                "client",
                "ours first byte ms",
                "ours MB/s",
                "ours out MB",
                "rrd filter MB/s",
                "rrd filter out MB",
                "ours/rerun",
                "target (>= 2x, < 50 ms)",
            ],
            rows,
            "llrrrrrrl",
        )
    )


if __name__ == "__main__":
    main()
