"""Benchmark: scan + index of real Rerun recordings, next to `rerun rrd stats` on the same files.

    /work/venv/bin/python benchmarks/codec.py [--data-dir DIR] [--big-mb 220] [--small-chunks 50000]
                                              [--repeat 3] [--json]

1. Generates (once; reused while the parameters match) two recordings with the real rerun SDK, each in
   its own subprocess:
   * ``big.rrd``:   Points3D clouds (160k points, ~2.6 MB per log call) and RGB images (1024x768,
     ~2.4 MB per log call) on a ``frame`` sequence timeline (plus the automatic ``log_time``),
     until the file holds at least ``--big-mb`` MB;
   * ``small.rrd``: ``--small-chunks`` Scalars log calls spread over ``--small-entities`` entities, with
     the SDK batcher set to ``flush_num_rows=1`` so that every log call becomes its own 1-row chunk.
   Chunk and row counts are checked with our own decoder.
2. Times on each file (page cache warm, best of ``--repeat``, wall clock with ``time.perf_counter``):
   * ours, scan + index: ``summarize(iter_events(path), path)`` (what ``fleet rrd inspect`` does: every
     message decoded, ``chunk_meta`` for every chunk), in a worker process, timed in-process;
   * ours, footer index: ``summarize_from_footer(path)`` (the same summary from the RRD footer);
   * ours, scan only: ``iter_events(path)`` (framing + protobuf, no LZ4 / Arrow);
   * ours, whole process: ``fleet rrd inspect --scan FILE`` and ``fleet rrd inspect FILE`` (footer),
     interpreter start and imports included;
   * the peer: ``rerun rrd stats FILE`` (the native ``rerun`` binary of rerun-sdk, full decode; its
     output is captured, never printed), and for reference ``rerun rrd stats --no-decode FILE``
     (transport-level statistics only, no Arrow decoding: less work than ours). Its only other flag,
     ``--continue-on-error``, changes nothing on valid files.
   Every measurement runs in its own child process so that its peak RSS (``wait4`` rusage) and CPU time
   are its own.

MB = 10**6 bytes. ``ours/rerun`` is the throughput ratio (rerun time / our time): >= 1 meets the target.
"""

from __future__ import annotations

import argparse
import importlib.metadata
import importlib.util
import json
import os
import platform
import re
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as `python benchmarks/codec.py` without the editable install
    sys.path.insert(0, str(ROOT))

GENERATOR_VERSION = 1
MB = 1_000_000
POINTS_PER_CLOUD = 160_000  # 12 B positions + 4 B colors per point: ~2.6 MB per log call
IMAGE_SHAPE = (768, 1024, 3)  # uint8 RGB: ~2.4 MB per log call
BIG_FLUSH_EVERY = 2  # frames between file size checks while generating big.rrd


# --- child processes ------------------------------------------------------------------------------


@dataclass
class ProcResult:
    argv: list[str]
    exit_code: int
    wall_s: float
    cpu_s: float  # user + system
    peak_rss_mb: float
    stdout: str
    stderr: str


def run_process(argv: list[str], env: dict[str, str] | None = None) -> ProcResult:
    """Run `argv` (argv[0] an absolute path) with stdout/stderr captured to files; wall clock around
    spawn + exit, CPU time and peak RSS of that very child from wait4."""
    with tempfile.TemporaryDirectory(prefix="codec-bench-") as tmp:
        out, err = os.path.join(tmp, "stdout"), os.path.join(tmp, "stderr")
        flags = os.O_WRONLY | os.O_CREAT | os.O_TRUNC
        actions = [
            (os.POSIX_SPAWN_OPEN, 0, os.devnull, os.O_RDONLY, 0),
            (os.POSIX_SPAWN_OPEN, 1, out, flags, 0o600),
            (os.POSIX_SPAWN_OPEN, 2, err, flags, 0o600),
        ]
        start = time.perf_counter()
        pid = os.posix_spawn(argv[0], argv, env if env is not None else dict(os.environ), file_actions=actions)
        _, status, usage = os.wait4(pid, 0)
        wall = time.perf_counter() - start
        stdout = Path(out).read_text(errors="replace")
        stderr = Path(err).read_text(errors="replace")
    return ProcResult(
        argv,
        os.waitstatus_to_exitcode(status),
        wall,
        usage.ru_utime + usage.ru_stime,
        usage.ru_maxrss * 1024 / MB,
        stdout,
        stderr,
    )  # ru_maxrss: KiB


def checked(result: ProcResult, what: str) -> ProcResult:
    if result.exit_code != 0:
        tail = "\n".join((result.stderr or result.stdout).strip().splitlines()[-20:])
        raise SystemExit(f"{what} failed (exit {result.exit_code}): {' '.join(result.argv)}\n{tail}")
    return result


def worker_argv(*args: str) -> list[str]:
    return [sys.executable, str(Path(__file__).resolve()), "_worker", *args]


# --- workers (run in child processes: `codec.py _worker ...`) ---------------------------------------


def worker_gen_big(path: str, target_mb: float) -> dict[str, Any]:
    import numpy as np
    import rerun as rr

    rec = rr.RecordingStream("codec_bench_big", recording_id="codec-bench-big")
    rec.save(path)
    rng = np.random.default_rng(20241)
    height, width, _ = IMAGE_SHAPE
    yy, xx = np.mgrid[0:height, 0:width]
    base = np.stack([xx * 255 // width, yy * 255 // height, (xx + yy) * 255 // (width + height)], axis=-1).astype(
        np.uint8
    )
    frame = 0
    while True:
        rec.set_time("frame", sequence=frame)
        positions = rng.standard_normal((POINTS_PER_CLOUD, 3), dtype=np.float32) * 20.0
        colors = rng.integers(0, 256, (POINTS_PER_CLOUD, 3), dtype=np.uint8)
        rec.log("/vehicle/lidar/points", rr.Points3D(positions, colors=colors, radii=0.02))
        image = base + rng.integers(0, 16, IMAGE_SHAPE, dtype=np.uint8)  # a gradient with sensor noise
        rec.log("/vehicle/camera/front", rr.Image(image, color_model="RGB"))
        frame += 1
        if frame % BIG_FLUSH_EVERY == 0:
            rec.flush()
            if os.path.getsize(path) >= target_mb * MB:
                break
    rec.flush()
    rec.disconnect()  # closes the file sink: writes the End message and the footer
    return {"frames": frame, "log_calls": 2 * frame}


def worker_gen_small(path: str, chunks: int, entities: int) -> dict[str, Any]:
    import rerun as rr

    # Flush after every row: each log call becomes its own 1-row chunk (what a low-latency or
    # badly configured robot logger produces). The default batcher would merge them into a few chunks.
    config = rr.ChunkBatcherConfig(flush_num_rows=1)
    rec = rr.RecordingStream("codec_bench_small", recording_id="codec-bench-small", batcher_config=config)
    rec.save(path)
    names = [f"/robot_{e // 10:02d}/signal_{e % 10}" for e in range(entities)]
    for i in range(chunks):
        rec.set_time("step", sequence=i // entities)
        rec.log(names[i % entities], rr.Scalars(float(i % 997) * 0.01))
    rec.flush()
    rec.disconnect()
    return {"log_calls": chunks, "batcher": str(config).replace("\n", " ")}


def worker_ours(mode: str, path: str, repeat: int) -> dict[str, Any]:
    import resource

    from services.rrd.decoder import iter_events
    from services.rrd.footer import summarize_from_footer
    from services.rrd.messages import ArrowMessage
    from services.rrd.summary import summarize

    baseline_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / MB
    walls: list[float] = []
    cpus: list[float] = []
    counts: dict[str, Any] = {}
    for _ in range(repeat):
        wall0, cpu0 = time.perf_counter(), time.process_time()
        if mode == "index":
            summary = summarize(iter_events(path), path)
            wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
            if summary.error is not None:
                raise SystemExit(f"{path}: {summary.error}")
            stores = list(summary.stores.values())
            counts = {
                "chunks": sum(s.chunks for s in stores),
                "rows": sum(s.rows for s in stores),
                "entities": sum(len(s.entities) for s in stores),
                "timelines": sorted({t for s in stores for t in s.timelines}),
                "stores": len(stores),
            }
        elif mode == "footer":
            footer_summary = summarize_from_footer(path)
            wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
            if footer_summary is None:
                raise SystemExit(f"{path}: no usable RRD footer")
            counts = {"chunks": sum(s.chunks for s in footer_summary.stores.values())}
        elif mode == "scan":
            chunks = payload = 0
            for event in iter_events(path):
                if isinstance(event, ArrowMessage):
                    chunks += 1
                    payload += event.size
            wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
            counts = {"chunks": chunks, "arrow_msg_bytes": payload}
        else:
            raise SystemExit(f"unknown mode {mode!r}")
        walls.append(wall)
        cpus.append(cpu)
    return {"walls": walls, "cpus": cpus, "baseline_rss_mb": baseline_rss, **counts}


def worker_main(args: list[str]) -> None:
    kind, rest = args[0], args[1:]
    if kind == "gen-big":
        result = worker_gen_big(rest[0], float(rest[1]))
    elif kind == "gen-small":
        result = worker_gen_small(rest[0], int(rest[1]), int(rest[2]))
    elif kind == "ours":
        result = worker_ours(rest[0], rest[1], int(rest[2]))
    else:
        raise SystemExit(f"unknown worker {kind!r}")
    print(json.dumps(result))


# --- data generation ------------------------------------------------------------------------------


def log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def ensure_recording(data_dir: Path, name: str, params: dict[str, Any], gen_args: list[str]) -> dict[str, Any]:
    """The recording `name` in `data_dir`, generated unless present with the same parameters."""
    path = data_dir / name
    sidecar = data_dir / (name + ".json")
    wanted = {"generator": GENERATOR_VERSION, "rerun_sdk": importlib.metadata.version("rerun-sdk"), **params}
    if path.exists() and sidecar.exists():
        info: dict[str, Any] = json.loads(sidecar.read_text())
        if info.get("params") == wanted and info.get("size_bytes") == path.stat().st_size:
            log(f"reusing {path} ({info['size_bytes'] / MB:.1f} MB, {info['chunks']} chunks)")
            return info
    data_dir.mkdir(parents=True, exist_ok=True)
    tmp = data_dir / ("tmp-" + name)
    tmp.unlink(missing_ok=True)
    log(f"generating {path} with rerun-sdk {wanted['rerun_sdk']} ...")
    gen = checked(run_process(worker_argv(*gen_args[:1], str(tmp), *gen_args[1:])), f"generating {name}")
    verify = checked(run_process(worker_argv("ours", "index", str(tmp), "1")), f"decoding {name}")
    counts = json.loads(verify.stdout)
    info = {
        "params": wanted,
        "size_bytes": tmp.stat().st_size,
        "generated_in_s": round(gen.wall_s, 2),
        "generator_output": json.loads(gen.stdout),
        **{k: counts[k] for k in ("chunks", "rows", "entities", "timelines")},
    }
    os.replace(tmp, path)
    sidecar.write_text(json.dumps(info, indent=2) + "\n")
    log(
        f"generated {path}: {info['size_bytes'] / MB:.1f} MB in {gen.wall_s:.1f} s; our decoder counts "
        f"{info['chunks']} chunks, {info['rows']} rows, {info['entities']} entities, "
        f"timelines {', '.join(info['timelines'])}"
    )
    return info


# --- measurements ---------------------------------------------------------------------------------


@dataclass
class Measurement:
    name: str
    best_s: float
    runs_s: list[float]
    cpu_s: float  # CPU time (user + sys) of the best run
    peak_rss_mb: float
    note: str = ""
    extra: dict[str, Any] = field(default_factory=dict)

    def rates(self, size: int, chunks: int) -> tuple[float, float]:
        return size / MB / self.best_s, chunks / self.best_s


def measure_ours(mode: str, path: Path, repeat: int) -> Measurement:
    result = checked(run_process(worker_argv("ours", mode, str(path), str(repeat))), f"ours {mode}")
    data = json.loads(result.stdout)
    best = min(range(repeat), key=lambda i: data["walls"][i])
    name, note = {
        "index": ("ours scan+index (in-process)", "summarize(iter_events(path)): every chunk read"),
        "footer": ("ours footer index (in-process)", "summarize_from_footer(path): the RRD footer"),
        "scan": ("ours scan only (in-process)", "iter_events(path), no chunk_meta"),
    }[mode]
    extra = {k: v for k, v in data.items() if k not in ("walls", "cpus")}
    return Measurement(
        name,
        data["walls"][best],
        data["walls"],
        data["cpus"][best],
        result.peak_rss_mb,
        note + f"; RSS after imports {data['baseline_rss_mb']:.0f} MB",
        extra,
    )


def measure_process(name: str, argv: list[str], repeat: int, note: str = "") -> tuple[Measurement, ProcResult]:
    runs = [checked(run_process(argv), name) for _ in range(repeat)]
    best = min(runs, key=lambda r: r.wall_s)
    return Measurement(
        name, best.wall_s, [r.wall_s for r in runs], best.cpu_s, max(r.peak_rss_mb for r in runs), note
    ), best


def parse_rerun_chunks(stdout: str) -> int | None:
    match = re.search(r"^num_chunks = (.+)$", stdout, re.MULTILINE)
    if match is None:
        return None
    digits = re.sub(r"\D", "", match.group(1))  # "50 001" uses a thin space as thousands separator
    return int(digits) if digits else None


def warm_page_cache(path: Path) -> None:
    with open(path, "rb") as fh:
        while fh.read(16 * 1024 * 1024):
            pass


def find_rerun_binary(explicit: str | None) -> tuple[str, str]:
    """The native `rerun` executable (the venv's `rerun` script is a Python wrapper that adds ~70 ms
    of interpreter start-up to every call, so it is bypassed), and how it was found."""
    if explicit:
        return str(Path(explicit).resolve()), "--rerun"
    if os.environ.get("RERUN_CLI_PATH"):
        return os.environ["RERUN_CLI_PATH"], "RERUN_CLI_PATH"
    spec = importlib.util.find_spec("rerun_cli")
    for folder in (spec.submodule_search_locations or []) if spec is not None else []:
        native = Path(folder) / "rerun"
        if native.is_file():
            return str(native), "rerun_cli package (native binary behind the `rerun` script)"
    script = Path(sys.executable).parent / "rerun"
    if script.is_file():
        return str(script), "venv script"
    raise SystemExit("cannot find the rerun CLI: pass --rerun PATH")


def bench_file(label: str, path: Path, info: dict[str, Any], rerun_bin: str, repeat: int) -> dict[str, Any]:
    size = path.stat().st_size
    log(f"timing {label}: {size / MB:.1f} MB, {info['chunks']} chunks, best of {repeat} ...")
    warm_page_cache(path)
    index = measure_ours("index", path, repeat)
    footer = measure_ours("footer", path, repeat)
    scan = measure_ours("scan", path, repeat)
    chunks = int(index.extra["chunks"])
    if int(footer.extra["chunks"]) != chunks:
        log(f"WARNING: {label}: the footer lists {footer.extra['chunks']} chunks, the scan {chunks}")
    fleet_code = f"import sys; sys.path.insert(0, {str(ROOT)!r}); from services.cli.main import main; main()"
    fleet_argv = [sys.executable, "-c", fleet_code, "rrd", "inspect", "--scan", str(path)]
    fleet, _ = measure_process(
        "ours: fleet rrd inspect --scan (whole process)", fleet_argv, repeat, "interpreter start + imports included"
    )
    fleet_footer, _ = measure_process(
        "ours: fleet rrd inspect (whole process)",
        [*fleet_argv[:-2], str(path)],
        repeat,
        "footer index; interpreter start + imports included",
    )
    peer, peer_run = measure_process(
        "rerun rrd stats", [rerun_bin, "rrd", "stats", str(path)], repeat, "default invocation: decodes every chunk"
    )
    no_decode, _ = measure_process(
        "rerun rrd stats --no-decode",
        [rerun_bin, "rrd", "stats", "--no-decode", str(path)],
        repeat,
        "reference only: transport level, Arrow never decoded (less work)",
    )
    peer_chunks = parse_rerun_chunks(peer_run.stdout)
    peer.extra = {"num_chunks": peer_chunks, "stdout_lines": peer_run.stdout.count("\n")}
    if peer_chunks is not None and peer_chunks != chunks:
        log(f"WARNING: {label}: rerun rrd stats counts {peer_chunks} chunks, we count {chunks}")
    measurements = [index, footer, scan, fleet, fleet_footer, peer, no_decode]
    return {
        "file": label,
        "path": str(path),
        "size_bytes": size,
        "size_mb": round(size / MB, 3),
        "chunks": chunks,
        "rows": index.extra["rows"],
        "entities": index.extra["entities"],
        "timelines": index.extra["timelines"],
        "rerun_num_chunks": peer_chunks,
        "ours_mb_s": round(size / MB / index.best_s, 2),
        "ours_chunks_s": round(chunks / index.best_s, 1),
        "rerun_mb_s": round(size / MB / peer.best_s, 2),
        "rerun_chunks_s": round(chunks / peer.best_s, 1),
        "ratio_ours_rerun": round(peer.best_s / index.best_s, 3),
        "ratio_footer_rerun": round(peer.best_s / footer.best_s, 3),
        "ratio_whole_process": round(peer.best_s / fleet.best_s, 3),
        "measurements": [
            {**asdict(m), "mb_s": round(m.rates(size, chunks)[0], 2), "chunks_s": round(m.rates(size, chunks)[1], 1)}
            for m in measurements
        ],
        "generation": {k: v for k, v in info.items() if k not in ("chunks", "rows", "entities", "timelines")},
    }


# --- output ---------------------------------------------------------------------------------------


def format_table(headers: list[str], rows: list[list[str]], align: str) -> str:
    """A plain-text table; `align` has one letter per column: l(eft) or r(ight)."""
    widths = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(headers)]

    def line(cells: list[str]) -> str:
        return "  ".join(
            c.ljust(w) if a == "l" else c.rjust(w) for c, w, a in zip(cells, widths, align, strict=True)
        ).rstrip()

    return "\n".join([line(headers), line(["-" * w for w in widths]), *(line(r) for r in rows)])


def print_report(report: dict[str, Any]) -> None:
    env = report["environment"]
    print(f"rerun rrd stats: {env['rerun_binary']} ({env['rerun_version']}; found via {env['rerun_found_via']})")
    print(
        f"python {env['python']}, {env['cpus']} CPUs (load average {env['load_average_1m_at_start']} at start); "
        f"page cache warm; best of {env['repeat']}; MB = 10^6 bytes"
    )
    print()
    files = report["files"]
    print(
        format_table(
            [
                "file",
                "size MB",
                "chunks",
                "ours MB/s",
                "ours chunks/s",
                "rrd stats MB/s",
                "rrd stats chunks/s",
                "ours/rerun",
                "(whole process)",
                "footer/rerun",
            ],
            [
                [
                    f["file"],
                    f"{f['size_mb']:.1f}",
                    f"{f['chunks']:,}",
                    f"{f['ours_mb_s']:.1f}",
                    f"{f['ours_chunks_s']:,.0f}",
                    f"{f['rerun_mb_s']:.1f}",
                    f"{f['rerun_chunks_s']:,.0f}",
                    f"{f['ratio_ours_rerun']:.2f}x",
                    f"{f['ratio_whole_process']:.2f}x",
                    f"{f['ratio_footer_rerun']:.1f}x",
                ]
                for f in files
            ],
            "lrrrrrrrrr",
        )
    )
    print()
    print(
        "ours/rerun = rerun time / our scan+index time, every chunk read (>= 1.00x meets the target); "
        "(whole process) = same with `fleet rrd inspect --scan FILE` as a process; "
        "footer/rerun = with the index read from the file's RRD footer instead"
    )
    print()
    rows = []
    for f in files:
        for i, m in enumerate(f["measurements"]):
            rows.append(
                [
                    f["file"] if i == 0 else "",
                    m["name"],
                    f"{m['best_s']:.3f}",
                    f"{m['mb_s']:.1f}",
                    f"{m['chunks_s']:,.0f}",
                    f"{m['cpu_s']:.2f}",
                    f"{m['peak_rss_mb']:.0f}",
                    m["note"],
                ]
            )
    print(
        format_table(
            ["file", "measurement", "best s", "MB/s", "chunks/s", "CPU s", "peak RSS MB", "note"], rows, "llrrrrrl"
        )
    )
    print()
    for f in files:
        agree = "agrees" if f["rerun_num_chunks"] == f["chunks"] else f"says {f['rerun_num_chunks']}"
        print(
            f"{f['file']}: {f['chunks']:,} chunks / {f['rows']:,} rows / {f['entities']} entities by our decoder "
            f"(rerun rrd stats {agree}); timelines: {', '.join(f['timelines'])}"
        )


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["_worker"]:
        worker_main(argv[1:])
        return
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--data-dir",
        type=Path,
        default=ROOT / "benchmarks" / "data",
        help="where the generated recordings live (default: benchmarks/data, gitignored)",
    )
    parser.add_argument("--big-mb", type=float, default=220, help="minimum size of big.rrd in MB (default 220)")
    parser.add_argument(
        "--small-chunks", type=int, default=50_000, help="1-row chunks (log calls) in small.rrd (default 50000)"
    )
    parser.add_argument(
        "--small-entities", type=int, default=100, help="entities the small chunks are spread over (default 100)"
    )
    parser.add_argument("--repeat", type=int, default=3, help="runs per measurement, the best counts (default 3)")
    parser.add_argument("--rerun", help="the rerun executable (default: the native binary of rerun-sdk)")
    parser.add_argument("--json", action="store_true", help="print the results as JSON on stdout instead of tables")
    args = parser.parse_args(argv)
    if args.repeat < 1 or args.small_chunks < 1 or args.small_entities < 1 or args.big_mb <= 0:
        parser.error("--repeat, --small-chunks, --small-entities and --big-mb must be positive")

    load = os.getloadavg()[0]
    if load > 0.5 * (os.cpu_count() or 1):
        log(f"WARNING: load average {load:.2f}: other processes compete for the CPUs, timings will be noisy")
    data_dir: Path = args.data_dir.resolve()
    big = ensure_recording(data_dir, "big.rrd", {"kind": "big", "big_mb": args.big_mb}, ["gen-big", str(args.big_mb)])
    small = ensure_recording(
        data_dir,
        "small.rrd",
        {"kind": "small", "chunks": args.small_chunks, "entities": args.small_entities},
        ["gen-small", str(args.small_chunks), str(args.small_entities)],
    )
    if big["size_bytes"] < args.big_mb * MB:
        raise SystemExit(f"big.rrd is only {big['size_bytes'] / MB:.1f} MB")
    one_row = small["chunks"] - 1  # minus the static /__properties chunk
    if small["rows"] != small["chunks"] or one_row < args.small_chunks:
        raise SystemExit(
            f"small.rrd has {small['chunks']} chunks for {small['rows']} rows: the SDK batched "
            f"log calls together (expected {args.small_chunks} 1-row chunks)"
        )

    rerun_bin, found_via = find_rerun_binary(args.rerun)
    version = checked(run_process([rerun_bin, "--version"]), "rerun --version").stdout.split("(")[0].strip()
    report: dict[str, Any] = {
        "environment": {
            "python": platform.python_version(),
            "platform": platform.platform(),
            "cpus": os.cpu_count(),
            "load_average_1m_at_start": round(load, 2),
            "repeat": args.repeat,
            "rerun_binary": rerun_bin,
            "rerun_found_via": found_via,
            "rerun_version": version,
            "rerun_sdk": importlib.metadata.version("rerun-sdk"),
            "versions": {p: importlib.metadata.version(p) for p in ("protobuf", "pyarrow", "lz4", "numpy")},
        },
        "files": [
            bench_file("big.rrd", data_dir / "big.rrd", big, rerun_bin, args.repeat),
            bench_file("small.rrd", data_dir / "small.rrd", small, rerun_bin, args.repeat),
        ],
    }
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        print_report(report)


if __name__ == "__main__":
    main()
