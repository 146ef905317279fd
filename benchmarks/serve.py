"""Benchmark: serving a run as .rrd over HTTP, next to `rerun rrd filter` on the same local file.

    .venv/bin/python benchmarks/serve.py [--repeat 5] [--json]

Uploads benchmarks/data/big.rrd (>= 200 MB, made by benchmarks/codec.py) into a fresh `fleet serve`,
then times `GET /v1/runs/RUN/recording.rrd` whole and filtered to one entity (time to first byte,
MB/s over the run's size), and `rerun rrd filter` doing the same selection on the local file (the
whole file, and with the other entities dropped). Each download is timed with two clients: httpx
(a Python client, reading the body and dropping it) and curl (a native one, writing it to a file as
`rerun rrd filter` does); on a 2-core machine the Python client's own work competes with the
server's, so curl shows more of what the server can send. Target: >= 2x `rerun rrd filter`
throughput, first byte < 50 ms. MB = 10**6 bytes; best of --repeat.
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
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as `python benchmarks/serve.py` without the editable install
    sys.path.insert(0, str(ROOT))

from benchmarks.codec import MB, ensure_recording, find_rerun_binary, format_table, log  # noqa: E402
from benchmarks.ingest import FleetServer  # noqa: E402
from services.rrd.footer import summarize_from_footer  # noqa: E402

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


def time_curl(curl: str, url: str, params: dict[str, str], out: Path) -> tuple[float, float, int]:
    """(seconds to the first byte, seconds to the last, bytes) of one GET by curl, written to `out`."""
    full = str(httpx.URL(url, params=params))
    start = time.perf_counter()
    done = subprocess.run(
        [curl, "-sSf", "-o", str(out), "-w", "%{time_starttransfer}", full], check=True, capture_output=True, text=True
    )
    total = time.perf_counter() - start
    size = out.stat().st_size
    out.unlink()
    return float(done.stdout), total, size


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
        for name, params in (("full", {}), ("entity", {"include": chosen})):
            clients = {"ours": lambda p=params: time_download(url, p)}
            if curl is not None:
                clients["ours_curl"] = lambda p=params: time_curl(curl, url, p, workdir / "download.rrd")
            for client, timed in clients.items():
                runs = [timed() for _ in range(args.repeat)]
                ttfb = min(r[0] for r in runs)
                total = min(r[1] for r in runs)
                results[f"{client}_{name}"] = {
                    "ttfb_s": ttfb,
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
        for client in ("ours", "ours_curl"):
            ours = results.get(f"{client}_{name}")
            if ours is None:
                continue
            ratio = ours["mb_s"] / peer["mb_s"]
            rows.append(
                [
                    name,
                    "httpx" if client == "ours" else "curl",
                    f"{ours['ttfb_s'] * 1000:.1f}",
                    f"{ours['mb_s']:.0f}",
                    f"{ours['bytes_out'] / MB:.1f}",
                    f"{peer['mb_s']:.0f}",
                    f"{peer['bytes_out'] / MB:.1f}",
                    f"{ratio:.2f}x",
                    "met" if ratio >= RATIO_TARGET and ours["ttfb_s"] < TTFB_TARGET_S else "MISSED",
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
