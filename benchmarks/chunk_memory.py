"""Measure: the server's peak memory for an LZ4 bomb upload and for concurrent downloads of big chunks.

    .venv/bin/python benchmarks/chunk_memory.py [--bomb-mb 1024] [--chunk-mb 200] [--downloads 3]
                                                [--env FLEET_DECOMPRESS_BUDGET_BYTES=268435456 ...] [--json]

1. Starts `fleet serve` (the code this script lies in; `PYTHONPATH` passed on) on free loopback ports
   with a new data dir, `FLEET_DURABILITY=off`, no scheduler; `--env` adds settings.
2. Bomb: one valid chunk whose blob column holds `--bomb-mb` MB of zeros; LZ4 makes the message about
   1/255 of that. Uploaded once (`POST /v1/uploads`); reports the answer and the server's peak RSS
   (`VmHWM` of /proc/PID/status) before and after.
3. Downloads: a new server; a run of one chunk of `--chunk-mb` MB (zeros, LZ4) is uploaded, then
   downloaded `--downloads` times at once (`GET /v1/runs/RUN/recording.rrd`, the run still hot: each
   download decompresses the chunk for its metadata); reports the peak RSS before and after.
MB = 10**6 bytes.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import httpx
import lz4.block
import numpy as np
import pyarrow as pa

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from services.rrd.pb import common_pb2, log_msg_pb2  # noqa: E402

FLEET = str(Path(sys.executable).with_name("fleet"))
MB = 10**6


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _store_id(run_id: str) -> common_pb2.StoreId:
    return common_pb2.StoreId(
        kind=1,  # type: ignore[arg-type]
        recording_id=run_id,
        application_id=common_pb2.ApplicationId(id="memory"),
    )


def big_chunk_rrd(run_id: str, size: int) -> bytes:
    """An .rrd stream: SetStoreInfo, then one chunk at /blob whose Blob column holds `size` zero bytes."""
    chunk_id = struct.pack(">QQ", time.time_ns(), 1)
    schema = pa.schema(
        [
            pa.field("rerun.controls.RowId", pa.binary(16), nullable=False, metadata={b"rerun:kind": b"control"}),
            pa.field("frame", pa.int64(), metadata={b"rerun:kind": b"index", b"rerun:index_name": b"frame"}),
            pa.field(
                "Blob:blob",
                pa.list_(pa.list_(pa.uint8())),
                metadata={
                    b"rerun:kind": b"data",
                    b"rerun:component": b"Blob:blob",
                    b"rerun:archetype": b"rerun.archetypes.Blob",
                },
            ),
        ],
        metadata={b"rerun:entity_path": b"/blob", b"rerun:id": f"chunk_{chunk_id.hex()}".encode()},
    )
    blob = pa.ListArray.from_arrays(pa.array([0, size], pa.int32()), pa.array(np.zeros(size, np.uint8)))
    batch = pa.record_batch(
        [
            pa.array([chunk_id], pa.binary(16)),
            pa.array([0], pa.int64()),
            pa.ListArray.from_arrays(pa.array([0, 1], pa.int32()), blob),
        ],
        schema=schema,
    )
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, schema) as writer:
        writer.write_batch(batch)
    ipc = sink.getvalue().to_pybytes()
    arrow = log_msg_pb2.ArrowMsg(
        store_id=_store_id(run_id),
        compression=2,  # type: ignore[arg-type]
        uncompressed_size=len(ipc),
        encoding=log_msg_pb2.ENCODING_ARROW_IPC,
        payload=lz4.block.compress(ipc, store_size=False),
    )
    arrow.chunk_id.CopyFrom(
        common_pb2.Tuid(time_ns=int.from_bytes(chunk_id[:8], "big"), inc=int.from_bytes(chunk_id[8:], "big"))
    )
    info = log_msg_pb2.SetStoreInfo(
        info=log_msg_pb2.StoreInfo(
            store_id=_store_id(run_id), store_version=log_msg_pb2.StoreVersion(crate_version_bits=0x2900)
        )
    )
    out = bytearray(b"RRF2\x00\x29\x00\x00\x01\x02\x00\x00")
    for kind, body in ((1, info.SerializeToString()), (2, arrow.SerializeToString())):
        out += struct.pack("<QQ", kind, len(body)) + body
    return bytes(out)


class Server:
    def __init__(self, env: dict[str, str]) -> None:
        self.dir = tempfile.TemporaryDirectory()
        self.port = _free_port()
        full = {
            **os.environ,
            "FLEET_DATA_DIR": self.dir.name,
            "FLEET_AUTH": "off",  # on loopback, like the peer (no auth); a token is checked once per stream
            "FLEET_HTTP_ADDR": f"127.0.0.1:{self.port}",
            "FLEET_GRPC_ADDR": f"127.0.0.1:{_free_port()}",
            "FLEET_DURABILITY": "off",
            "FLEET_SCHEDULER": "false",
            "FLEET_MIN_FREE_BYTES": "0",
            "PYTHONPATH": str(ROOT),
            **env,
        }
        self.log = open(Path(self.dir.name).with_suffix(".log"), "wb")  # noqa: SIM115
        self.proc = subprocess.Popen([FLEET, "serve"], env=full, stdout=self.log, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            try:
                if httpx.get(self.url + "/healthz", timeout=1).status_code == 200:
                    return
            except httpx.TransportError:
                time.sleep(0.1)
        raise RuntimeError("fleet serve did not start")

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def peak_rss_mb(self) -> float:
        with open(f"/proc/{self.proc.pid}/status") as fh:
            return next(int(line.split()[1]) for line in fh if line.startswith("VmHWM:")) * 1024 / MB

    def alive(self) -> bool:
        return self.proc.poll() is None

    def stop(self) -> None:
        self.proc.terminate()
        self.proc.wait(timeout=60)
        self.log.close()
        self.dir.cleanup()


def bomb(env: dict[str, str], size_mb: int) -> dict[str, Any]:
    body = big_chunk_rrd("bomb", size_mb * MB)
    server = Server(env)
    try:
        before = server.peak_rss_mb()
        response = httpx.post(server.url + "/v1/uploads", content=body, timeout=600)
        return {
            "upload_mb": round(len(body) / MB, 2),
            "declared_mb": size_mb,
            "status": response.status_code,
            "answer": response.json().get("message", response.json()),
            "peak_rss_mb_before": round(before),
            "peak_rss_mb_after": round(server.peak_rss_mb()),
            "alive": server.alive(),
        }
    finally:
        server.stop()


def downloads(env: dict[str, str], size_mb: int, count: int) -> dict[str, Any]:
    server = Server(env)
    try:
        answer = httpx.post(server.url + "/v1/uploads", content=big_chunk_rrd("big", size_mb * MB), timeout=600)
        answer.raise_for_status()
        before = server.peak_rss_mb()
        sizes: list[int] = []

        def download() -> None:
            with httpx.stream("GET", server.url + "/v1/runs/big/recording.rrd", timeout=600) as response:
                sizes.append(sum(len(piece) for piece in response.iter_bytes()))

        started = time.monotonic()
        threads = [threading.Thread(target=download) for _ in range(count)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        return {
            "chunk_mb": size_mb,
            "downloads": count,
            "bytes_each": sizes,
            "seconds": round(time.monotonic() - started, 2),
            "peak_rss_mb_before": round(before),
            "peak_rss_mb_after": round(server.peak_rss_mb()),
        }
    finally:
        server.stop()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--bomb-mb", type=int, default=1024)
    parser.add_argument("--chunk-mb", type=int, default=200)
    parser.add_argument("--downloads", type=int, default=3)
    parser.add_argument("--env", action="append", default=[], help="NAME=VALUE for the server")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    env = dict(item.split("=", 1) for item in args.env)
    results = {"bomb": bomb(env, args.bomb_mb), "downloads": downloads(env, args.chunk_mb, args.downloads)}
    print(json.dumps(results, indent=None if args.json else 1))


if __name__ == "__main__":
    main()
