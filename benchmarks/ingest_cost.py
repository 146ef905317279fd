"""Benchmark: what filing one one-row chunk costs in process, in CPU instructions (repeatable on a
shared machine, where timings move by a fifth from one hour to the next) or in CPU time.

    .venv/bin/python benchmarks/ingest_cost.py [--messages 5000] [--cpu] [--stamped] [--json]

The requests are those `benchmarks/ingest.py` sends for one robot of ``small.rrd`` (one-row chunks of
scalars, made with the real SDK by that script's helpers if missing). Each is decoded as the gRPC
handler does (`requests.decode_request`) and filed by `IngestService.accept` into a hot tier in a temporary
folder, with the replay of live streams on and the start-up objects frozen out of garbage
collection, as in `fleet serve`; no catalog, no transport.
``--stamped``: each chunk re-encoded with the two times rerun-sdk stamps on every chunk it streams
over gRPC (`rerun:timestamp_sdk_ipc_encoded`, `rerun:timestamp_sdk_grpc_sink`), which a recording
saved to a file, like small.rrd, lacks: what a live robot's stream costs.

Instructions (the default; needs valgrind): the script runs itself twice under `valgrind
--tool=callgrind`, once filing 2,000 messages (layouts and caches warm) and once 2,000 + N, at the
same time on two cores; the difference over N is the figure. CPU (``--cpu``): the CPU seconds of
filing N messages after 2,000 in this process, per message (best of 3). The figure says how many of
the ingest path's modules ran compiled (FLEET_COMPILE=1; for a tree built in place, run the script
from that tree).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import shutil
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks.ingest import ensure_small, prepare_requests  # noqa: E402 - after the sys.path fix above

WARM = 2000


def requests(count: int, stamped: bool = False) -> list[bytes]:
    data_dir = ROOT / "benchmarks" / "data"
    ensure_small(data_dir)  # the one benchmarks/ingest.py sends by default
    prepared, _ = prepare_requests(str(data_dir / "small.rrd"), [0], stamped=stamped)
    return prepared[0][:count]


def file_messages(batch: list[bytes], warm: int) -> float:
    """File `batch`; the CPU seconds of all but its first `warm` messages."""
    from services.hot.store import HotStore
    from services.ingest.replay import ReplayHub
    from services.ingest.requests import decode_request
    from services.ingest.service import IngestService
    from services.runtime import freeze_startup_objects
    from services.settings import Durability

    tmp = Path(tempfile.mkdtemp(prefix="ingest-cost-"))
    try:
        hot = HotStore(tmp / "hot", durability=Durability.INTERVAL, interval_ms=200, min_free_bytes=0)
        service = IngestService(
            hot,
            None,
            default_robot="robot",
            max_streams=10,
            close_after=dt.timedelta(hours=1),
            replay=ReplayHub(64 << 20),
        )
        source = service.open_source(live=True)
        freeze_startup_objects()  # as `fleet serve` does once started: collections walk what filing makes
        offset, started = 0, 0.0
        for i, request in enumerate(batch):
            if i == warm:
                started = time.process_time()
            service.accept(source, decode_request(request, offset))
            offset += len(request)
        spent = time.process_time() - started
        service.close_source(source)
        service.close()
        return spent
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def save(batch: list[bytes], path: Path) -> None:
    path.write_bytes(b"".join(len(r).to_bytes(4, "little") + r for r in batch))


def load(path: Path, count: int) -> list[bytes]:
    data, at = path.read_bytes(), 0
    batch: list[bytes] = []
    while at < len(data) and len(batch) < count:
        size = int.from_bytes(data[at : at + 4], "little")
        batch.append(data[at + 4 : at + 4 + size])
        at += 4 + size
    return batch


def instructions(saved: Path, count: int) -> int:
    """Instructions callgrind counts for this script filing the first `count` messages of `saved`
    (the whole process: start-up included, the same in both runs)."""
    command = [sys.executable, __file__, "--child", str(saved), str(count)]
    out = subprocess.run(
        ["valgrind", "--tool=callgrind", "--callgrind-out-file=/dev/null", *command],
        capture_output=True,
        text=True,
        check=True,
    )
    for line in out.stderr.splitlines():
        if "Collected :" in line:
            return int(line.split()[-1])
    raise RuntimeError(f"callgrind printed no total:\n{out.stderr[-2000:]}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--messages", type=int, default=5000, help="messages counted, after 2,000 (default 5000)")
    parser.add_argument("--cpu", action="store_true", help="CPU time instead of instructions (no valgrind needed)")
    parser.add_argument("--stamped", action="store_true", help="chunks stamped as a live SDK stream's are")
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--child", nargs=2, help=argparse.SUPPRESS)  # under valgrind: FILE COUNT
    args = parser.parse_args()
    if args.child is not None:
        count = int(args.child[1])
        file_messages(load(Path(args.child[0]), count), count)
        return
    batch = requests(WARM + args.messages, args.stamped)
    if len(batch) < WARM + args.messages:
        sys.exit(f"small.rrd holds {len(batch)} messages: ask for at most {len(batch) - WARM} (--messages)")
    from services.compiled import compiled_modules, compiled_summary

    compiled = compiled_summary()
    if args.cpu:
        figure = min(file_messages(batch, WARM) for _ in range(3)) / args.messages * 1e6
        result = {"messages": args.messages, "stamped": args.stamped, "cpu_us_per_message": round(figure, 1)}
        text = f"{figure:.1f} us of CPU per one-row chunk (best of 3, {args.messages} messages; {compiled})"
    else:
        if shutil.which("valgrind") is None:
            sys.exit("valgrind is not installed: apt-get install valgrind, or use --cpu")
        with tempfile.TemporaryDirectory(prefix="ingest-cost-") as tmp:
            saved = Path(tmp) / "requests"
            save(batch, saved)
            with ThreadPoolExecutor(2) as pool:
                base, total = pool.map(lambda n: instructions(saved, n), [WARM, WARM + args.messages])
        figure = (total - base) / args.messages
        result = {"messages": args.messages, "stamped": args.stamped, "instructions_per_message": round(figure)}
        text = f"{figure:,.0f} instructions per one-row chunk ({args.messages} messages, callgrind; {compiled})"
    result["compiled_modules"] = len(compiled_modules())
    print(json.dumps(result) if args.json else text)


if __name__ == "__main__":
    main()
