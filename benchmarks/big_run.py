"""Benchmark: one big run end to end, at 5, 20 and 50 GB: ingest, promotion, downloads from warm, the
catalog service, archive and restore; each step's throughput beside the store's own, and the server's
memory, which must not grow with the run's size.

    .venv/bin/python benchmarks/big_run.py [--gb 5,20,50] [--workdir DIR] [--upload smallest|all|none]
                                           [--window-frames 1000] [--one-server] [--check-disk]
                                           [--image-side N] [--json [PATH]]

Not in CI: it needs the disk. The sizes run one after the other, each in a fresh folder under
--workdir (default: the temporary folder) deleted before the next. Before each, the disk it needs is
computed: the run is on disk twice at most at any time (the hot file beside the store's scratch copy,
or the hot file beside the warm copy until promotion removes it; the warm copy beside the
cold one while archiving; the cold copy beside the restored one, once a SeaweedFS vacuum has given
back the warm copy's space; the SDK's file beside its uploaded hot copy), so 2 x size + 10 % + 2 GB
(the depot refuses data below 1 GiB free). With less free, it stops there and says so;
`--check-disk` only prints the plan. For each size:

1. SeaweedFS as benchmarks/analytics.py starts it (loopback, free ports), with smaller volumes and
   more of them (`weed server` holds 8 volumes in all by default, 7 taken by the first bucket):
   bucket `fleet` holds the warm tier (`s3://fleet/warm`), bucket `fleet-cold` the cold one. A
   fresh `fleet serve` with `FLEET_AUTH=off` (loopback), `FLEET_SCHEDULER=false` (nothing moves
   unless asked), `FLEET_WARM_DAYS=0` (a warm run is due for archive at once), and
   `FLEET_S3_PART_BYTES` / `FLEET_S3_UPLOAD_CONCURRENCY` at their defaults.
2. ingest: a child process with the real rerun-sdk streams the run over gRPC
   (`RecordingStream.connect_grpc("rerun+http://127.0.0.1:PORT/proxy")`), made as it goes, no
   source file: RGB images 640x480 on /camera/front at 10 Hz (four random frames, each image a
   copy with a row changed: incompressible), /robot/battery (Scalars) and /robot/base
   (Transform3D) at 100 Hz, on the `frame` timeline (a tick every 10 ms) and the SDK's log_time,
   until the images add up to the size. The SDK's batcher cuts chunks by size and rows, not by its
   clock, so they do not depend on the machine's speed: three images (2.8 MB) or 100 ticks of the
   scalar or the pose in a chunk, ~580 chunks per GB. Timed from the first log call until the
   depot holds the run closed; MB/s over the hot file.
3. promotion: `POST /v1/runs/RUN/promote`, beside the store's raw write: a boto3 multipart upload of
   the hot file to a scratch bucket (16 MiB parts, 4 at once, as the depot's defaults), dropped after.
4. downloads from warm: the whole run (`GET /v1/runs/RUN/recording.rrd`, curl; first byte: the
   response's headers) beside one GET of the sealed object by a presigned URL (curl), twice each,
   alternating, the depot's first, the best of each (a first read may come from disk); windowed
   downloads of /robot/battery and of /camera/front over --window-frames ticks in the middle of the
   run (`?timeline=frame&start=A&end=B&include=ENTITY`), three times on one httpx client (the first
   on a new connection, the others reusing it): time to the body's first byte (target < 150 ms; the
   first try and the best) and to its last (the first try).
5. catalog service: `GetRrdManifest`, then `FetchChunks` of that entity's chunks overlapping that
   window (manifest rows filtered on `chunk_entity_path`, `frame:start` and `frame:end`, its static
   chunks too), over gRPC as the viewer does; first byte: the first FetchChunks answer, counted from
   the manifest request.
6. archive: `POST /v1/retention/run?action=archive` (the recording copied to the cold bucket,
   checked, then deleted from warm); restore: `POST /v1/runs/RUN/restore` (the copy back, on a
   thread of the depot) until the run says `restored`, then a windowed download must answer. Beside
   both, the store's copy through a client: its GET of the object piped into a boto3 multipart put
   to a scratch bucket (SeaweedFS answers UploadPartCopy, the copy inside the store, with
   InternalError).
7. upload (at the smallest size only, unless --upload all): the run saved to a file by the SDK
   (`RecordingStream.save`), then `POST /v1/uploads` of it by curl to another fresh `fleet serve`,
   once everything above is done and removed.

`--image-side N` makes the images N times smaller a side (and the SDK batcher's byte bound N^2
times smaller): a run with the ticks of a --gb run, and at least its chunks (the scalar's and the
pose's are cut by bytes more often), in 1/N^2 of its bytes. What grows with the chunk count (the
index, a window's plan, a manifest, the catalog's first byte) is measured at the count of a run
this disk cannot hold: `--gb 50 --image-side 4` is a 3.1 GB run with a 50 GB run's ticks.

The server is restarted (same data, same ports) before promotion, the whole download, the windows,
archive and restore, so that each step's peak RSS is a fresh server's plus what the step itself
needs, not what earlier steps left in its heap (`--one-server`: one process throughout, as in
production, where that drift shows). The restart before promotion recovers the hot run from disk,
as a node does after a crash: its RSS at start shows what that costs (a few messages, whatever the
run's size).

For each step: MB, seconds, MB/s, the store's raw MB/s and the ratio where there is one, the
server's CPU seconds, its RSS at the step's start, its peak during the step (VmHWM reset at the
start through /proc/PID/clear_refs, and VmRSS sampled every 0.2 s) and how far above the start
that is, and the most disk the size's folder took meanwhile. A progress line every 10 s. Then,
over all sizes, each step's peak RSS and MB/s: a peak that grows by more than 64 MB and 5 MB per
GB of run from the smallest size to the largest is flagged GROWS. `--json` prints all of it as JSON
instead of the tables; `--json PATH` writes it there after each size, and prints the tables.
MB = 10**6 bytes, GB = 10**9.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import sys
import tempfile
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
# Run as `python benchmarks/big_run.py`: the repository first, and not this folder, whose catalog.py
# would stand in for the catalog package.
sys.path[:] = [str(ROOT), *(p for p in sys.path if p not in (str(ROOT), str(ROOT / "benchmarks")))]

import httpx  # noqa: E402
from boto3.s3.transfer import TransferConfig  # noqa: E402

from benchmarks import big_run_steps as steps  # noqa: E402
from benchmarks.analytics import BUCKET, s3_client, wait_for_bucket  # noqa: E402
from benchmarks.big_run_steps import APPLICATION, CAMERA, SCALAR, Step  # noqa: E402
from benchmarks.catalog import find_entry  # noqa: E402
from benchmarks.codec import MB, format_table, log  # noqa: E402
from benchmarks.ingest import FleetServer  # noqa: E402
from benchmarks.serve_warm import WarmServer, sealed_key  # noqa: E402
from tests.services.hot.page_cache import uncache  # noqa: E402

GB = 10**9
COLD_BUCKET, SCRATCH, SCRATCH_COPY = "fleet-cold", "bench-put", "bench-copy"  # scratch buckets: one use each
TRANSFER = TransferConfig(multipart_threshold=16 << 20, multipart_chunksize=16 << 20, max_concurrency=4)
FIRST_BYTE_TARGET_S = 0.150
DOWNLOAD_TRIES = 2  # whole downloads each way
GROWTH_MB, GROWTH_MB_PER_GB = 64.0, 5.0
LIMIT_S = 6 * 3600  # any one request or wait (a 50 GB promotion takes minutes)


class BigServer(WarmServer):
    """`fleet serve` with warm and cold tiers in SeaweedFS, a warm run due for archive at once."""

    def __init__(self, workdir: Path, endpoint: str) -> None:
        super().__init__(workdir, endpoint)
        self.extra |= {"FLEET_COLD_URL": f"s3://{COLD_BUCKET}/cold", "FLEET_WARM_DAYS": "0"}


class UploadServer(FleetServer):
    """A plain `fleet serve` (hot tier only) that promotes nothing by itself."""

    def argv_env(self) -> tuple[list[str], dict[str, str]]:
        argv, env = super().argv_env()
        return argv, {**env, "FLEET_SCHEDULER": "false"}


def disk_needed(size: int) -> int:
    return int(2 * size * 1.1 + 2 * GB)


class Depot:
    """The steps against one `fleet serve` with its tiers in SeaweedFS, each appending its figures."""

    def __init__(self, server: BigServer, client: Any, master: int, workdir: Path, run_id: str, args: Any) -> None:
        self.server, self.client, self.master, self.run_id, self.args = server, client, master, run_id, args
        self.base = f"http://127.0.0.1:{server.http_port}"
        self.url = f"{self.base}/v1/runs/{run_id}/recording.rrd"
        self.weed_dir, self.gen_log = workdir / "seaweedfs", workdir / "generator.log"
        self.out: list[dict[str, Any]] = []
        self.http = httpx.Client(timeout=LIMIT_S)

    def fresh(self) -> dict[str, float] | None:
        """Restart the server before a step (unless --one-server), so that the step's peak RSS is the
        server's at start plus what the step itself needs, not what earlier steps left in its heap."""
        if self.args.one_server:
            return None
        self.server.stop()
        started = time.perf_counter()
        self.server.start(timeout=LIMIT_S)
        return {"start_s": time.perf_counter() - started, "rss_mb": self.server.rss_mb()}

    def stored(self) -> Callable[[], int]:
        """Progress of a write into the store: what its folder has grown by since now."""
        before = steps.tree_bytes(self.weed_dir)
        return lambda: steps.tree_bytes(self.weed_dir) - before

    def ingest(self, total: int) -> tuple[Path, int]:
        hot = self.server.data_dir / "hot" / self.run_id / "run.rrd"
        url = f"rerun+http://127.0.0.1:{self.server.grpc_port}/proxy"
        proc = steps.start_generator("grpc", url, total, self.run_id, self.gen_log, self.args.image_side)
        try:
            with Step("ingest (gRPC, rerun-sdk)", self.server.pid, total, lambda: steps.size_of(hot)) as st:
                assert proc.stdin is not None
                proc.stdin.write("go\n")
                proc.stdin.flush()
                generator = steps.finish_generator(proc, self.gen_log)
                sent_s = time.perf_counter() - st.start
                steps.wait_run(self.base, self.run_id, lambda r: r["status"] == "closed", "closed", 600)
        finally:
            if proc.poll() is None:  # the depot went away mid-stream
                proc.kill()
                proc.wait()
        self.out.append(st.result(hot.stat().st_size, generator=generator, generator_exit_s=sent_s))
        return hot, int(generator["ticks"])

    def promote(self, hot: Path) -> tuple[str, int]:
        size, done = hot.stat().st_size, [0]
        self.client.create_bucket(Bucket=SCRATCH)
        # Both read the file from the disk: the depot drops a run's pages from the page cache once
        # they are on disk, and the put would leave them cached for the promotion after it.
        uncache(hot)
        with Step("store: multipart put", None, size, lambda: done[0]) as raw:
            count = lambda n: done.__setitem__(0, done[0] + n)  # noqa: E731
            self.client.upload_file(str(hot), SCRATCH, "put", Config=TRANSFER, Callback=count)
        steps.drop_bucket(self.client, SCRATCH)
        restart = self.fresh()  # the hot run recovered from disk, as after a crash
        uncache(hot)
        with Step("promotion", self.server.pid, size, self.stored()) as st:
            answer = httpx.post(f"{self.base}/v1/runs/{self.run_id}/promote", timeout=LIMIT_S)
        if answer.status_code != 200:
            raise SystemExit(f"promote: HTTP {answer.status_code}: {answer.text[:500]}")
        key = sealed_key(self.client, self.run_id)
        sealed = int(self.client.head_object(Bucket=BUCKET, Key=key)["ContentLength"])
        hot_left = steps.tree_bytes(self.server.data_dir / "hot")
        self.out.append(
            st.result(
                sealed, size / MB / raw.seconds, detail=answer.json()["detail"], hot_left=hot_left, restart=restart
            )
        )
        return key, sealed

    def download(self, key: str, sealed: int) -> None:
        """The whole run from the depot beside one GET of the sealed object, DOWNLOAD_TRIES times
        each, alternating, the depot's first: what the store reads from disk the first time is in
        the page cache for the next reader. The best of each; the server's CPU and peak RSS over
        all of its tries."""
        restart = self.fresh()
        params = {"Bucket": BUCKET, "Key": key}
        presigned = self.client.generate_presigned_url("get_object", Params=params, ExpiresIn=LIMIT_S)
        ours: list[tuple[float, int, float]] = []
        theirs: list[float] = []
        with Step("whole download (curl)", self.server.pid, sealed) as st:
            for _ in range(DOWNLOAD_TRIES):
                started = time.perf_counter()
                got, first = steps.curl_get(self.args.curl, self.url, st)
                ours.append((time.perf_counter() - started, got, first))
                started = time.perf_counter()
                raw_got, _ = steps.curl_get(self.args.curl, presigned, st)
                theirs.append(raw_got / MB / (time.perf_counter() - started))
        seconds, got, first = min(ours)
        tries = {"tries_s": [o[0] for o in ours], "store_tries_mb_s": theirs}
        self.out.append(st.result(got, max(theirs), first, seconds, restart=restart, **tries))

    def windows(self, window: tuple[int, int]) -> None:
        restart = self.fresh()
        entry = find_entry(self.server.grpc_port, APPLICATION)
        if entry is None:
            raise SystemExit(f"the depot's catalog service lists no dataset {APPLICATION!r}")
        for entity in (SCALAR, CAMERA):
            params = {"timeline": "frame", "start": str(window[0]), "end": str(window[1]), "include": entity}
            with Step(f"window {entity} (HTTP)", self.server.pid) as st:
                tries = [steps.stream_get(self.http, self.url, params) for _ in range(3)]
            best = min(t[0] for t in tries)
            figures = {"best_first_byte_s": best, "tries": tries, "restart": restart}
            self.out.append(st.result(tries[0][2], None, tries[0][0], tries[0][1], **figures))
            with Step(f"catalog {entity} (gRPC)", self.server.pid) as st:
                fetched = steps.catalog_window(self.server.grpc_port, entry, self.run_id, entity, window)
            self.out.append(st.result(fetched.pop("bytes"), None, fetched.pop("first_byte_s"), **fetched))

    def archive_restore(self, key: str, sealed: int, window: tuple[int, int]) -> None:
        self.client.create_bucket(Bucket=SCRATCH_COPY)
        with Step("store: GET into a multipart put", None, sealed, self.stored()) as raw:
            body = self.client.get_object(Bucket=BUCKET, Key=key)["Body"]
            self.client.upload_fileobj(body, SCRATCH_COPY, "copy", Config=TRANSFER)
        steps.drop_bucket(self.client, SCRATCH_COPY)
        copy_mb_s = sealed / MB / raw.seconds
        restart = self.fresh()
        archive = httpx.stream("POST", f"{self.base}/v1/retention/run", params={"action": "archive"}, timeout=LIMIT_S)
        with Step("archive (warm to cold)", self.server.pid, sealed, self.stored()) as st, archive as answer:
            lines = steps.ndjson_lines(answer)
        done = [x for x in lines if x.get("event") == "done" and x.get("run") == self.run_id]
        if not done or not done[0]["ok"] or done[0]["action"] != "archive":
            raise SystemExit(f"archive of {self.run_id}: {lines}")
        self.out.append(st.result(sealed, copy_mb_s, detail=done[0]["detail"], restart=restart))
        started, before = time.perf_counter(), steps.tree_bytes(self.weed_dir)
        steps.vacuum(self.weed_dir, self.master, sealed * 9 // 10)
        after = steps.tree_bytes(self.weed_dir)
        log(f"  SeaweedFS vacuum: {time.perf_counter() - started:.1f} s, {before / MB:,.0f} -> {after / MB:,.0f} MB")

        restored = lambda r: (r.get("lifecycle") or {}).get("restore_state") == "restored"  # noqa: E731
        restart = self.fresh()
        with Step("restore (cold to warm)", self.server.pid, sealed, self.stored()) as st:
            asked = httpx.post(f"{self.base}/v1/runs/{self.run_id}/restore", timeout=600)
            if asked.status_code != 202:
                raise SystemExit(f"restore: HTTP {asked.status_code}: {asked.text[:500]}")
            steps.wait_run(self.base, self.run_id, restored, "restored", LIMIT_S)
        self.out.append(st.result(sealed, copy_mb_s, restart=restart))
        params = {"timeline": "frame", "start": str(window[0]), "end": str(window[1]), "include": SCALAR}
        if steps.stream_get(self.http, self.url, params)[2] <= 0:
            raise SystemExit("the restored run's window came back empty")

    def all_steps(self, total: int) -> list[dict[str, Any]]:
        hot, ticks = self.ingest(total)
        key, sealed = self.promote(hot)
        self.download(key, sealed)
        window = (ticks // 2, ticks // 2 + self.args.window_frames - 1)
        self.windows(window)
        self.archive_restore(key, sealed, window)
        self.http.close()
        return self.out


def upload_step(workdir: Path, total: int, run_id: str, curl_bin: str, side: int = 1) -> dict[str, Any]:
    folder = workdir / "upload"
    folder.mkdir()
    path, gen_log = folder / "run.rrd", folder / "generator.log"
    log("  saving the run to a file with the SDK ...")
    proc = steps.start_generator("file", str(path), total, run_id, gen_log, side)
    assert proc.stdin is not None
    proc.stdin.write("go\n")
    proc.stdin.flush()
    steps.finish_generator(proc, gen_log)
    size = path.stat().st_size
    server = UploadServer(folder)
    server.start()
    try:
        with Step("upload (POST /v1/uploads, curl)", server.pid, size) as st:
            argv = [curl_bin, "-sSf", "-X", "POST", "-H", "Content-Type: application/octet-stream", "-H", "Expect:"]
            body = steps.curl(
                [*argv, "--upload-file", str(path), f"http://127.0.0.1:{server.http_port}/v1/uploads"], st, "rchar"
            )
        answer = json.loads(body)
        if answer.get("runs") != [run_id]:
            raise SystemExit(f"upload: {answer}")
        return st.result(size, chunks_new=answer.get("chunks_new"))
    finally:
        server.stop()
        shutil.rmtree(folder, ignore_errors=True)


def one_size(gb: float, parent: Path, args: Any, upload: bool) -> dict[str, Any]:
    total = int(gb * GB) // (args.image_side * args.image_side)
    workdir = Path(tempfile.mkdtemp(prefix=f"big-run-{gb:g}gb-", dir=parent))
    run_id = f"big-{gb:g}gb-{uuid.uuid4().hex[:8]}"
    disk = Step.disk = steps.DiskWatch(workdir)
    started = time.perf_counter()
    out: list[Any] = []
    try:
        with steps.seaweedfs(workdir / "seaweedfs") as (endpoint, master):
            client = s3_client(endpoint)
            wait_for_bucket(client)
            client.create_bucket(Bucket=COLD_BUCKET)
            (workdir / "fleet").mkdir()
            server = BigServer(workdir / "fleet", endpoint)
            server.start()
            start_rss = server.rss_mb()
            try:
                out += Depot(server, client, master, workdir, run_id, args).all_steps(total)
            finally:
                server.stop()
        shutil.rmtree(workdir / "seaweedfs")
        shutil.rmtree(workdir / "fleet")
        if upload:
            out.append(upload_step(workdir, total, f"{run_id}-upload", args.curl, args.image_side))
    finally:
        used = disk.stop()
        Step.disk = None
        shutil.rmtree(workdir, ignore_errors=True)
    return {
        "gb": gb,
        "image_side": args.image_side,
        "run_id": run_id,
        "run_bytes": out[0]["bytes"],
        "wall_s": time.perf_counter() - started,
        "disk_needed_bytes": disk_needed(total),
        "disk_peak_bytes": used,
        "server_start_rss_mb": start_rss,
        "steps": out,
    }


def _n(value: float | None, fmt: str = ".0f") -> str:
    return "-" if value is None else format(value, fmt)


def print_size(size: dict[str, Any]) -> None:
    print(
        f"\n{size['gb']:g} GB: run {size['run_bytes'] / MB:,.0f} MB, {size['wall_s'] / 60:.1f} min wall; disk used at "
        f"most {size['disk_peak_bytes'] / GB:.1f} GB (planned {size['disk_needed_bytes'] / GB:.1f}); server RSS "
        f"{size['server_start_rss_mb']:.0f} MB at start; load average {os.getloadavg()[0]:.2f}"
    )
    rows = []
    for s in size["steps"]:
        ratio = s["mb_s"] / s["raw_mb_s"] if s["raw_mb_s"] and s["mb_s"] else None
        first = _n(s["first_byte_s"] and s["first_byte_s"] * 1000)
        if "best_first_byte_s" in s:
            met = "met" if s["first_byte_s"] < FIRST_BYTE_TARGET_S else "MISSED"
            first = f"{first} / {s['best_first_byte_s'] * 1000:.0f} ({met})"
        figures = [_n(s["bytes"] / MB, ".1f"), f"{s['seconds']:.2f}", _n(s["mb_s"]), _n(s["raw_mb_s"])]
        memory = [_n(s["rss_start_mb"]), _n(s["rss_peak_mb"]), _n(s["rss_growth_mb"])]
        memory.append(_n(s["disk_peak_bytes"] and s["disk_peak_bytes"] / GB, ".2f"))
        rows.append([s["step"], *figures, _n(ratio, ".2f"), first, _n(s["server_cpu_s"], ".1f"), *memory])
    headers = ["step", "MB", "seconds", "MB/s", "store MB/s", "ratio", "first byte ms", "server CPU s"]
    print(format_table([*headers, "RSS start MB", "RSS peak MB", "RSS growth MB", "disk GB"], rows, "l" + "r" * 11))
    print("first byte of a window: first try / best of 3 (target < 150 ms); store: the raw figure of the same bytes")


def print_across(sizes: list[dict[str, Any]]) -> None:
    """Each step's server peak RSS and MB/s by run size; a peak that grows with size is flagged."""
    names = list(dict.fromkeys(s["step"] for size in sizes for s in size["steps"]))
    rows = []
    for name in names:
        found = [next((s for s in size["steps"] if s["step"] == name), None) for size in sizes]
        peaks = [(size["gb"], s["rss_peak_mb"]) for size, s in zip(sizes, found, strict=True) if s is not None]
        verdict = "-"
        if len(peaks) >= 2:
            (gb0, p0), (gb1, p1) = peaks[0], peaks[-1]
            grows = p1 - p0 > GROWTH_MB and (p1 - p0) / (gb1 - gb0) > GROWTH_MB_PER_GB
            verdict = f"{'GROWS' if grows else 'ok'} ({p1 - p0:+.0f} MB, {(p1 - p0) / (gb1 - gb0):+.0f} MB/GB)"
        memory = [_n(s and s["rss_peak_mb"]) for s in found]
        rows.append([name, *memory, *(_n(s and s["mb_s"]) for s in found), verdict])
    labels = [f"{s['gb']:g} GB" for s in sizes]
    headers = ["step", *(f"RSS MB {x}" for x in labels), *(f"MB/s {x}" for x in labels), "peak RSS with size"]
    print("\nby run size: the server's peak RSS during each step, and its MB/s")
    print(format_table(headers, rows, "l" + "r" * 2 * len(sizes) + "l"))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--gb", default="5,20,50", help="run sizes in GB, in order (default 5,20,50)")
    parser.add_argument(
        "--workdir", type=Path, default=Path(tempfile.gettempdir()), help="where each size's folder is made"
    )
    parser.add_argument(
        "--upload", choices=("smallest", "all", "none"), default="smallest", help="at which sizes to time an upload"
    )
    parser.add_argument("--window-frames", type=int, default=1000, help="window length in frame ticks (10 ms)")
    parser.add_argument("--check-disk", action="store_true", help="print the disk each size needs, and stop")
    parser.add_argument(
        "--one-server", action="store_true", help="one server process for all steps (default: restarted before most)"
    )
    parser.add_argument(
        "--image-side",
        type=int,
        default=1,
        help="images N times smaller a side: the ticks and chunks of a --gb run in 1/N^2 of its bytes",
    )
    parser.add_argument("--json", nargs="?", const="-", help="JSON instead of tables; with a PATH, written there too")
    args = parser.parse_args(argv)
    sizes = [float(x) for x in args.gb.split(",")]
    args.curl = shutil.which("curl")
    if args.curl is None:
        raise SystemExit("big_run.py times downloads with curl: install it")
    args.workdir.mkdir(parents=True, exist_ok=True)
    report: dict[str, Any] = {"machine": {"cpus": os.cpu_count(), "python": platform.python_version()}, "sizes": []}
    for gb in sizes:
        need, free = disk_needed(int(gb * GB) // args.image_side**2), shutil.disk_usage(args.workdir).free
        if args.check_disk:
            print(f"{gb:g} GB: needs {need / GB:.1f} GB, {free / GB:.1f} GB free: {'fits' if need <= free else 'no'}")
            continue
        if need > free:
            report["stopped"] = f"stopped before {gb:g} GB: needs {need / GB:.1f} GB, {free / GB:.1f} GB free"
            log(report["stopped"])
            break
        shrunk = f" (images 1/{args.image_side} a side: {gb / args.image_side**2:g} GB)" if args.image_side > 1 else ""
        log(f"{gb:g} GB run{shrunk} in {args.workdir} ...")
        size = one_size(
            gb, args.workdir, args, args.upload == "all" or (args.upload == "smallest" and gb == min(sizes))
        )
        report["sizes"].append(size)
        if args.json not in (None, "-"):
            Path(args.json).write_text(json.dumps(report, indent=2))
        if args.json != "-":
            print_size(size)
    if args.check_disk:
        return
    if args.json == "-":
        print(json.dumps(report, indent=2))
        return
    if report["sizes"]:
        print_across(report["sizes"])
    if "stopped" in report:
        print(report["stopped"])


if __name__ == "__main__":
    main()
