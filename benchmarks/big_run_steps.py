"""The parts of benchmarks/big_run.py: the run's generator (a child process with the real rerun-sdk,
`python benchmarks/big_run_steps.py gen grpc|file TARGET BYTES RUN_ID`), one step's watch over the
server (memory, CPU, progress), SeaweedFS (started with room for big runs) and its housekeeping, and
the timed reads (curl, the catalog service's GetRrdManifest + FetchChunks for one entity's window)."""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
# Run as a script: the repository first, and not this folder, whose catalog.py would stand in for
# the catalog package.
sys.path[:] = [str(ROOT), *(p for p in sys.path if p not in (str(ROOT), str(ROOT / "benchmarks")))]

import grpc  # noqa: E402
import httpx  # noqa: E402
import numpy as np  # noqa: E402
import pyarrow as pa  # noqa: E402
import pyarrow.compute as pc  # noqa: E402

from benchmarks.analytics import seaweedfs_server  # noqa: E402
from benchmarks.catalog import (  # noqa: E402
    CHANNEL_OPTIONS,
    CLIENT_VERSION,
    VIEWER_COLUMNS,
    chunk_ids,
    fetch_chunks_call,
    segment_manifest,
)
from benchmarks.codec import MB, log  # noqa: E402
from benchmarks.ingest import proc_tree, tree_cpu_s, tree_status_kb  # noqa: E402
from core.backoff import backoff_delay  # noqa: E402
from services.redap.dataframe import dataframe_part  # noqa: E402
from services.redap.pb import cloud_pb2  # noqa: E402

APPLICATION, ROBOT = "big_run", "robot-big"
CAMERA, SCALAR, POSE = "/camera/front", "/robot/battery", "/robot/base"
IMAGE_SHAPE = (480, 640, 3)  # uint8 RGB, 0.92 MB
TICKS_PER_IMAGE = 10  # `frame` ticks at 100 Hz; the camera at 10 Hz, the scalar and the pose every tick
SAMPLE_S, PROGRESS_S = 0.2, 10.0


# --- the generator (child process) -----------------------------------------------------------------


def generate(mode: str, target: str, total: int, run_id: str, side: int = 1) -> None:
    """Log camera images until `total` bytes of them, a scalar and a pose every tick, streamed over
    gRPC (`mode` grpc, `target` the depot's URL) or saved (`file`, `target` a path). Four random
    frames made once, each image a copy of one with a row changed: cheap, and incompressible.
    `side`: images that many times smaller a side, the batcher's byte bound as many squared."""
    import rerun as rr

    shape = (IMAGE_SHAPE[0] // side, IMAGE_SHAPE[1] // side, IMAGE_SHAPE[2])
    rng = np.random.default_rng(7)
    frames = [rng.integers(0, 256, shape, dtype=np.uint8) for _ in range(4)]
    # Chunks cut by size and rows only, not by the batcher's clock, so that they do not depend on the
    # machine's speed: three images (2.8 MB), or 100 ticks (one second) of the scalar and the pose.
    flush_bytes = (2 << 20) // (side * side)
    batching = rr.ChunkBatcherConfig(flush_tick=3600.0, flush_num_bytes=flush_bytes, flush_num_rows=100)
    rec = rr.RecordingStream(APPLICATION, recording_id=run_id, batcher_config=batching)
    if mode == "grpc":
        rec.connect_grpc(target)
    else:
        rec.save(target)
    rec.send_property("fleet", rr.AnyValues(robot_id=ROBOT))
    print("READY", flush=True)
    sys.stdin.readline()
    start, cpu = time.perf_counter(), time.process_time()
    tick = sent = 0
    while sent < total:
        rec.set_time("frame", sequence=tick)
        if tick % TICKS_PER_IMAGE == 0:
            n = tick // TICKS_PER_IMAGE
            image = frames[n % len(frames)].copy()
            image[n % shape[0]] ^= 0x55
            rec.log(CAMERA, rr.Image(image))
            sent += image.nbytes
        rec.log(SCALAR, rr.Scalars([100.0 - tick * 1e-5]))
        rec.log(POSE, rr.Transform3D(translation=[tick * 1e-3, 0.0, 0.0]))
        tick += 1
    rec.flush(timeout_sec=86400)
    rec.disconnect()
    seconds, cpu_s = time.perf_counter() - start, time.process_time() - cpu
    print("DONE " + json.dumps({"ticks": tick, "image_bytes": sent, "seconds": seconds, "cpu_s": cpu_s}), flush=True)


def start_generator(
    mode: str, target: str, total: int, run_id: str, log_path: Path, side: int = 1
) -> subprocess.Popen[str]:
    """The generator, ready (connected, its frames made): write a line to its stdin to start it."""
    with open(log_path, "ab") as err:
        proc = subprocess.Popen(
            [sys.executable, __file__, "gen", mode, target, str(total), run_id, str(side)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=err,
            text=True,
        )
    assert proc.stdout is not None
    if proc.stdout.readline().strip() != "READY":
        proc.kill()
        raise SystemExit(f"the generator did not start: {log_path.read_text()[-2000:]}")
    return proc


def finish_generator(proc: subprocess.Popen[str], log_path: Path) -> dict[str, Any]:
    """Wait for the generator's end (no time limit: a 50 GB run takes a while) and its figures."""
    assert proc.stdout is not None
    line = proc.stdout.readline()
    if proc.wait() != 0 or not line.startswith("DONE "):
        raise SystemExit(f"the generator failed ({proc.returncode}): {log_path.read_text()[-2000:]}")
    figures: dict[str, Any] = json.loads(line[5:])
    return figures


# --- one step's watch over the server -----------------------------------------------------------------


def reset_peak(pid: int) -> bool:
    """Reset VmHWM of `pid` and its children (`5` to /proc/PID/clear_refs); False if refused."""
    try:
        for member in proc_tree(pid):
            with open(f"/proc/{member}/clear_refs", "w") as fh:
                fh.write("5")
    except OSError:
        return False
    return True


def io_bytes(pid: int, key: str) -> int:
    """rchar / wchar of /proc/PID/io, in bytes (0 once the process is gone)."""
    with contextlib.suppress(OSError), open(f"/proc/{pid}/io") as fh:
        for line in fh:
            if line.startswith(key + ":"):
                return int(line.split()[1])
    return 0


def size_of(path: Path) -> int:
    """A file's size, 0 while it does not exist."""
    try:
        return path.stat().st_size
    except FileNotFoundError:
        return 0


def tree_bytes(path: Path) -> int:
    """Disk space the files under `path` take (their blocks)."""
    total = 0
    for folder, _, files in os.walk(path):
        for name in files:
            with contextlib.suppress(OSError):
                total += os.lstat(os.path.join(folder, name)).st_blocks * 512
    return total


class DiskWatch:
    """Disk the files under `path` take (sampled every 0.2 s; what other processes write elsewhere on
    the disk is not counted): the most over the whole size (`stop`), and over a step (`mark` starts one)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.peak = self.step_peak = tree_bytes(path)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, name="disk", daemon=True)
        self._thread.start()

    def _watch(self) -> None:
        while not self._stop.wait(SAMPLE_S):
            used = tree_bytes(self.path)
            self.peak, self.step_peak = max(self.peak, used), max(self.step_peak, used)

    def mark(self) -> None:
        self.step_peak = tree_bytes(self.path)

    def step_bytes(self) -> int:
        return max(self.step_peak, tree_bytes(self.path))

    def stop(self) -> int:
        self._stop.set()
        self._thread.join()
        return self.peak


class Step:
    """One timed step. The server's RSS (its process tree) sampled every 0.2 s and its VmHWM reset at
    the start, so the peak is the step's own; its CPU seconds; a progress line every 10 s from
    `done()` (bytes so far, settable once the step's client has started); with `Step.disk` set, the
    most disk used during the step."""

    disk: DiskWatch | None = None

    def __init__(self, name: str, pid: int | None, total: int = 0, done: Callable[[], int] | None = None) -> None:
        self.name, self.pid, self.total, self.done = name, pid, total, done
        self.rss_samples: list[float] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, name=f"step-{name}", daemon=True)
        self.seconds = self.rss_start = self.rss_end = self.cpu_s = 0.0
        self.hwm_reset = False
        self.disk_peak: int | None = None

    def _rss_mb(self) -> float:
        return tree_status_kb(self.pid, "VmRSS") / 1024 if self.pid is not None else 0.0

    def _watch(self) -> None:
        last = time.perf_counter()
        while not self._stop.wait(SAMPLE_S):
            if self.pid is not None:
                with contextlib.suppress(OSError, RuntimeError):
                    self.rss_samples.append(self._rss_mb())
            if time.perf_counter() - last >= PROGRESS_S:
                last = time.perf_counter()
                elapsed = last - self.start
                done = self.done() if self.done is not None else 0
                rss = f", server RSS {self.rss_samples[-1]:.0f} MB" if self.rss_samples else ""
                of = f" of {self.total / MB:,.0f}" if self.total else ""
                rate = f"{done / MB / elapsed:.0f} MB/s"
                log(f"  {self.name}: {done / MB:,.0f}{of} MB after {elapsed:.0f} s ({rate}){rss}")

    def __enter__(self) -> Step:
        if self.disk is not None:
            self.disk.mark()
        if self.pid is not None:
            self.hwm_reset = reset_peak(self.pid)
            self.rss_start, self._cpu = self._rss_mb(), tree_cpu_s(self.pid)
        self.start = time.perf_counter()
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.seconds = time.perf_counter() - self.start
        self.disk_peak = self.disk.step_bytes() if self.disk is not None else None
        self._stop.set()
        self._thread.join()
        if self.pid is not None:
            self.rss_end, self.cpu_s = self._rss_mb(), tree_cpu_s(self.pid) - self._cpu

    def peak_rss_mb(self) -> float:
        sampled = max([*self.rss_samples, self.rss_start, self.rss_end])
        hwm = tree_status_kb(self.pid, "VmHWM") / 1024 if self.pid is not None and self.hwm_reset else 0.0
        return max(sampled, hwm)

    def result(
        self,
        size: int,
        raw_mb_s: float | None = None,
        first_byte_s: float | None = None,
        seconds: float | None = None,
        **extra: Any,
    ) -> dict[str, Any]:
        """The step's figures; `seconds`: of one of the tries the step made (default: all of it)."""
        peak = self.peak_rss_mb() if self.pid is not None else None
        seconds = self.seconds if seconds is None else seconds
        return {
            "step": self.name,
            "bytes": size,
            "seconds": seconds,
            "mb_s": size / MB / seconds if seconds > 0 else None,
            "raw_mb_s": raw_mb_s,
            "first_byte_s": first_byte_s,
            "server_cpu_s": self.cpu_s if self.pid is not None else None,
            "rss_start_mb": self.rss_start if self.pid is not None else None,
            "rss_peak_mb": peak,
            "rss_growth_mb": peak - self.rss_start if peak is not None else None,
            "rss_end_mb": self.rss_end if self.pid is not None else None,
            "disk_peak_bytes": self.disk_peak,
            **extra,
        }


# --- SeaweedFS ---------------------------------------------------------------------------------------

# `weed server`'s defaults hold 8 volumes of 30 GB in all, and each bucket (a collection) takes 7 at
# its first write: the second bucket gets one (a 50 GB cold copy does not fit), a third none (its
# writes fail with InternalError). Smaller volumes, and enough of them (none is allocated ahead).
WEED_FLAGS = ["-volume.max=400", "-master.volumeSizeLimitMB=4096"]


def seaweedfs(data_dir: Path, timeout: float = 60) -> contextlib.AbstractContextManager[tuple[str, int]]:
    """benchmarks/analytics.py's SeaweedFS (free loopback ports, data in `data_dir`) with WEED_FLAGS;
    yields the S3 endpoint URL and the master's port."""
    return seaweedfs_server(data_dir, timeout, WEED_FLAGS)


def vacuum(data_dir: Path, master: int, freed: int, limit_s: float = 300) -> None:
    """Give back the space of deleted objects now (SeaweedFS's volumes are append-only; its master
    vacuums by itself every 15 minutes, past 30 % garbage), until `freed` bytes are: the filer
    deletes an object's chunks in the background, so the first pass may find none yet."""
    target, deadline = tree_bytes(data_dir) - freed, time.monotonic() + limit_s
    while True:
        httpx.get(f"http://127.0.0.1:{master}/vol/vacuum", params={"garbageThreshold": "0.0001"}, timeout=limit_s)
        if tree_bytes(data_dir) <= target or time.monotonic() > deadline:
            return
        time.sleep(1.0)  # the filer's deletions are still on their way, bounded by the deadline


def drop_bucket(client: Any, bucket: str) -> None:
    """Empty and delete a bucket: SeaweedFS drops its collection's volumes with it, so the disk is free."""
    for page in client.get_paginator("list_objects_v2").paginate(Bucket=bucket):
        for item in page.get("Contents", []):
            client.delete_object(Bucket=bucket, Key=item["Key"])
    client.delete_bucket(Bucket=bucket)


# --- timed reads ----------------------------------------------------------------------------------------


def curl(argv: list[str], step: Step, key: str = "wchar") -> str:
    """Run curl (its progress: the bytes it wrote out, or read in with key rchar); its -w output."""
    with subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) as proc:
        step.done = lambda: io_bytes(proc.pid, key)
        out, err = proc.communicate()
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(argv[:3])} ...: curl exit {proc.returncode}: {err[-500:]}")
    return out


def curl_get(curl_bin: str, url: str, step: Step) -> tuple[int, float]:
    """(bytes, seconds to the response's headers) of one GET, the body dropped."""
    out = curl([curl_bin, "-sSf", "-o", os.devnull, "-w", "%{size_download} %{time_starttransfer}", url], step)
    size, first = out.split()
    return int(size), float(first)


def stream_get(client: httpx.Client, url: str, params: dict[str, str]) -> tuple[float, float, int]:
    """(seconds to the body's first byte, to its last, bytes) of one streamed GET on a client made
    beforehand (a new httpx client loads its TLS settings first: 30-80 ms that are not the server's)."""
    start = time.perf_counter()
    first: float | None = None
    size = 0
    with client.stream("GET", url, params=params) as response:
        response.raise_for_status()
        for piece in response.iter_raw():
            first = first if first is not None else time.perf_counter() - start
            size += len(piece)
    return first or 0.0, time.perf_counter() - start, size


def window_rows(manifest: pa.Table, entity: str, window: tuple[int, int]) -> pa.Table:
    """The manifest's chunks of `entity` that overlap `window` on the frame timeline, and its static ones."""
    low, high = window
    overlaps = pc.and_kleene(
        pc.less_equal(manifest.column("frame:start"), high), pc.greater_equal(manifest.column("frame:end"), low)
    )
    keep = pc.and_(
        pc.equal(manifest.column("chunk_entity_path"), entity),
        pc.fill_null(pc.or_kleene(manifest.column("chunk_is_static"), overlaps), False),
    )
    return manifest.filter(keep)


def catalog_window(port: int, entry: str, segment: str, entity: str, window: tuple[int, int]) -> dict[str, Any]:
    """What a viewer does to show one entity's window of a run: GetRrdManifest, then FetchChunks of
    just the chunks of that entity overlapping the window (one request)."""
    metadata = [*CLIENT_VERSION, ("x-rerun-entry-id", entry)]
    with grpc.insecure_channel(f"127.0.0.1:{port}", options=CHANNEL_OPTIONS) as channel:
        fetch = fetch_chunks_call(channel)
        start = time.perf_counter()
        manifest = segment_manifest(channel, segment, metadata)
        manifest_s = time.perf_counter() - start
        rows = window_rows(manifest, entity, window)
        part = dataframe_part(rows.select(VIEWER_COLUMNS))
        received: list[bytes] = []
        first: float | None = None
        bytes_in = 0
        for answer in fetch(cloud_pb2.FetchChunksRequest(chunk_infos=[part]), metadata=CLIENT_VERSION, timeout=600):
            first = first if first is not None else time.perf_counter() - start
            bytes_in += len(answer)
            received += chunk_ids(answer)
    wanted = rows.column("chunk_id").to_pylist()
    if sorted(received) != sorted(wanted):
        raise SystemExit(f"FetchChunks of {entity}: {len(received)} chunks received, {len(wanted)} asked")
    return {
        "bytes": bytes_in,
        "first_byte_s": first,
        "manifest_s": manifest_s,
        "manifest_rows": manifest.num_rows,
        "manifest_bytes": manifest.nbytes,  # as Arrow holds it
        "chunks": len(received),
    }


def wait_run(base: str, run_id: str, done: Callable[[dict[str, Any]], bool], what: str, limit_s: float) -> None:
    """Poll `GET /v1/runs/RUN` until `done(answer)`: every 0.1 s at first, then less often, up to
    once a second. (A run's page costs the server about 34 ms of CPU on the embedded catalog: polled
    every 0.1 s through a 20 GB restore, about 40 s of the 77 s of CPU the restore was charged with.)"""
    deadline = time.monotonic() + limit_s
    polls = 0
    while True:
        answer = httpx.get(f"{base}/v1/runs/{run_id}", timeout=60)
        if answer.status_code == 200 and done(answer.json()):
            return
        if time.monotonic() > deadline:
            raise SystemExit(f"run {run_id} not {what} after {limit_s:.0f} s: {answer.text[:500]}")
        polls += 1
        time.sleep(backoff_delay(polls, first=0.1, cap=1.0))  # polling the run's state, bounded by the deadline


def ndjson_lines(response: httpx.Response) -> list[dict[str, Any]]:
    return [json.loads(line) for line in response.iter_lines() if line.strip()]


if __name__ == "__main__" and sys.argv[1:2] == ["gen"]:
    generate(sys.argv[2], sys.argv[3], int(sys.argv[4]), sys.argv[5], int(sys.argv[6]))
