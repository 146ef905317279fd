"""Benchmark: what ingest's check of a chunk costs in process (`chunk_meta` then `check_chunk`: its
schema, its header and every value, fully validated), beside decompressing the chunk with
`lz4.block` alone, over the recordings of benchmarks/ingest.py.

    .venv/bin/python -m benchmarks.chunk_check [--passes 7] [--json]

big.rrd: 93 chunks of 2.4-2.6 MB (point clouds and images; their metadata read from the first bytes
of each payload, the rest decompressed by the check); small.rrd: 50,001 one-row chunks of scalars
(checked from their record batch body). CPU time of the best pass (`time.process_time`), per chunk.
The recordings are made with the real SDK by benchmarks/ingest.py's helpers if missing.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import lz4.block

ROOT = Path(__file__).resolve().parents[1]
if sys.path[0] != str(ROOT):  # run as a script, the benchmarks folder (its catalog.py) must not shadow
    sys.path.insert(0, str(ROOT))

from benchmarks.codec import ensure_recording  # noqa: E402 - after the sys.path fix above
from benchmarks.ingest import ensure_small  # noqa: E402
from services.rrd import ArrowMessage, iter_events  # noqa: E402
from services.rrd.chunk import chunk_meta  # noqa: E402
from services.rrd.messages import Compression  # noqa: E402
from services.rrd.validate import check_chunk  # noqa: E402

DATA = ROOT / "benchmarks" / "data"


def best_us(messages: list[ArrowMessage], passes: int, work: str) -> float:
    best = float("inf")
    for _ in range(passes):
        start = time.process_time()
        for msg in messages:
            if work == "check":
                check_chunk(msg, chunk_meta(msg))
            elif msg.compression == Compression.LZ4:
                lz4.block.decompress(msg.payload, uncompressed_size=msg.uncompressed_size)
        best = min(best, time.process_time() - start)
    return best / len(messages) * 1e6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--passes", type=int, default=7)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    ensure_recording(DATA, "big.rrd", {"kind": "big", "big_mb": 220.0}, ["gen-big", "220.0"])
    ensure_small(DATA)
    results = {}
    for name in ("big", "small"):
        messages = [e for e in iter_events(DATA / f"{name}.rrd") if isinstance(e, ArrowMessage)]
        size = sum(len(m.raw) for m in messages) / len(messages)
        results[name] = {
            "chunks": len(messages),
            "mean_bytes": round(size),
            "check_us": round(best_us(messages, args.passes, "check"), 1),
            "lz4_block_us": round(best_us(messages, args.passes, "lz4"), 1),
        }
    if args.json:
        print(json.dumps(results))
        return
    for name, r in results.items():
        print(
            f"{name}: {r['chunks']} chunks of {r['mean_bytes'] / 1e3:,.1f} KB: ingest's check {r['check_us']:,} us "
            f"a chunk; lz4.block.decompress alone {r['lz4_block_us']:,} us (CPU, best of {args.passes})"
        )


if __name__ == "__main__":
    main()
