"""Benchmark: opening a ~1 GB run the way Rerun's viewer does, from the depot and from `rerun server`.

    .venv/bin/python benchmarks/catalog.py [--mb 1000] [--repeat 3] [--batch-mb 64] [--json]

1. The recording is ``benchmarks/codec.py``'s big recording (point clouds and images, 2.4-2.6 MB
   chunks, written by the real SDK) grown to ``--mb`` MB: ``benchmarks/data/catalog.rrd``.
2. Ours: a fresh ``fleet serve`` (``FLEET_AUTH=off`` on loopback) takes the file by
   ``POST /v1/uploads`` and seals it (``POST /v1/runs/RUN/promote``): a warm run on local disk. It is
   then stopped and started again on the same data dir, so its peak RSS is that of serving only.
   The peer: ``rerun server -d catalog=DIR`` (Rerun 0.41's own catalog server, which loads the file
   into memory at start) on the same file.
3. Timed, for each server in turn (best of ``--repeat``, alternating which goes first), what the viewer
   does to open the segment: ``GetRrdManifest``, then every chunk of the manifest with
   ``FetchChunks`` (the viewer's columns: chunk_id, chunk_is_static, chunk_byte_offset, chunk_key),
   in requests of about ``--batch-mb`` MB of chunks, one after the other, over gRPC on loopback; the
   client takes each response as bytes and checks that every chunk of the manifest came (by id).
4. An SDK query, as an analyst runs it: ``CatalogClient(...).get_dataset(...)
   .filter_segments([RUN]).filter_contents([LIDAR]).reader(index="frame")`` filtered to the middle
   tenth of the frames, to an Arrow table (best of ``--repeat``; the rows must agree).
5. Peak RSS of each server process (``VmHWM``, its whole life: for the peer, loading included).

MB = 10**6 bytes. Target: ours within 1.5x of the peer's time (ours / rerun <= 1.5).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as `python benchmarks/catalog.py` without the editable install
    sys.path.insert(0, str(ROOT))

import grpc  # noqa: E402
import httpx  # noqa: E402
import pyarrow as pa  # noqa: E402

from benchmarks.codec import MB, ensure_recording, find_rerun_binary, format_table, log  # noqa: E402
from benchmarks.ingest import FleetServer, Server  # noqa: E402
from services.redap.dataframe import dataframe_part  # noqa: E402
from services.redap.pb import cloud_pb2  # noqa: E402
from services.redap.tuid import Tuid  # noqa: E402
from services.rrd.footer import summarize_from_footer  # noqa: E402
from services.rrd.manifest import read_manifest  # noqa: E402
from services.rrd.pb import common_pb2  # noqa: E402
from services.rrd.protowire import fields  # noqa: E402

SERVICE = "/rerun.cloud.v1alpha1.RerunCloudService/"
DATASET = "catalog"
RATIO_TARGET = 1.5
CLIENT_VERSION = [("x-rerun-client-version", "rerun/0.41.0")]
CHANNEL_OPTIONS = [("grpc.max_receive_message_length", 2**31 - 1), ("grpc.max_send_message_length", 2**31 - 1)]
VIEWER_COLUMNS = ["chunk_id", "chunk_is_static", "chunk_byte_offset", "chunk_key"]


class RerunCatalogServer(Server):
    """`rerun server -d catalog=DIR`: Rerun's own catalog server, every run in memory."""

    name = "rerun"

    def __init__(self, workdir: Path, binary: str, folder: Path) -> None:
        super().__init__(workdir)
        self.binary = binary
        self.folder = folder

    def argv_env(self) -> tuple[list[str], dict[str, str]]:
        port, dataset = str(self.grpc_port), f"{DATASET}={self.folder}"
        return [self.binary, "server", "--host", "127.0.0.1", "-p", port, "-d", dataset], dict(os.environ)

    def ready(self) -> bool:
        with grpc.insecure_channel(f"127.0.0.1:{self.grpc_port}") as channel:
            try:
                stub = channel.unary_unary(
                    SERVICE + "Version",
                    request_serializer=cloud_pb2.VersionRequest.SerializeToString,
                    response_deserializer=cloud_pb2.VersionResponse.FromString,
                )
                stub(cloud_pb2.VersionRequest(), timeout=1)
            except grpc.RpcError as exc:
                return bool(exc.code() != grpc.StatusCode.UNAVAILABLE)
        return True


def find_entry(port: int, name: str) -> str | None:
    """The entry id of a dataset by name (FindEntries); None if the server does not answer it."""
    with grpc.insecure_channel(f"127.0.0.1:{port}") as channel:
        call = channel.unary_unary(
            SERVICE + "FindEntries",
            request_serializer=cloud_pb2.FindEntriesRequest.SerializeToString,
            response_deserializer=cloud_pb2.FindEntriesResponse.FromString,
        )
        try:
            found = call(cloud_pb2.FindEntriesRequest(), metadata=CLIENT_VERSION, timeout=30)
        except grpc.RpcError:
            return None
    ids = [e.id.id for e in found.entries if e.name == name]
    return str(Tuid.from_proto(ids[0])) if ids else None


def depot_entry(server: FleetServer, run_id: str, application: str) -> str:
    """Ours: FindEntries, or the dataset id the sealed run's run.json keeps (a depot whose catalog
    server does not list entries yet)."""
    found = find_entry(server.grpc_port, application)
    if found is not None:
        return found
    for path in (server.data_dir / "warm").rglob("run.json"):
        if path.parent.name == run_id:
            return str(json.loads(path.read_text())["dataset_id"])
    raise SystemExit(f"no dataset entry for {application!r}")


def chunk_ids(response: bytes) -> list[bytes]:
    """The chunk id of each ArrowMsg of a serialized FetchChunksResponse, read off the wire."""
    ids = []
    for number, _, start, end in fields(response):
        if number != 1:
            continue
        for inner, _, value, value_end in fields(memoryview(response)[start:end]):
            if inner == 6:  # ArrowMsg.chunk_id: Tuid{fixed64 time_ns = 1; fixed64 inc = 2}
                tuid = bytes(memoryview(response)[start + value : start + value_end])
                ids.append(tuid[1:9][::-1] + tuid[10:18][::-1])
    return ids


def fetch_chunks_call(channel: grpc.Channel) -> Any:
    """FetchChunks on `channel`, its answers as bytes (the client's own decoding is not what is measured)."""
    return channel.unary_stream(
        SERVICE + "FetchChunks",
        request_serializer=cloud_pb2.FetchChunksRequest.SerializeToString,
        response_deserializer=None,
    )


def segment_manifest(channel: grpc.Channel, segment: str, metadata: list[tuple[str, str]]) -> pa.Table:
    """The segment's RRD manifest, by GetRrdManifest, as one table."""
    get_manifest = channel.unary_stream(
        SERVICE + "GetRrdManifest",
        request_serializer=cloud_pb2.GetRrdManifestRequest.SerializeToString,
        response_deserializer=cloud_pb2.GetRrdManifestResponse.FromString,
    )
    request = cloud_pb2.GetRrdManifestRequest(segment_id=common_pb2.SegmentId(id=segment))
    parts = list(get_manifest(request, metadata=metadata, timeout=600))
    return pa.concat_tables([read_manifest(p.rrd_manifest) for p in parts])


def open_segment(port: int, entry: str, segment: str, batch_bytes: int) -> dict[str, Any]:
    """GetRrdManifest, then every chunk with FetchChunks: what opening the segment in the viewer asks."""
    metadata = [*CLIENT_VERSION, ("x-rerun-entry-id", entry)]
    with grpc.insecure_channel(f"127.0.0.1:{port}", options=CHANNEL_OPTIONS) as channel:
        fetch = fetch_chunks_call(channel)
        start = time.perf_counter()
        manifest = segment_manifest(channel, segment, metadata)
        manifest_s = time.perf_counter() - start
        wanted = set(manifest.column("chunk_id").to_pylist())
        sizes = manifest.column("chunk_byte_size").to_pylist()
        columns = manifest.select(VIEWER_COLUMNS)
        received: list[bytes] = []
        responses = bytes_in = 0
        first = row = 0
        while first < manifest.num_rows:
            total = 0
            row = first
            while row < manifest.num_rows and (row == first or total + sizes[row] <= batch_bytes):
                total += sizes[row]
                row += 1
            request_part = dataframe_part(columns.slice(first, row - first))
            for answer in fetch(cloud_pb2.FetchChunksRequest(chunk_infos=[request_part]), metadata=CLIENT_VERSION):
                responses += 1
                bytes_in += len(answer)
                received += chunk_ids(answer)
            first = row
        seconds = time.perf_counter() - start
    if set(received) != wanted or len(received) != len(wanted):
        raise SystemExit(f"port {port}: {len(received)} chunks received, {len(wanted)} in the manifest")
    return {
        "seconds": seconds,
        "manifest_s": manifest_s,
        "chunks": len(received),
        "responses": responses,
        "bytes_received": bytes_in,
    }


QUERIED_ENTITY = "/vehicle/lidar/points"


def sdk_query(port: int, dataset: str, run_id: str, frames: tuple[int, int]) -> dict[str, Any]:
    """Time the SDK's reader over one entity and a window of frames (the querying is the client's:
    the server answers FindChunks and FetchChunks)."""
    import datafusion
    import rerun as rr

    started = time.perf_counter()
    client = rr.catalog.CatalogClient(f"rerun+http://127.0.0.1:{port}")
    reader = client.get_dataset(dataset).filter_segments([run_id]).filter_contents([QUERIED_ENTITY])
    df = reader.reader(index="frame")
    low, high = frames
    table = df.filter(
        (datafusion.col("frame") >= datafusion.lit(low)) & (datafusion.col("frame") < datafusion.lit(high))
    )
    result = table.to_arrow_table()
    return {"seconds": time.perf_counter() - started, "rows": result.num_rows, "bytes": result.nbytes}


def prepare_ours(workdir: Path, source: Path, run_id: str) -> None:
    """Upload and seal the run in a first `fleet serve`, stopped after."""
    loader = FleetServer(workdir)
    try:
        loader.start(timeout=120)
        base = f"http://127.0.0.1:{loader.http_port}"
        with open(source, "rb") as fh:
            answer = httpx.post(f"{base}/v1/uploads", content=iter(lambda: fh.read(1 << 20), b""), timeout=1800)
        answer.raise_for_status()
        assert answer.json()["runs"] == [run_id], answer.text
        sealed = httpx.post(f"{base}/v1/runs/{run_id}/promote", timeout=1800)
        if sealed.status_code != 200:
            raise SystemExit(f"promote: HTTP {sealed.status_code}: {sealed.text}")
    finally:
        loader.stop()


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data-dir", type=Path, default=ROOT / "benchmarks" / "data")
    parser.add_argument("--mb", type=float, default=1000, help="size of the run (default 1000 MB)")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--batch-mb", type=float, default=64, help="chunk bytes asked per FetchChunks call")
    parser.add_argument("--rerun", help="the rerun executable (default: the native binary of rerun-sdk)")
    parser.add_argument("--tmp", type=Path, default=None, help="where the servers' folders go (default: $TMPDIR)")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    if args.repeat < 1 or args.mb <= 0 or args.batch_mb <= 0:
        parser.error("--repeat, --mb and --batch-mb must be positive")

    data_dir = args.data_dir.resolve()
    info = ensure_recording(data_dir, "catalog.rrd", {"kind": "big", "big_mb": args.mb}, ["gen-big", str(args.mb)])
    source = data_dir / "catalog.rrd"
    summary = summarize_from_footer(str(source))
    assert summary is not None, "catalog.rrd has no footer"
    store = next(s for s in summary.stores.values() if s.store_id.kind.name == "RECORDING")
    run_id, application = store.store_id.recording_id, store.store_id.application_id
    rerun_bin, _ = find_rerun_binary(args.rerun)
    batch_bytes = int(args.batch_mb * MB)

    root = Path(tempfile.mkdtemp(prefix="catalog-bench-", dir=args.tmp))
    servers: dict[str, Server] = {}
    results: dict[str, Any] = {"run_bytes": source.stat().st_size, "chunks": info["chunks"], "batch_mb": args.batch_mb}
    try:
        ours_dir = root / "ours"
        ours_dir.mkdir()
        log(f"uploading and sealing {source} ({source.stat().st_size / MB:.1f} MB) in the depot ...")
        prepare_ours(ours_dir, source, run_id)
        peer_dir = root / "rerun"
        (peer_dir / "data").mkdir(parents=True)
        try:  # `rerun server -d` skips symbolic links: a hard link, else a copy
            os.link(source, peer_dir / "data" / "catalog.rrd")
        except OSError:
            shutil.copy(source, peer_dir / "data" / "catalog.rrd")
        servers["ours"] = FleetServer(ours_dir)
        servers["rerun"] = RerunCatalogServer(peer_dir, rerun_bin, peer_dir / "data")
        for name, server in servers.items():
            started = time.perf_counter()
            server.start(timeout=600)
            results[f"{name}_start_s"] = time.perf_counter() - started
        entries = {
            "ours": depot_entry(servers["ours"], run_id, application),  # type: ignore[arg-type]
            "rerun": find_entry(servers["rerun"].grpc_port, DATASET),
        }
        runs: dict[str, list[dict[str, Any]]] = {"ours": [], "rerun": []}
        for i in range(args.repeat):
            for name in ("ours", "rerun") if i % 2 == 0 else ("rerun", "ours"):
                entry = entries[name]
                assert entry is not None, f"{name}: no dataset entry"
                run = open_segment(servers[name].grpc_port, entry, run_id, batch_bytes)
                log(
                    f"{name} #{i + 1}: {run['seconds']:.2f} s ({run['manifest_s'] * 1000:.0f} ms manifest), "
                    f"{run['chunks']} chunks in {run['responses']} responses, {run['bytes_received'] / MB:.0f} MB"
                )
                runs[name].append(run)
        frames = store.timelines["frame"]
        window = (
            frames.min + (frames.max - frames.min) * 45 // 100,
            frames.min + (frames.max - frames.min) * 55 // 100,
        )
        names = {"ours": application, "rerun": DATASET}
        queries: dict[str, list[dict[str, Any]]] = {"ours": [], "rerun": []}
        for i in range(args.repeat):
            for name in ("ours", "rerun") if i % 2 == 0 else ("rerun", "ours"):
                query = sdk_query(servers[name].grpc_port, names[name], run_id, window)
                log(f"{name} query #{i + 1}: {query['seconds']:.2f} s, {query['rows']} rows")
                queries[name].append(query)
        assert queries["ours"][0]["rows"] == queries["rerun"][0]["rows"] > 0, "the two servers' rows differ"
        for name, server in servers.items():
            best = min(runs[name], key=lambda r: r["seconds"])
            results[name] = {**best, "runs_s": [r["seconds"] for r in runs[name]], "peak_rss_mb": server.peak_rss_mb()}
            results[name]["query"] = min(queries[name], key=lambda q: q["seconds"])
    finally:
        for server in servers.values():
            server.stop()
        shutil.rmtree(root, ignore_errors=True)

    ratio = results["ours"]["seconds"] / results["rerun"]["seconds"]
    results["ratio"] = ratio
    query_ratio = results["ours"]["query"]["seconds"] / results["rerun"]["query"]["seconds"]
    results["query_ratio"] = query_ratio
    if args.json:
        print(json.dumps(results, indent=2))
        return
    size = results["run_bytes"]
    print(
        f"run: {size / MB:.1f} MB, {results['chunks']} chunks; GetRrdManifest + every chunk by FetchChunks "
        f"(~{args.batch_mb:g} MB a call) over gRPC on loopback; best of {args.repeat}"
    )
    rows = []
    for name, label in (("ours", "depot, warm run on local disk"), ("rerun", "rerun server -d (in memory)")):
        r = results[name]
        rows.append(
            [
                label,
                f"{r['seconds']:.2f}",
                f"{size / MB / r['seconds']:.0f}",
                f"{r['manifest_s'] * 1000:.0f}",
                str(r["responses"]),
                f"{r['bytes_received'] / MB:.0f}",
                f"{r['peak_rss_mb']:.0f}",
            ]
        )
    print(
        format_table(
            ["server", "open s", "MB/s", "manifest ms", "responses", "MB received", "peak RSS MB"], rows, "lrrrrrr"
        )
    )
    verdict = "met" if ratio <= RATIO_TARGET else "MISSED"
    print(f"opening the run, ours / rerun: {ratio:.2f}x the time (target <= {RATIO_TARGET}x: {verdict})")
    query_rows = results["ours"]["query"]["rows"]
    print(
        f"SDK query ({QUERIED_ENTITY}, frames {window[0]}..{window[1]}, {query_rows} rows): "
        f"ours {results['ours']['query']['seconds']:.2f} s, rerun {results['rerun']['query']['seconds']:.2f} s, "
        f"{query_ratio:.2f}x (target <= {RATIO_TARGET}x: {'met' if query_ratio <= RATIO_TARGET else 'MISSED'})"
    )


if __name__ == "__main__":
    main()
