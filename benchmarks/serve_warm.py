"""`benchmarks/serve.py --tier warm`: a sealed run served from the warm store, beside the store itself.

A real S3 server (SeaweedFS on loopback, as in benchmarks/analytics.py) holds the warm tier of a
fresh `fleet serve`. big.rrd is uploaded, then sealed into the warm tier (`POST .../promote`, timed
once the promotion of a run of a few KB has warmed the process up, as a server that has been up a
while is; that first one is printed too), beside a boto3 multipart upload of the same file (the
depot's part size and concurrency): the store's own write speed. Both read their bytes from the
disk, not the page cache: a run's file is dropped from the cache once on disk, and the file put is
too. Then, each best of --repeat, with curl for both sides so that the client is the same native
one:

- `whole`: `GET /v1/runs/RUN/recording.rrd` against one plain GET of the sealed object (a presigned
  URL to the store): target >= 0.8x;
- `entity`: the same download filtered to the heaviest entity (bytes out, MB/s over them);
- for context, the object read by 8 MiB ranged GETs one after another (boto3), what a reader that
  does not read ahead gets, and through a bare relay (benchmarks/bare_relay.py: one thread copying
  the store's GET to the client, no HTTP server): what any server in the middle can hope for when
  the store, the server and the client share the same cores.

Memory: the server's peak RSS (VmHWM) before and after the downloads.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx
from boto3.s3.transfer import TransferConfig

from benchmarks.analytics import AWS, BUCKET, PREFIX, s3_client, seaweedfs, wait_for_bucket
from benchmarks.bare_relay import bare_relay
from benchmarks.codec import MB, format_table, log
from benchmarks.ingest import FleetServer, proc_status_kb, tree_cpu_s
from services.storage.objectstore import PART_BYTES, UPLOAD_CONCURRENCY
from tests.services.hot.page_cache import uncache

# The multipart put beside promotion sends parts as the depot does by default
DEPOT_PARTS = TransferConfig(
    multipart_threshold=PART_BYTES, multipart_chunksize=PART_BYTES, max_concurrency=UPLOAD_CONCURRENCY
)
WARM_TARGET = 0.8  # of one plain GET stream of the same object
PROMOTE_TARGET = 0.9  # of a multipart put of the same bytes


class WarmServer(FleetServer):
    """`fleet serve` with its warm tier in the SeaweedFS at `endpoint`."""

    def __init__(self, workdir: Path, endpoint: str) -> None:
        super().__init__(workdir)
        self.extra = {
            **AWS,
            "FLEET_WARM_URL": f"s3://{BUCKET}/{PREFIX}",
            "FLEET_S3_ENDPOINT_URL": endpoint,
            "FLEET_SCHEDULER": "false",
        }

    def argv_env(self) -> tuple[list[str], dict[str, str]]:
        argv, env = super().argv_env()
        return argv, {**env, **self.extra}

    def peak_rss_mb(self) -> float:
        return proc_status_kb(self.pid, "VmHWM") / 1024


def curl_seconds(curl: str, url: str) -> tuple[float, int, float | None]:
    """(seconds to the last byte, bytes, seconds to the response's first byte) of one GET by curl,
    the body dropped."""
    start = time.perf_counter()
    done = subprocess.run(
        [curl, "-sSf", "-o", os.devnull, "-w", "%{size_download} %{time_starttransfer}", url],
        check=True,
        capture_output=True,
        text=True,
    )
    size, first = done.stdout.split()
    return time.perf_counter() - start, int(size), float(first)


def ranged_seconds(client: Any, key: str, size: int, piece: int = 8 * 1024 * 1024) -> float:
    start = time.perf_counter()
    for offset in range(0, size, piece):
        end = min(offset + piece, size) - 1
        client.get_object(Bucket=BUCKET, Key=key, Range=f"bytes={offset}-{end}")["Body"].read()
    return time.perf_counter() - start


def sealed_key(client: Any, run_id: str) -> str:
    pages = client.get_paginator("list_objects_v2").paginate(Bucket=BUCKET, Prefix=f"{PREFIX}/")
    keys = [o["Key"] for page in pages for o in page.get("Contents", []) if o["Key"].endswith("/recording.rrd")]
    mine = [k for k in keys if f"/{run_id}/" in k]
    if len(mine) != 1:
        raise SystemExit(f"sealed object of run {run_id} not found in the warm store: {keys}")
    return str(mine[0])


def run_warm(source: Path, run_id: str, chosen: str, repeat: int) -> dict[str, Any]:
    curl = shutil.which("curl")
    if curl is None:
        raise SystemExit("--tier warm times downloads with curl: install it")
    size = source.stat().st_size
    workdir = Path(tempfile.mkdtemp(prefix="serve-warm-bench-"))
    results: dict[str, Any] = {"run_bytes": size, "entity": chosen}
    try:
        with seaweedfs(workdir / "seaweedfs") as endpoint:
            client = s3_client(endpoint)
            wait_for_bucket(client)
            uncache(source)
            start = time.perf_counter()
            client.upload_file(str(source), BUCKET, "bench-multipart/recording.rrd", Config=DEPOT_PARTS)
            results["multipart_put_s"] = time.perf_counter() - start
            client.delete_object(Bucket=BUCKET, Key="bench-multipart/recording.rrd")
            server = WarmServer(workdir / "fleet", endpoint)
            (workdir / "fleet").mkdir()
            server.start()
            try:
                results |= _serve(server, client, curl, source, run_id, chosen, repeat)
            finally:
                server.stop()
    finally:
        shutil.rmtree(workdir, ignore_errors=True)
    return results


WARM_UP_RUN = """
import rerun as rr
rr.init("bench-warm-up", recording_id="bench-warm-up", spawn=False)
rr.save({path!r})
for i in range(10):
    rr.set_time("frame", sequence=i)
    rr.log("/warm_up", rr.Scalars([float(i)]))
"""


def _first_promotion(base: str, workdir: Path) -> float:
    """Promote a run of a few KB first, as a server that has been up a while has: a process's first
    promotion also loads pyiceberg and opens the lakehouse's catalog (about 0.3 s, once). Returns
    how long that first promotion took."""
    path = workdir / "warm-up.rrd"
    subprocess.run([sys.executable, "-c", WARM_UP_RUN.format(path=str(path))], check=True, timeout=120)
    answer = httpx.post(f"{base}/v1/uploads", content=path.read_bytes(), timeout=60).json()
    start = time.perf_counter()
    httpx.post(f"{base}/v1/runs/{answer['runs'][0]}/promote", timeout=600).raise_for_status()
    return time.perf_counter() - start


def promotion_steps(server_log: Path, run_id: str) -> str:
    """How long each step of the run's promotion took, as the server logged it."""
    for line in reversed(server_log.read_text(errors="replace").splitlines()):
        if f"promoted run {run_id}:" in line and line.endswith(")"):
            return line[line.rindex("(") + 1 : -1]
    return "not logged"


def _serve(
    server: WarmServer, client: Any, curl: str, source: Path, run_id: str, chosen: str, repeat: int
) -> dict[str, Any]:
    base = f"http://127.0.0.1:{server.http_port}"
    log(f"uploading {source} ({source.stat().st_size / MB:.1f} MB) ...")
    with open(source, "rb") as fh:
        answer = httpx.post(f"{base}/v1/uploads", content=fh, timeout=600).json()
    assert answer["runs"] == [run_id], answer
    rss_before = server.peak_rss_mb()
    first_promote_s = _first_promotion(base, server.workdir)
    log("promoting it to the warm tier ...")
    uncache(server.data_dir / "hot" / run_id / "run.rrd")  # as the depot leaves it (and as the put read)
    cpu = tree_cpu_s(server.pid)
    start = time.perf_counter()
    promoted = httpx.post(f"{base}/v1/runs/{run_id}/promote", timeout=3600)
    promote_s = time.perf_counter() - start
    promote_cpu_s = tree_cpu_s(server.pid) - cpu
    if promoted.status_code != 200:
        raise SystemExit(f"promote: HTTP {promoted.status_code}: {promoted.text[:500]}")
    rss_promoted = server.peak_rss_mb()
    steps = promotion_steps(server.log_path, run_id)
    key = sealed_key(client, run_id)
    size = client.head_object(Bucket=BUCKET, Key=key)["ContentLength"]
    presigned = client.generate_presigned_url("get_object", Params={"Bucket": BUCKET, "Key": key}, ExpiresIn=900)
    url = f"{base}/v1/runs/{run_id}/recording.rrd"
    log("timing downloads ...")
    timed = {
        "ours_whole": lambda: curl_seconds(curl, url),
        "ours_entity": lambda: curl_seconds(curl, str(httpx.URL(url, params={"include": chosen}))),
        "store_get": lambda: curl_seconds(curl, presigned),
        "store_ranged_8mib": lambda: (ranged_seconds(client, key, size), size, None),
    }
    relay = contextlib.ExitStack()
    relayed = relay.enter_context(bare_relay(presigned))
    timed["bare_relay"] = lambda: curl_seconds(curl, relayed)
    out: dict[str, Any] = {
        "promote_s": promote_s,
        "promote_cpu_s": promote_cpu_s,
        "first_promote_s": first_promote_s,
        "promote_steps": steps,
        "sealed_bytes": size,
        "rss_mb": {"before_promote": rss_before, "after_promote": rss_promoted},
    }
    times: dict[str, list[tuple[float, int, float | None]]] = {name: [] for name in timed}
    # The CPU each middle spends on a whole download: the server's (its process tree), the bare
    # relay's (a thread of this process, which is otherwise idle while curl runs).
    cpu_of = {"ours_whole": lambda: tree_cpu_s(server.pid), "bare_relay": time.process_time}
    cpu_s = dict.fromkeys(cpu_of, 0.0)
    for _ in range(repeat):  # each step in turn, so that a slow spell of the machine falls on all of them
        for name, once in timed.items():
            before = cpu_of[name]() if name in cpu_of else 0.0
            times[name].append(once())
            if name in cpu_of:
                cpu_s[name] += cpu_of[name]() - before
    out["cpu_s_per_gib"] = {name: cpu / (repeat * size / MB / 1024) for name, cpu in cpu_s.items()}
    for name, runs in times.items():
        best = min(r[0] for r in runs)
        firsts = [r[2] for r in runs if r[2] is not None]
        out[name] = {
            "seconds": best,
            "median_s": statistics.median(r[0] for r in runs),
            "bytes_out": runs[0][1],
            "mb_s": runs[0][1] / MB / best,
            "first_byte_s": min(firsts) if firsts else None,
        }
    relay.close()
    out["rss_mb"]["after_downloads"] = server.peak_rss_mb()
    return out


def print_warm(results: dict[str, Any], repeat: int) -> None:
    store = results["store_get"]["mb_s"]
    size = results["sealed_bytes"]
    promote_mb_s = size / MB / results["promote_s"]
    multipart_mb_s = results["run_bytes"] / MB / results["multipart_put_s"]
    rss = results["rss_mb"]
    print(
        f"warm tier on SeaweedFS (loopback): sealed run {size / MB:.1f} MB; best of {repeat}; curl on both "
        f"sides; load average {os.getloadavg()[0]:.2f} at the end"
    )
    rows = []
    for name, label in (
        ("ours_whole", "GET recording.rrd (whole)"),
        ("ours_entity", f"GET recording.rrd?include={results['entity']}"),
        ("store_get", "store: one GET of the object"),
        ("store_ranged_8mib", "store: 8 MiB ranged GETs in sequence"),
        ("bare_relay", "bare relay of the store's GET (context)"),
    ):
        r = results[name]
        ratio = r["mb_s"] / store
        verdict = "-"
        if name == "ours_whole":
            verdict = "met" if ratio >= WARM_TARGET else "MISSED"
        first = "-" if r["first_byte_s"] is None else f"{r['first_byte_s'] * 1000:.0f}"
        figures = [f"{r['bytes_out'] / MB:.1f}", f"{r['seconds']:.2f}", first, f"{r['mb_s']:.0f}", f"{ratio:.2f}x"]
        rows.append([label, *figures, verdict])
    promote_ratio = promote_mb_s / multipart_mb_s
    rows.append(
        [
            "promotion (POST .../promote)",
            f"{size / MB:.1f}",
            f"{results['promote_s']:.2f}",
            "-",
            f"{promote_mb_s:.0f}",
            f"{promote_ratio:.2f}x of multipart put ({multipart_mb_s:.0f} MB/s)",
            "met" if promote_ratio >= PROMOTE_TARGET else "MISSED",
        ]
    )
    print(
        format_table(
            [
                "step",
                "MB",
                "seconds",
                "first byte ms",
                "MB/s",
                "vs the store",
                f"target (>= {WARM_TARGET}x, >= {PROMOTE_TARGET}x)",
            ],
            rows,
            "lrrrrll",
        )
    )
    medians = {
        name: results["store_get"]["median_s"] / results[name]["median_s"] for name in ("ours_whole", "bare_relay")
    }
    print(
        f"medians against the store's: whole download {medians['ours_whole']:.2f}x, bare relay "
        f"{medians['bare_relay']:.2f}x"
    )
    cpu = results["cpu_s_per_gib"]
    print(
        f"CPU per GiB of whole download: the server {cpu['ours_whole']:.2f} s, the bare relay {cpu['bare_relay']:.2f} s"
    )
    print(
        f"the server's CPU for the promotion: {results['promote_cpu_s']:.2f} s "
        f"({results['promote_cpu_s'] / (size / MB / 1024):.2f} s per GiB sealed); its steps: {results['promote_steps']}"
    )
    print(
        f"the server's first promotion (a run of a few KB, before the big one) took "
        f"{results['first_promote_s']:.2f} s: a process's first also loads pyiceberg and opens the lakehouse"
    )
    print(
        f"server peak RSS: {rss['before_promote']:.0f} MB after the upload, {rss['after_promote']:.0f} MB after "
        f"promotion, {rss['after_downloads']:.0f} MB after the downloads"
    )


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--tier",
        choices=("hot", "warm"),
        default="hot",
        help="hot: the run as uploaded, beside rerun rrd filter (default); warm: sealed into SeaweedFS, beside "
        "the store's own GET",
    )
