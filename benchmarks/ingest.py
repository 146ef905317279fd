"""Benchmark: gRPC ingest of real Rerun recordings by R robots at once, ours next to `rerun --serve-grpc`.

    .venv/bin/python benchmarks/ingest.py [--robots 8] [--procs 2] [--repeat 2] [--workload big,small]
                                          [--servers ours,rerun] [--client aio|thread] [--memory-passes 3]
                                          [--workers N] [--catalog duckdb|postgres] [--server-cpus LIST]
                                          [--load-cpus LIST] [--big-mb 220] [--small-chunks 50000] [--stamped]
                                          [--rules FILE --servers ours,ours+rules] [--json]

1. The recordings are those of ``benchmarks/codec.py`` (``benchmarks/data/big.rrd``: 93 chunks of
   2.4-2.6 MB, point clouds and images; ``small.rrd``: 50,001 one-row chunks of scalars), generated
   with the real SDK by its helpers if missing (same parameters, same files).
2. For each workload and each repetition (the two servers take turns going first), each server is
   started fresh on free loopback ports:
   * ours: ``fleet serve`` with ``FLEET_DURABILITY=interval`` (group commit, the default) and a new
     empty ``FLEET_DATA_DIR`` (other ``FLEET_*`` variables of the environment are passed on);
     ready when ``/healthz`` answers;
   * the peer: the native ``rerun`` binary of rerun-sdk, ``rerun --serve-grpc --bind 127.0.0.1
     --port P --server-memory-limit L`` (no viewer: it keeps every message in memory for viewers that
     connect later). L (``--rerun-memory-limit``, default 16GiB) is chosen so that it never drops data:
     both servers keep everything they are sent (ours on disk, rerun in memory). With rerun's
     default of 1GiB it would start dropping its oldest messages part-way through the big workload.
3. ``--procs`` load processes (children of this script) replay the recording's messages as R robots
   (``--robots``), R/P each: robot k sends every SetStoreInfo / ArrowMsg / BlueprintActivationCommand
   of the file in order, with the recording id of RECORDING stores changed to ``<id>-r<k>`` (chunk
   payloads untouched; with ``--stamped``, each chunk re-encoded with the two times rerun-sdk stamps
   on every chunk it streams over gRPC, as a live robot's stream has them and a file lacks them),
   each robot on its own gRPC channel (own TCP connection), as one
   client-streaming ``MessageProxyService/WriteMessages`` call of pre-serialized
   ``WriteMessagesRequest``s: by default a grpc.aio task per robot (``--client thread``: the blocking
   API, a thread per robot, which costs the load processes about twice the CPU per message).
   Preparing the requests and connecting are not timed: each load process reports READY, and when all
   are, this script writes "go" to all of them at once.
4. Timed: from "go" until the last robot's call has returned (the server answers once it consumed the
   whole stream; ours has then written every chunk to its hot files). Measured meanwhile: the server's
   peak RSS (``VmHWM`` of /proc/PID/status: the peak over its whole life, start-up included; RSS also
   sampled every 20 ms to show its course), its CPU time, user + system (/proc/PID/stat), and the load
   processes' CPU. After the calls: "drain", how long the server's CPU stays busy (it might still be
   working on what it acknowledged), then the check that everything arrived: for ours, ``/metrics``
   counts robots x chunks new chunks and no duplicates; for rerun (first run of each workload), its
   history read back with ``ReadMessages`` as a viewer would: robots x chunks chunks of R recordings.
5. Memory: one more run of ours on big chunks where each robot sends the recording ``--memory-passes``
   times in a row (as new recordings each time): bounded memory means the same peak RSS for 3x the
   bytes. Printed in MB of RSS per GB ingested (bounded: < 50 both ways): its peak against the 1-pass
   runs' peaks, and the highest RSS of its last third against its first third.

6. Workers (``--workers N``): ours is started as ``fleet serve --workers N`` (N processes sharing the
   ports: the parent binds them, its worker children accept on them). More than one worker needs a
   shared catalog, so for N > 1 (or ``--catalog postgres``) each start of ours gets a new empty
   database on the local Postgres (``tests/postgres.py``'s ``temporary_database``, migrated with
   ``fleet db upgrade``, dropped after the run): ``FLEET_CATALOG_URL=postgresql+psycopg://postgres@
   127.0.0.1:5432/NAME``. The server's CPU is then summed over the parent and all its descendants
   (walked through /proc/PID/task/*/children; a breakdown per process is in ``--json``), its RSS too
   (peak RSS: the sum of each process's VmHWM, an upper bound). Postgres's own CPU is not counted
   (nor rerun's memory-only storage: it has no catalog). Reported per run besides chunks/s and MB/s:
   the server's CPU in µs per chunk (all its processes: what one chunk costs, whichever worker took
   it) and the load generator's share of the cores (its CPU seconds / wall / cores).

   To show 1..16 workers on a larger machine, give the load its own cores, so that it does not
   compete with the workers, and enough of them: on 1-row chunks the grpc.aio load processes spend
   about 60-90 µs of CPU per message against the server's 150-250, so a worker that saturates its core
   needs about half a core of load; use ``--procs`` ≈ N/2 + 1 on as many cores, and at least 4 robots
   per worker (the kernel hands each connection to one worker, so fewer streams leave workers idle).
   For example, on a 32-core machine::

       for n in 1 2 4 8 16; do .venv/bin/python benchmarks/ingest.py --workload small --servers ours \
           --memory-passes 0 --workers $n --catalog postgres --robots $((4 * n)) --procs $((n / 2 + 1)) \
           --server-cpus 0-$((n - 1)) --load-cpus 16-$((16 + n / 2)); done

   ``--server-cpus`` and ``--load-cpus`` pin the server (all its processes) and the load processes
   to those CPUs (sched_setaffinity; default: not pinned). A load share near 1.0 of its cores means
   the load, not the server, set the pace: give it more.

7. Rules (``--rules FILE``): server ``ours+rules`` is ours with the rules file applied before it starts
   (the live rules then evaluate, on a thread of the server, each chunk of an entity the file names;
   the others cost one dict lookup). ``--servers ours,ours+rules`` runs both in turn and prints the
   server's CPU per chunk of each and their ratio (target: within 10 %), of the best runs and of the
   medians, and the rules' worker's own CPU per chunk (``fleet_live_rules_cpu_seconds_total``: the
   server's figure varies by more than the rules cost from one run to the next on a shared machine,
   so use ``--repeat 5`` or more). For example, with
   ``benchmarks/rules-bench.toml`` (one entity of the small workload's 100, and four not in it)::

       .venv/bin/python benchmarks/ingest.py --workload small --servers ours,ours+rules \
           --rules benchmarks/rules-bench.toml --memory-passes 0 --no-read-back --repeat 3

MB = 10**6 bytes; bytes = sum of the inner messages sent (protobuf LogMsg contents, as in an RRD file).
``ours/rerun`` = our MB/s / rerun's MB/s on the same workload (best run of each); targets: >= 1.0x on
big chunks, >= 0.5x on 1-row chunks. Both servers and the load share the machine's CPUs: on a small
machine the load processes' CPU (shown) caps the faster server's figure.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.metadata
import json
import os
import platform
import resource
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import IO, Any

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as `python benchmarks/ingest.py` without the editable install
    sys.path.insert(0, str(ROOT))

from benchmarks.codec import (  # noqa: E402 - after the sys.path fix above
    MB,
    checked,
    ensure_recording,
    find_rerun_binary,
    format_table,
    log,
    run_process,
)

METHOD = "/rerun.sdk_comms.v1alpha1.MessageProxyService/WriteMessages"
MAX_SEND = 512 * 1024 * 1024
CALL_TIMEOUT_S = 900.0
RSS_POLL_S = 0.02
TARGETS = {"big": 1.0, "small": 0.5}
CLK_TCK = os.sysconf("SC_CLK_TCK")


# --- load processes (`ingest.py _load ...`) --------------------------------------------------------


SMALL_CHUNKS = 50_000
SMALL_ENTITIES = 100


def ensure_small(data_dir: Path, chunks: int = SMALL_CHUNKS, entities: int = SMALL_ENTITIES) -> dict[str, Any]:
    """`small.rrd` in `data_dir` (one-row chunks of scalars), generated unless present as asked."""
    return ensure_recording(
        data_dir,
        "small.rrd",
        {"kind": "small", "chunks": chunks, "entities": entities},
        ["gen-small", str(chunks), str(entities)],
    )


def _renamed(store_id: Any, suffix: str, base: str) -> None:
    """Give a RECORDING store id (kind 1) the robot's recording id; blueprint ids are left alone."""
    if store_id.kind == 1:
        store_id.recording_id = base + suffix


def stamped_chunk(msg: Any) -> bytes:
    """The ArrowMsg `msg` (an ArrowMessage) re-encoded with its chunk's schema stamped as rerun-sdk
    stamps each chunk it streams over gRPC: when it was encoded and when it was sent
    ("SECONDS.NANOSECONDS"). A recording saved to a file lacks them; the depot must key its
    layouts without them."""
    from services.rrd.chunk import read_chunk, with_batch

    def stamp(ns: int) -> bytes:
        return f"{ns // 10**9}.{ns % 10**9:09d}".encode()

    batch = read_chunk(msg)
    encoded = time.time_ns()
    stamps = {  # sent a few tens of microseconds after it was encoded, as the SDK's gRPC sink does
        b"rerun:timestamp_sdk_ipc_encoded": stamp(encoded),
        b"rerun:timestamp_sdk_grpc_sink": stamp(encoded + 41_000),
    }
    batch = batch.replace_schema_metadata({**(batch.schema.metadata or {}), **stamps})
    return bytes(with_batch(msg, batch).raw)


def prepare_requests(
    path: str, robots: list[int], passes: int = 1, stamped: bool = False
) -> tuple[dict[int, list[bytes]], dict[int, dict[str, int]]]:
    """For each robot: every message of the recording as a serialized WriteMessagesRequest with the
    robot's own recording id, and what that amounts to (messages, chunks, inner message bytes).
    With `passes` > 1 the robot sends the recording that many times in a row, each time as a new
    recording (`<id>-r<k>`, then `<id>-r<k>-p1`, ...): more bytes through the same streams. With
    `stamped`, chunks carry the stamps of a live SDK stream (`stamped_chunk`)."""
    from services.rrd.decoder import iter_events
    from services.rrd.messages import ArrowMessage, BlueprintActivationMessage, StoreInfoMessage
    from services.rrd.pb import log_msg_pb2, sdk_comms_pb2

    sends = [(k, p) for k in robots for p in range(passes)]
    lists: dict[tuple[int, int], list[bytes]] = {s: [] for s in sends}
    counts = {k: {"messages": 0, "chunks": 0, "bytes": 0} for k in robots}
    suffixes = {(k, p): f"-r{k}" + (f"-p{p}" if p else "") for k, p in sends}
    for event in iter_events(path):
        inner: Any
        if isinstance(event, StoreInfoMessage):
            inner, field_name = log_msg_pb2.SetStoreInfo.FromString(bytes(event.raw)), "set_store_info"
            store_id = inner.info.store_id
        elif isinstance(event, ArrowMessage):
            raw = stamped_chunk(event) if stamped else bytes(event.raw)
            inner, field_name = log_msg_pb2.ArrowMsg.FromString(raw), "arrow_msg"
            store_id = inner.store_id
        elif isinstance(event, BlueprintActivationMessage):
            inner = log_msg_pb2.BlueprintActivationCommand.FromString(bytes(event.raw))
            field_name, store_id = "blueprint_activation_command", inner.blueprint_id
        else:
            continue  # stream headers, End, footers: not sent over gRPC
        base = store_id.recording_id
        for send in sends:
            _renamed(store_id, suffixes[send], base)
            request = sdk_comms_pb2.WriteMessagesRequest(log_msg=log_msg_pb2.LogMsg(**{field_name: inner}))
            lists[send].append(request.SerializeToString())
            c = counts[send[0]]
            c["messages"] += 1
            c["bytes"] += inner.ByteSize()
            c["chunks"] += field_name == "arrow_msg"
        del inner
    requests = {k: [r for p in range(passes) for r in lists[k, p]] for k in robots}
    return requests, counts


def load_main(args: list[str]) -> None:
    """`_load CLIENT PASSES PATH HOST:PORT K1,K2,... [stamped]`: prepare, print READY, wait for a line on
    stdin, send, print DONE. CLIENT is `aio` (grpc.aio, one task per robot on one event loop) or `thread`
    (the blocking API, one thread per robot); `stamped`: chunks stamped as a live SDK stream's."""
    client, passes, path, target = args[0], int(args[1]), args[2], args[3]
    robots = [int(k) for k in args[4].split(",")]
    t0 = time.perf_counter()
    requests, counts = prepare_requests(path, robots, passes, stamped=args[5:6] == ["stamped"])
    prepare_s = time.perf_counter() - t0
    options = [
        ("grpc.max_send_message_length", MAX_SEND),
        ("grpc.max_receive_message_length", MAX_SEND),
        ("grpc.use_local_subchannel_pool", 1),  # each robot its own TCP connection, as separate machines
    ]
    ready = {"prepare_s": prepare_s, "pid": os.getpid()}
    if client == "aio":
        import asyncio

        results = asyncio.run(_send_aio(target, options, requests, ready))
    else:
        results = _send_threads(target, options, requests, ready)
    usage = resource.getrusage(resource.RUSAGE_SELF)
    for k, result in results.items():
        result.update(counts[k])
    print(
        "DONE "
        + json.dumps(
            {
                "robots": results,
                "cpu_s": usage.ru_utime + usage.ru_stime - ready["cpu0"],
                "peak_rss_mb": usage.ru_maxrss * 1024 / MB,
            }
        ),
        flush=True,
    )


def _cpu_now() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def _barrier(ready: dict[str, Any]) -> None:
    """Tell the orchestrator we are ready, wait for its go."""
    ready["cpu0"] = _cpu_now()
    print("READY " + json.dumps(ready), flush=True)
    sys.stdin.readline()


async def _send_aio(
    target: str, options: list[tuple[str, int]], requests: dict[int, list[bytes]], ready: dict[str, Any]
) -> dict[int, dict[str, Any]]:
    import asyncio

    import grpc

    from services.rrd.pb import sdk_comms_pb2

    channels = {k: grpc.aio.insecure_channel(target, options=options) for k in requests}
    for channel in channels.values():
        await asyncio.wait_for(channel.channel_ready(), 60)
    results: dict[int, dict[str, Any]] = {}

    async def robot(k: int) -> None:
        call = channels[k].stream_unary(
            METHOD, request_serializer=None, response_deserializer=sdk_comms_pb2.WriteMessagesResponse.FromString
        )
        start = time.time()
        error = None
        try:
            stream = call(timeout=CALL_TIMEOUT_S)
            for request in requests[k]:
                await stream.write(request)
            await stream.done_writing()
            await stream
        except grpc.RpcError as exc:
            error = f"{exc.code().name}: {exc.details()}"
        results[k] = {"start": start, "end": time.time(), "error": error}

    await asyncio.get_running_loop().run_in_executor(None, _barrier, ready)
    await asyncio.gather(*(robot(k) for k in requests))
    for channel in channels.values():
        await channel.close()
    return results


def _send_threads(
    target: str, options: list[tuple[str, int]], requests: dict[int, list[bytes]], ready: dict[str, Any]
) -> dict[int, dict[str, Any]]:
    import grpc

    from services.rrd.pb import sdk_comms_pb2

    channels = {k: grpc.insecure_channel(target, options=options) for k in requests}
    for channel in channels.values():
        grpc.channel_ready_future(channel).result(timeout=60)
    go = threading.Event()
    results: dict[int, dict[str, Any]] = {}

    def robot(k: int) -> None:
        call = channels[k].stream_unary(
            METHOD, request_serializer=None, response_deserializer=sdk_comms_pb2.WriteMessagesResponse.FromString
        )
        go.wait()
        start = time.time()
        error = None
        try:
            call(iter(requests[k]), timeout=CALL_TIMEOUT_S)
        except grpc.RpcError as exc:
            error = f"{exc.code().name}: {exc.details()}"  # the call object is also the error
        results[k] = {"start": start, "end": time.time(), "error": error}

    threads = [threading.Thread(target=robot, args=(k,), name=f"robot-{k}") for k in requests]
    for thread in threads:
        thread.start()
    _barrier(ready)
    go.set()
    for thread in threads:
        thread.join()
    for channel in channels.values():
        channel.close()
    return results


# --- servers --------------------------------------------------------------------------------------


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def proc_status_kb(pid: int, key: str) -> int:
    with open(f"/proc/{pid}/status") as fh:
        for line in fh:
            if line.startswith(key + ":"):
                return int(line.split()[1])
    raise RuntimeError(f"no {key} in /proc/{pid}/status")


def proc_times(pid: int) -> tuple[float, float]:
    """(user, system) CPU seconds of a process, all its threads."""
    with open(f"/proc/{pid}/stat") as fh:
        fields = fh.read().rsplit(")", 1)[1].split()
    return int(fields[11]) / CLK_TCK, int(fields[12]) / CLK_TCK  # utime, stime (fields 14 and 15 of stat)


def proc_cpu_s(pid: int) -> float:
    return sum(proc_times(pid))


def proc_name(pid: int) -> str:
    """What the process is, from its command line: the server itself, a worker, a helper."""
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as fh:
            argv = fh.read().decode(errors="replace").split("\0")
    except OSError:
        return "?"
    line = " ".join(argv)
    if "resource_tracker" in line:
        return "multiprocessing resource tracker"
    if "multiprocessing" in line:
        return "worker"
    return " ".join(Path(argv[0]).name.split() + argv[1:3]).strip()


def proc_tree(pid: int) -> list[int]:
    """`pid` and all its descendants (each thread's /proc/PID/task/TID/children)."""
    found, todo = [], [pid]
    while todo:
        current = todo.pop()
        found.append(current)
        try:
            for task in os.listdir(f"/proc/{current}/task"):
                with open(f"/proc/{current}/task/{task}/children") as fh:
                    todo += [int(child) for child in fh.read().split()]
        except OSError:
            continue  # gone meanwhile
    return found


def tree_times(pid: int) -> dict[int, tuple[float, float]]:
    """(user, system) CPU seconds of `pid` and of each of its descendants, by process."""
    times = {}
    for member in proc_tree(pid):
        with contextlib.suppress(OSError, IndexError, ValueError):
            times[member] = proc_times(member)
    return times


def tree_cpu_s(pid: int) -> float:
    return sum(u + s for u, s in tree_times(pid).values())


def tree_status_kb(pid: int, key: str) -> int:
    """The sum of a /proc/PID/status value (VmRSS, VmHWM) over `pid` and its descendants."""
    total = 0
    for member in proc_tree(pid):
        with contextlib.suppress(OSError, RuntimeError):
            total += proc_status_kb(member, key)
    return total


def cpu_list(text: str | None) -> set[int] | None:
    """`0-3,8` -> {0, 1, 2, 3, 8}."""
    if not text:
        return None
    cpus: set[int] = set()
    for part in text.split(","):
        low, _, high = part.partition("-")
        cpus.update(range(int(low), int(high or low) + 1))
    return cpus


def pinned(cpus: set[int] | None) -> Any:
    """A `preexec_fn` that pins the child (and what it starts) to `cpus`; None when not pinned."""
    if cpus is None:
        return None
    return lambda: os.sched_setaffinity(0, cpus)


def http_get(port: int, path: str, timeout: float = 10) -> tuple[int, str]:
    import httpx

    response = httpx.get(f"http://127.0.0.1:{port}{path}", timeout=timeout)
    return response.status_code, response.text


class Server:
    """A server process under test: started, polled for RSS, stopped."""

    name = ""

    def __init__(self, workdir: Path, cpus: set[int] | None = None) -> None:
        self.workdir = workdir
        self.cpus = cpus  # pinned to these CPUs (None: not pinned)
        self.grpc_port = free_port()
        self.proc: subprocess.Popen[bytes] | None = None
        self.log_path = workdir / f"{self.name}.log"
        self.samples: list[tuple[float, int]] = []  # (time.time(), VmRSS KiB)
        self._stop_polling = threading.Event()
        self._poller: threading.Thread | None = None

    @property
    def pid(self) -> int:
        assert self.proc is not None
        return self.proc.pid

    def argv_env(self) -> tuple[list[str], dict[str, str]]:
        raise NotImplementedError

    def ready(self) -> bool:
        raise NotImplementedError

    def start(self, timeout: float = 60) -> None:
        argv, env = self.argv_env()
        with open(self.log_path, "wb") as out:
            self.proc = subprocess.Popen(
                argv,
                env=env,
                stdin=subprocess.DEVNULL,
                stdout=out,
                stderr=subprocess.STDOUT,
                cwd=self.workdir,
                preexec_fn=pinned(self.cpus),
            )
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise SystemExit(f"{self.name} exited ({self.proc.returncode}) at start:\n{self.log_tail()}")
            with contextlib.suppress(OSError):
                if self.ready():
                    return
            time.sleep(0.05)  # polling for readiness, bounded by the deadline
        raise SystemExit(f"{self.name} did not become ready within {timeout} s:\n{self.log_tail()}")

    def log_tail(self, lines: int = 30) -> str:
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-lines:])
        except OSError:
            return ""

    def rss_mb(self) -> float:
        return tree_status_kb(self.pid, "VmRSS") * 1024 / MB

    def peak_rss_mb(self) -> float:
        """VmHWM: the process's peak; with worker processes the sum of theirs (an upper bound)."""
        return tree_status_kb(self.pid, "VmHWM") * 1024 / MB

    def start_polling(self) -> None:
        def poll() -> None:
            while not self._stop_polling.is_set():
                with contextlib.suppress(OSError, RuntimeError):
                    self.samples.append((time.time(), tree_status_kb(self.pid, "VmRSS")))
                self._stop_polling.wait(RSS_POLL_S)

        self._poller = threading.Thread(target=poll, name=f"rss-{self.name}", daemon=True)
        self._poller.start()

    def stop_polling(self) -> None:
        self._stop_polling.set()
        if self._poller is not None:
            self._poller.join()

    def stop(self) -> None:
        self.stop_polling()
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


class FleetServer(Server):
    name = "ours"

    def __init__(
        self,
        workdir: Path,
        cpus: set[int] | None = None,
        workers: int | None = None,
        catalog: str = "duckdb",
        rules: Path | None = None,
    ) -> None:
        super().__init__(workdir, cpus)
        self.rules = rules  # a rules file applied before the start (`ours+rules`)
        if rules is not None:
            self.name = "ours+rules"
        self.http_port = free_port()
        self.data_dir = workdir / "fleet-data"
        self.workers = workers  # `fleet serve --workers N` (None: the option left out)
        self.catalog = catalog  # duckdb (embedded) or postgres (a new database for this server)
        self.catalog_url: str | None = None
        self._database = contextlib.ExitStack()

    def env(self) -> dict[str, str]:
        env = {
            **os.environ,
            "FLEET_DATA_DIR": str(self.data_dir),
            "FLEET_AUTH": "off",  # on loopback, like the peer (no auth); a token is checked once per stream
            "FLEET_DURABILITY": "interval",
            "FLEET_HTTP_ADDR": f"127.0.0.1:{self.http_port}",
            "FLEET_GRPC_ADDR": f"127.0.0.1:{self.grpc_port}",
            "FLEET_PEER_ADDR": "127.0.0.1:0",  # workers' peer ports: any free one
        }
        if self.catalog_url is not None:
            env["FLEET_CATALOG_URL"] = self.catalog_url
        return env

    def fleet(self, *args: str) -> list[str]:
        fleet = Path(sys.executable).with_name("fleet")
        if fleet.is_file():
            return [str(fleet), *args]
        code = f"import sys; sys.path.insert(0, {str(ROOT)!r}); from services.cli.main import main; main()"
        return [sys.executable, "-c", code, *args]

    def argv_env(self) -> tuple[list[str], dict[str, str]]:
        workers = [] if self.workers is None else ["--workers", str(self.workers)]
        return self.fleet("serve", *workers), self.env()

    def start(self, timeout: float = 120) -> None:
        if self.catalog == "postgres":
            from tests.postgres import temporary_database

            self.catalog_url = self._database.enter_context(temporary_database("ingest_bench"))
            checked(run_process(self.fleet("db", "upgrade"), env=self.env()), "fleet db upgrade")
        if self.rules is not None:
            self.apply_rules(self.rules)
        super().start(timeout)

    def apply_rules(self, rules: Path) -> None:
        """The rules file as the running rules of the catalog the server is about to open (written by
        a child process: this script's own folder shadows the `catalog` package)."""
        self.data_dir.mkdir(parents=True, exist_ok=True)
        if self.catalog_url is None:
            checked(run_process(self.fleet("db", "upgrade"), env=self.env()), "fleet db upgrade")
        url = self.catalog_url or f"duckdb:///{self.data_dir.resolve() / 'catalog.duckdb'}"
        code = (
            f"import sys, datetime as dt; sys.path.insert(0, {str(ROOT)!r})\n"
            "from sqlalchemy.orm import sessionmaker\n"
            "from catalog import corpus\n"
            "from catalog.db import create_engine, session_scope\n"
            f"engine = create_engine({url!r})\n"
            "with session_scope(sessionmaker(engine), write=True) as session:\n"
            f"    corpus.add_rules_version(session, {rules.read_text()!r}, 'benchmark', dt.datetime.now(dt.UTC))\n"
            "engine.dispose()\n"
        )
        checked(run_process([sys.executable, "-c", code]), "apply the rules")

    def stop(self) -> None:
        try:
            super().stop()
        finally:
            self._database.close()  # the run's database is dropped

    def hot_files(self) -> list[Path]:
        """The run files of its hot tier (one per worker with --workers)."""
        return [*self.data_dir.glob("hot/*/run.rrd"), *self.data_dir.glob("workers/*/hot/*/run.rrd")]

    def ready(self) -> bool:
        import httpx

        try:
            return http_get(self.http_port, "/healthz", timeout=1)[0] == 200
        except httpx.TransportError:
            return False

    def metrics(self) -> dict[str, float]:
        status, text = http_get(self.http_port, "/metrics")
        if status != 200:
            raise SystemExit(f"GET /metrics: HTTP {status}")
        values = {}
        for line in text.splitlines():
            if line.startswith("fleet_") and not line.startswith("fleet_build_info"):
                name, value = line.split()
                values[name] = float(value)
        return values


class RerunServer(Server):
    name = "rerun"

    def __init__(self, workdir: Path, binary: str, memory_limit: str, cpus: set[int] | None = None) -> None:
        super().__init__(workdir, cpus)
        self.binary = binary
        self.memory_limit = memory_limit

    def argv_env(self) -> tuple[list[str], dict[str, str]]:
        argv = [
            self.binary,
            "--serve-grpc",
            "--bind",
            "127.0.0.1",
            "--port",
            str(self.grpc_port),
            "--server-memory-limit",
            self.memory_limit,
        ]
        return argv, dict(os.environ)

    def ready(self) -> bool:
        with socket.create_connection(("127.0.0.1", self.grpc_port), timeout=1):
            return True


# --- one run ---------------------------------------------------------------------------------------


@dataclass
class Run:
    server: str
    workload: str
    wall_s: float
    bytes: int
    chunks: int
    messages: int
    server_cpu_s: float
    server_sys_s: float  # the kernel's part of server_cpu_s: sockets, page cache, fsync
    load_cpu_s: float
    peak_rss_mb: float  # VmHWM: the server's peak over its life
    rss_start_mb: float  # just before "go"
    rss_end_mb: float  # after the drain
    rss_course_mb: list[float]  # sampled RSS at 0, 25, 50, 75, 100 % of the timed part
    rss_thirds_mb: list[float]  # highest sampled RSS in each third of the timed part
    drain_s: float
    drain_cpu_s: float
    prepare_s: float
    robot_walls_s: list[float]
    passes: int = 1  # times each robot sent the recording (as new recordings)
    check: str = ""
    load_cores: int = 1  # the cores the load processes could run on
    server_procs: dict[str, float] = field(default_factory=dict)  # CPU seconds by process (pid: its name)
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def mb_s(self) -> float:
        return self.bytes / MB / self.wall_s

    @property
    def chunks_s(self) -> float:
        return self.chunks / self.wall_s

    @property
    def cpu_us_per_chunk(self) -> float:
        """Server CPU (all its processes) per chunk: what a chunk costs, whichever worker took it."""
        return self.server_cpu_s / self.chunks * 1e6

    @property
    def load_share(self) -> float:
        """The load processes' CPU over the wall time, as a share of the cores they could use."""
        return self.load_cpu_s / self.wall_s / self.load_cores


def read_line(proc: subprocess.Popen[str], prefix: str, what: str, log_path: Path) -> dict[str, Any]:
    """The JSON of the next `PREFIX {...}` line a load process prints."""
    assert proc.stdout is not None
    line = proc.stdout.readline()
    if not line.startswith(prefix + " "):
        proc.wait()
        tail = "\n".join(log_path.read_text(errors="replace").splitlines()[-20:])
        raise SystemExit(f"{what}: expected {prefix}, got {line!r} (exit {proc.returncode})\n{tail}")
    result: dict[str, Any] = json.loads(line[len(prefix) + 1 :])
    return result


def wait_idle(pid: int, quiet_s: float = 0.5, threshold_s: float = 0.05, limit_s: float = 60) -> tuple[float, float]:
    """Wait until the process (and its descendants) use less than `threshold_s` CPU in `quiet_s`;
    returns (seconds until then, excluding the quiet window that proved it, CPU seconds used meanwhile)."""
    start, cpu0 = time.perf_counter(), tree_cpu_s(pid)
    busy_until, last = start, cpu0
    while time.perf_counter() - start < limit_s:
        time.sleep(quiet_s)
        now = tree_cpu_s(pid)
        if now - last < threshold_s:
            break
        busy_until, last = time.perf_counter(), now
    return busy_until - start, last - cpu0


def thirds(samples: list[tuple[float, int]], t0: float, t1: float) -> list[float]:
    """The highest RSS (MB) sampled in each third of [t0, t1]."""
    out = []
    for i in range(3):
        lo, hi = t0 + (t1 - t0) * i / 3, t0 + (t1 - t0) * (i + 1) / 3
        inside = [kb for t, kb in samples if lo <= t <= hi]
        out.append(max(inside) * 1024 / MB if inside else 0.0)
    return out


def course(samples: list[tuple[float, int]], t0: float, t1: float) -> list[float]:
    """RSS (MB) at 0, 25, 50, 75 and 100 % of [t0, t1]: the sample nearest each point."""
    if not samples:
        return []
    points = [t0 + (t1 - t0) * q / 4 for q in range(5)]
    return [min(samples, key=lambda s: abs(s[0] - p))[1] * 1024 / MB for p in points]


def run_once(
    server: Server,
    workload: str,
    path: Path,
    robots: int,
    procs: int,
    expect_chunks: int,
    client: str,
    passes: int = 1,
    check_rerun: bool = False,
    load_cpus: set[int] | None = None,
    stamped: bool = False,
) -> Run:
    """One timed run: `server` started, the load processes prepared, "go", all calls answered."""
    groups = [list(range(robots))[i::procs] for i in range(procs)]
    groups = [g for g in groups if g]
    server.start()
    loaders: list[subprocess.Popen[str]] = []
    logs: list[IO[bytes]] = []
    try:
        target = f"127.0.0.1:{server.grpc_port}"
        for i, group in enumerate(groups):
            err = open(server.workdir / f"load-{i}.log", "wb")  # noqa: SIM115 - closed below
            logs.append(err)
            argv = [
                sys.executable,
                str(Path(__file__).resolve()),
                "_load",
                client,
                str(passes),
                str(path),
                target,
                ",".join(map(str, group)),
                *(["stamped"] if stamped else []),
            ]
            loaders.append(
                subprocess.Popen(
                    argv,
                    stdin=subprocess.PIPE,
                    stdout=subprocess.PIPE,
                    stderr=err,
                    text=True,
                    preexec_fn=pinned(load_cpus),
                )
            )
        load_logs = [server.workdir / f"load-{i}.log" for i in range(len(loaders))]
        ready = [read_line(p, "READY", f"load process {i}", load_logs[i]) for i, p in enumerate(loaders)]
        time.sleep(0.5)  # let the preparation's page cache and allocator churn settle
        rss_start = server.rss_mb()
        times0 = tree_times(server.pid)
        server.start_polling()
        t_go = time.time()
        for p in loaders:
            assert p.stdin is not None
            p.stdin.write("go\n")
            p.stdin.flush()
        done = [read_line(p, "DONE", f"load process {i}", load_logs[i]) for i, p in enumerate(loaders)]
        t_end = max(r["end"] for d in done for r in d["robots"].values())
        times1 = tree_times(server.pid)
        drain_s, drain_cpu = wait_idle(server.pid)
        server.stop_polling()
        for p in loaders:
            p.wait(timeout=60)
        results = [r for d in done for r in d["robots"].values()]
        errors = [f"robot: {r['error']}" for r in results if r["error"]]
        if errors:
            tails = "\n".join(server.log_tail().splitlines()[-10:])
            raise SystemExit(f"{server.name} {workload}: {len(errors)} calls failed: {errors[:3]}\n{tails}")
        run = Run(
            server=server.name,
            workload=workload,
            wall_s=t_end - t_go,
            bytes=sum(r["bytes"] for r in results),
            chunks=sum(r["chunks"] for r in results),
            messages=sum(r["messages"] for r in results),
            server_cpu_s=sum(u + s - sum(times0.get(p, (0.0, 0.0))) for p, (u, s) in times1.items()),
            server_sys_s=sum(s - times0.get(p, (0.0, 0.0))[1] for p, (_, s) in times1.items()),
            load_cpu_s=sum(d["cpu_s"] for d in done),
            peak_rss_mb=server.peak_rss_mb(),
            rss_start_mb=rss_start,
            rss_end_mb=server.rss_mb(),
            rss_course_mb=course(server.samples, t_go, t_end),
            rss_thirds_mb=thirds(server.samples, t_go, t_end),
            drain_s=drain_s,
            drain_cpu_s=drain_cpu,
            prepare_s=max(r["prepare_s"] for r in ready),
            robot_walls_s=sorted(round(r["end"] - t_go, 3) for r in results),
            passes=passes,
            load_cores=len(load_cpus) if load_cpus else os.cpu_count() or 1,
            server_procs={
                f"{p} {proc_name(p)}": round(u + s - sum(times0.get(p, (0.0, 0.0))), 2) for p, (u, s) in times1.items()
            },
        )
        if isinstance(server, FleetServer):
            run.check, run.extra = check_ours(server, run, robots * passes * expect_chunks)
        elif check_rerun:
            run.check, run.extra = check_peer(server, robots * passes * expect_chunks, robots * passes)
        else:
            run.check = "not read back (only the first run of rerun is); its calls all succeeded"
        return run
    finally:
        for p in loaders:
            if p.poll() is None:
                p.kill()
                p.wait()
        for fh in logs:
            fh.close()
        server.stop()


def check_peer(server: Server, expected: int, recordings: int, idle_s: float = 5) -> tuple[str, dict[str, Any]]:
    """Rerun has no counters: read its history back as a viewer would (`ReadMessages` replays every
    message it holds, then stays open for new ones) and count the chunks and recordings. Done after
    the peak RSS was read (serving a reader costs memory)."""
    import grpc

    from services.rrd import protowire
    from services.rrd.pb import log_msg_pb2, sdk_comms_pb2

    channel = grpc.insecure_channel(
        f"127.0.0.1:{server.grpc_port}", options=[("grpc.max_receive_message_length", MAX_SEND)]
    )
    read = channel.unary_stream(
        "/rerun.sdk_comms.v1alpha1.MessageProxyService/ReadMessages",
        request_serializer=sdk_comms_pb2.ReadMessagesRequest.SerializeToString,
        response_deserializer=None,
    )
    stream = read(sdk_comms_pb2.ReadMessagesRequest(), timeout=600)
    chunks = 0
    ids: set[str] = set()
    last = [time.monotonic()]
    done = threading.Event()

    def watchdog() -> None:  # the stream never ends by itself: stop once it stays quiet
        while not done.wait(0.25):
            if time.monotonic() - last[0] > idle_s:
                stream.cancel()
                return

    threading.Thread(target=watchdog, name="read-back-watchdog", daemon=True).start()
    t0 = time.perf_counter()
    try:
        for response in stream:
            last[0] = time.monotonic()
            found = protowire.last_field(response, 1)  # ReadMessagesResponse.log_msg
            if found is None:
                continue
            log_msg = memoryview(response)[found[1] : found[2]]
            for number, _, start, end in protowire.fields(log_msg):
                if number == 2:  # arrow_msg
                    chunks += 1
                elif number == 1:  # set_store_info
                    info = log_msg_pb2.SetStoreInfo.FromString(bytes(log_msg[start:end])).info
                    if info.store_id.kind == 1:
                        ids.add(info.store_id.recording_id)
            if chunks >= expected and len(ids) >= recordings:
                break
    except grpc.RpcError as exc:
        if exc.code() != grpc.StatusCode.CANCELLED:
            raise
    finally:
        done.set()
        stream.cancel()
        channel.close()
    extra = {
        "read_back_chunks": chunks,
        "read_back_recordings": len(ids),
        "read_back_s": round(time.perf_counter() - t0, 2),
    }
    if chunks != expected or len(ids) != recordings:
        return (
            f"MISMATCH: read back {chunks:,} chunks of {len(ids)} recordings, expected {expected:,} of {recordings}"
        ), extra
    return f"ok: {chunks:,} chunks of {len(ids)} recordings read back with ReadMessages", extra


def check_ours(server: FleetServer, run: Run, expected: int) -> tuple[str, dict[str, Any]]:
    """Every chunk new, once, on disk: the counters of /metrics (updated when a stream ends)."""
    deadline = time.monotonic() + 30
    metrics = server.metrics()
    while metrics.get("fleet_live_streams", 0) > 0 and time.monotonic() < deadline:
        time.sleep(0.1)  # polling for the streams to be closed, bounded by the deadline
        metrics = server.metrics()
    new = int(metrics.get("fleet_ingest_chunks_new_total", -1))
    dup = int(metrics.get("fleet_ingest_chunks_duplicate_total", -1))
    files = server.hot_files()
    hot_bytes = sum(p.stat().st_size for p in files)
    extra = {"metrics": metrics, "hot_runs": len(files), "hot_bytes": hot_bytes}
    if new != expected or dup != 0:
        return f"MISMATCH: {new} new + {dup} duplicate chunks, expected {expected} new", extra
    return f"ok: {new:,} new chunks in /metrics, {extra['hot_runs']} hot runs, {hot_bytes / MB:,.1f} MB on disk", extra


# --- report ----------------------------------------------------------------------------------------


def best(runs: list[Run], server: str, workload: str) -> Run | None:
    mine = [r for r in runs if r.server == server and r.workload == workload and r.passes == 1]
    return min(mine, key=lambda r: r.wall_s) if mine else None


def summarize(runs: list[Run], workloads: list[str]) -> list[dict[str, Any]]:
    """Per workload: the best run of each server, the ratio (when both ran) and the memory figures."""
    out = []
    for w in workloads:
        entry: dict[str, Any] = {"workload": w, "target": TARGETS[w], "ratio_mb_s": None, "met": None}
        for name in ("ours", "rerun"):
            top = best(runs, name, w)
            if top is not None:
                entry[name] = {
                    "mb_s": round(top.mb_s, 1),
                    "chunks_s": round(top.chunks_s, 1),
                    "wall_s": round(top.wall_s, 3),
                    "peak_rss_mb": round(
                        max(r.peak_rss_mb for r in runs if r.server == name and r.workload == w and r.passes == 1), 1
                    ),
                }
        if "ours" in entry and "rerun" in entry:
            ratio = entry["ours"]["mb_s"] / entry["rerun"]["mb_s"]
            entry["ratio_mb_s"], entry["met"] = round(ratio, 3), ratio >= TARGETS[w]
        out.append(entry)
    return out


def rules_cost(runs: list[Run], workloads: list[str]) -> list[dict[str, Any]]:
    """Per workload run with and without rules: the server's CPU per chunk of each (best and median
    run) and their ratios, and what the rules' worker itself spent per chunk (its own CPU clock, read
    from /metrics: free of the run-to-run noise of the whole server's figure)."""
    out = []
    for w in workloads:
        costs: dict[str, list[float]] = {}
        for name in ("ours", "ours+rules"):
            mine = [r.cpu_us_per_chunk for r in runs if r.server == name and r.workload == w and r.passes == 1]
            if mine:
                costs[name] = mine
        if len(costs) != 2:
            continue
        ratio = min(costs["ours+rules"]) / min(costs["ours"])
        median_ratio = statistics.median(costs["ours+rules"]) / statistics.median(costs["ours"])
        worker = [
            r.extra["metrics"].get("fleet_live_rules_cpu_seconds_total", 0.0) * 1e6 / r.chunks
            for r in runs
            if r.server == "ours+rules" and r.workload == w and r.passes == 1 and "metrics" in r.extra
        ]
        worker_us = statistics.median(worker) if worker else None
        out.append(
            {
                "workload": w,
                "ours_us_per_chunk": round(min(costs["ours"]), 1),
                "rules_us_per_chunk": round(min(costs["ours+rules"]), 1),
                "ratio": round(ratio, 3),
                "median_ours_us_per_chunk": round(statistics.median(costs["ours"]), 1),
                "median_rules_us_per_chunk": round(statistics.median(costs["ours+rules"]), 1),
                "median_ratio": round(median_ratio, 3),
                "worker_us_per_chunk": None if worker_us is None else round(worker_us, 2),
                "worker_share": None if worker_us is None else round(worker_us / min(costs["ours"]), 3),
                "met": ratio <= 1.10,
            }
        )
    return out


def memory_verdict(runs: list[Run]) -> dict[str, Any] | None:
    """Does our memory grow with the bytes ingested? Two measures, each in MB of RSS per GB ingested
    (about 0 if memory is bounded, about 1000 if what is ingested stays in memory):
    * across runs: the peak of the run where each robot sends the recording N times against the
      highest peak of the 1-pass runs, per extra GB;
    * within that run: the highest RSS of its last third against its first third, per GB ingested
      in between.
    Bounded means both stay under 50 MB per GB."""
    ours = [r for r in runs if r.server == "ours" and r.workload == "big"]
    one = [r for r in ours if r.passes == 1]
    more = [r for r in ours if r.passes > 1]
    if not more or not one or len(more[0].rss_thirds_mb) != 3:
        return None
    run, base = more[0], max(one, key=lambda r: r.peak_rss_mb)
    within = (run.rss_thirds_mb[2] - run.rss_thirds_mb[0]) / (run.bytes * 2 / 3 / 1e9)
    across = (run.peak_rss_mb - base.peak_rss_mb) / ((run.bytes - base.bytes) / 1e9)
    return {
        "passes": run.passes,
        "gb": round(run.bytes / 1e9, 3),
        "peak_mb": round(run.peak_rss_mb, 1),
        "thirds_mb": [round(v, 1) for v in run.rss_thirds_mb],
        "rss_after_mb": round(run.rss_end_mb, 1),
        "gb_1_pass": round(base.bytes / 1e9, 3),
        "peaks_1_pass_mb": [round(r.peak_rss_mb, 1) for r in one],
        "mb_per_gb_across": round(across, 1),
        "mb_per_gb_within": round(within, 1),
        "bounded": across < 50 and within < 50,
    }


def compiled_status() -> str:
    """How many of the ingest path's modules the `fleet` beside this interpreter loads compiled (an
    install made with FLEET_COMPILE=1: all of them)."""
    python = Path(sys.executable)
    code = "from services.compiled import compiled_summary; print(compiled_summary())"
    out = subprocess.run([str(python), "-c", code], capture_output=True, text=True, cwd=python.parent)
    return out.stdout.strip() if out.returncode == 0 else "unknown"


def print_report(report: dict[str, Any]) -> None:
    env = report["environment"]
    print(
        f"rerun: {env['rerun_binary']} ({env['rerun_version']}), --serve-grpc "
        f"--server-memory-limit {env['rerun_memory_limit']} (memory only, drops nothing here)"
    )
    workers = "" if env["workers"] is None else f" --workers {env['workers']}"
    print(
        f"ours: fleet serve{workers}, {env['catalog']} catalog, FLEET_DURABILITY=interval (group commit), "
        f"hot tier in {env['tmp']}; ingest path: {env['compiled']}"
    )
    if env["server_cpus"] or env["load_cpus"]:
        print(f"pinned: servers to CPUs {env['server_cpus'] or 'any'}, load processes to {env['load_cpus'] or 'any'}")
    per_robot = "task on a grpc.aio event loop" if env["client"] == "aio" else "thread (blocking gRPC API)"
    print(
        f"load: {env['robots']} robots (distinct recording ids) from {env['procs']} processes, one gRPC channel "
        f"(TCP connection), one WriteMessages call and one {per_robot} per robot; best of {env['repeat']}"
        + ("; chunks stamped as a live SDK stream's" if env.get("stamped") else "")
    )
    print(
        f"python {env['python']}, grpcio {env['grpcio']}, {env['cpus']} CPUs shared by server and load "
        f"(load average {env['load_average_1m_at_start']} at start); MB = 10^6 bytes"
    )
    print()
    rows = []
    for r in report["runs"]:
        label = r["workload"] + (f" x{r['passes']}" if r["passes"] > 1 else "")
        rows.append(
            [
                label,
                r["server"],
                f"{r['bytes'] / MB:,.1f}",
                f"{r['chunks']:,}",
                f"{r['wall_s']:.2f}",
                f"{r['bytes'] / MB / r['wall_s']:,.1f}",
                f"{r['chunks'] / r['wall_s']:,.0f}",
                f"{r['peak_rss_mb']:,.0f}",
                f"{r['server_cpu_s']:.1f} ({r['server_sys_s']:.1f})",
                f"{r['cpu_us_per_chunk']:,.0f}",
                f"{r['load_cpu_s']:.1f}",
                f"{r['load_share']:.2f}",
                f"{r['drain_s']:.1f}",
            ]
        )
    print(
        format_table(
            [
                "workload",
                "server",
                "MB sent",
                "chunks",
                "wall s",
                "MB/s",
                "chunks/s",
                "peak RSS MB",
                "server CPU s (sys)",
                "CPU us/chunk",
                "load CPU s",
                "load share",
                "drain s",
            ],
            rows,
            "llrrrrrrrrrrr",
        )
    )
    print()
    print(
        "wall s: from 'go' to the last call answered; peak RSS: the server's VmHWM (summed over its processes); "
        "server CPU s: during the wall time, all its processes; CPU us/chunk: that per chunk; load CPU s: all "
        "load processes; load share: their CPU / wall / the cores they may use; drain s: server CPU still busy "
        "after the last answer"
    )
    print()
    rows = []
    for s in report["summary"]:
        ours, peer = s.get("ours"), s.get("rerun")
        rows.append(
            [
                s["workload"],
                f"{ours['mb_s']:,.1f}" if ours else "-",
                f"{ours['chunks_s']:,.0f}" if ours else "-",
                f"{peer['mb_s']:,.1f}" if peer else "-",
                f"{peer['chunks_s']:,.0f}" if peer else "-",
                f"{s['ratio_mb_s']:.2f}x" if s["ratio_mb_s"] is not None else "-",
                f">= {s['target']:.1f}x",
                {True: "met", False: "MISSED", None: "-"}[s["met"]],
                f"{ours['peak_rss_mb']:,.0f}" if ours else "-",
                f"{peer['peak_rss_mb']:,.0f}" if peer else "-",
            ]
        )
    print(
        format_table(
            [
                "workload",
                "ours MB/s",
                "ours chunks/s",
                "rerun MB/s",
                "rerun chunks/s",
                "ours/rerun",
                "target",
                "",
                "ours peak RSS MB",
                "rerun peak RSS MB",
            ],
            rows,
            "lrrrrrrlrr",
        )
    )
    print()
    print(
        "ours/rerun: our MB/s / rerun's MB/s, best run of each (the same bytes and chunks: also the chunks/s "
        "ratio); peak RSS: the highest of the runs"
    )
    print()
    print("ours, memory over each run (RSS MB at 0/25/50/75/100 % of the timed part; growth = peak - start):")
    for r in report["runs"]:
        if r["server"] != "ours":
            continue
        growth = r["peak_rss_mb"] - r["rss_start_mb"]
        label = r["workload"] + (f" x{r['passes']}" if r["passes"] > 1 else "")
        print(
            f"  {label:8} start {r['rss_start_mb']:.0f}, course "
            f"{' / '.join(f'{v:.0f}' for v in r['rss_course_mb'])}, peak {r['peak_rss_mb']:.0f}, after "
            f"{r['rss_end_mb']:.0f}: +{growth:.0f} MB over start, {r['bytes'] / 1e9:.2f} GB ingested"
        )
    verdict = report.get("memory")
    if verdict:
        t = verdict["thirds_mb"]
        peaks = ", ".join(f"{p:.0f}" for p in verdict["peaks_1_pass_mb"])
        print(
            f"  across runs: peak {verdict['peak_mb']:.0f} MB for {verdict['gb']:.2f} GB (x{verdict['passes']}) "
            f"against {peaks} MB for {verdict['gb_1_pass']:.2f} GB: "
            f"{verdict['mb_per_gb_across']:+.1f} MB per extra GB"
        )
        print(
            f"  within the x{verdict['passes']} run: highest RSS per third {t[0]:.0f} / {t[1]:.0f} / {t[2]:.0f} MB: "
            f"{verdict['mb_per_gb_within']:+.1f} MB per GB; RSS {verdict['rss_after_mb']:.0f} MB after the run"
        )
        print(
            "  memory "
            + (
                "bounded: < 50 MB per GB both ways"
                if verdict["bounded"]
                else "NOT bounded: grows by >= 50 MB per GB ingested"
            )
        )
    print()
    for r in report["runs"]:
        label = r["workload"] + (f" x{r['passes']}" if r["passes"] > 1 else "")
        print(f"{label:8} {r['server']:5} check: {r['check']}")


# --- main ------------------------------------------------------------------------------------------


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["_load"]:
        load_main(argv[1:])
        return
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--data-dir",
        type=Path,
        default=ROOT / "benchmarks" / "data",
        help="where codec.py's recordings live (default: benchmarks/data, gitignored)",
    )
    parser.add_argument("--robots", type=int, default=8, help="robots = concurrent streams (default 8)")
    parser.add_argument("--procs", type=int, default=2, help="load processes the robots are spread over (default 2)")
    parser.add_argument("--repeat", type=int, default=2, help="runs per server and workload, best counts (default 2)")
    parser.add_argument("--workload", default="big,small", help="comma-separated: big, small (default both)")
    parser.add_argument("--big-mb", type=float, default=220, help="minimum size of big.rrd in MB (default 220)")
    parser.add_argument(
        "--small-chunks", type=int, default=SMALL_CHUNKS, help="1-row chunks in small.rrd (default %(default)s)"
    )
    parser.add_argument(
        "--small-entities", type=int, default=SMALL_ENTITIES, help="entities of small.rrd (default %(default)s)"
    )
    parser.add_argument(
        "--servers", default="ours,rerun", help="comma-separated: ours, rerun (default both; the ratios need both)"
    )
    parser.add_argument(
        "--client",
        choices=["aio", "thread"],
        default="aio",
        help="load client: grpc.aio, one task per robot (default; half the CPU per message of "
        "the blocking API), or the blocking API, one thread per robot",
    )
    parser.add_argument("--rerun", help="the rerun executable (default: the native binary of rerun-sdk)")
    parser.add_argument(
        "--rerun-memory-limit",
        default="16GiB",
        help="rerun --server-memory-limit: large enough that it drops nothing (default 16GiB)",
    )
    parser.add_argument(
        "--no-read-back",
        action="store_true",
        help="skip reading rerun's history back after its first run of each workload (the check "
        "that it holds every chunk; ~30 s for the 1-row chunks)",
    )
    parser.add_argument(
        "--memory-passes",
        type=int,
        default=3,
        help="then one more run of ours on big chunks with each robot sending the recording this "
        "many times (as new recordings): memory must not grow with the bytes (default 3; 0: skip)",
    )
    parser.add_argument(
        "--workers",
        type=int,
        default=None,
        help="start ours as fleet serve --workers N (default: the option left out, one process on DuckDB)",
    )
    parser.add_argument(
        "--catalog",
        choices=["duckdb", "postgres"],
        default=None,
        help="ours's catalog: the embedded DuckDB, or a new database on the local Postgres per start "
        "(default: duckdb, postgres with --workers above 1)",
    )
    parser.add_argument("--server-cpus", help="pin the servers (all their processes) to these CPUs, e.g. 0-3")
    parser.add_argument("--load-cpus", help="pin the load processes to these CPUs, e.g. 4-5")
    parser.add_argument("--tmp", type=Path, default=None, help="where our server's data dirs go (default: $TMPDIR)")
    parser.add_argument(
        "--stamped",
        action="store_true",
        help="chunks stamped as rerun-sdk stamps those it streams (a file's lack the stamps): what robots send",
    )
    parser.add_argument(
        "--rules", type=Path, help="a rules file: server ours+rules is ours running it (--servers ours,ours+rules)"
    )
    parser.add_argument("--json", action="store_true", help="print the results as JSON on stdout instead of tables")
    args = parser.parse_args(argv)
    workloads = [w.strip() for w in args.workload.split(",") if w.strip()]
    servers = [s.strip() for s in args.servers.split(",") if s.strip()]
    if not servers or any(s not in ("ours", "rerun", "ours+rules") for s in servers):
        parser.error("--servers takes ours, rerun, ours+rules, or several of them separated by commas")
    if ("ours+rules" in servers) != (args.rules is not None):
        parser.error("--rules FILE goes with server ours+rules")
    if not workloads or any(w not in TARGETS for w in workloads):
        parser.error("--workload takes big, small or big,small")
    if min(args.robots, args.procs, args.repeat, args.small_chunks, args.small_entities) < 1 or args.big_mb <= 0:
        parser.error("--robots, --procs, --repeat, --small-chunks, --small-entities and --big-mb must be positive")
    if args.workers is not None and args.workers < 1:
        parser.error("--workers must be positive")
    catalog = args.catalog or ("postgres" if (args.workers or 1) > 1 else "duckdb")
    if catalog == "duckdb" and (args.workers or 1) > 1:
        parser.error("--workers above 1 needs --catalog postgres (the embedded DuckDB catalog has one writer)")
    server_cpus, load_cpus = cpu_list(args.server_cpus), cpu_list(args.load_cpus)

    def ours(workdir: Path, rules: Path | None = None) -> FleetServer:
        return FleetServer(workdir, server_cpus, args.workers, catalog, rules)

    load = os.getloadavg()[0]
    if load > 0.5 * (os.cpu_count() or 1):
        log(f"WARNING: load average {load:.2f}: other processes compete for the CPUs, timings will be noisy")
    data_dir: Path = args.data_dir.resolve()
    infos = {}
    if "big" in workloads:
        infos["big"] = ensure_recording(
            data_dir, "big.rrd", {"kind": "big", "big_mb": args.big_mb}, ["gen-big", str(args.big_mb)]
        )
    if "small" in workloads:
        infos["small"] = ensure_small(data_dir, args.small_chunks, args.small_entities)
    rerun_bin, _ = find_rerun_binary(args.rerun)
    version = checked(run_process([rerun_bin, "--version"]), "rerun --version").stdout.split("(")[0].strip()

    runs: list[Run] = []
    tmp_root = Path(tempfile.mkdtemp(prefix="ingest-bench-", dir=args.tmp))
    try:
        for w in workloads:
            path = data_dir / f"{w}.rrd"
            for i in range(args.repeat):
                order = servers if i % 2 == 0 else servers[::-1]  # alternate who goes first
                for name in order:
                    workdir = tmp_root / f"{w}-{name}-{i}"
                    workdir.mkdir()
                    server: Server = (
                        ours(workdir, args.rules if name == "ours+rules" else None)
                        if name.startswith("ours")
                        else RerunServer(workdir, rerun_bin, args.rerun_memory_limit, server_cpus)
                    )
                    log(f"{w} #{i + 1}: {name} ...")
                    run = run_once(
                        server,
                        w,
                        path,
                        args.robots,
                        args.procs,
                        int(infos[w]["chunks"]),
                        args.client,
                        check_rerun=i == 0 and not args.no_read_back,
                        load_cpus=load_cpus,
                        stamped=args.stamped,
                    )
                    log(
                        f"  {run.wall_s:.2f} s, {run.mb_s:,.1f} MB/s, {run.chunks_s:,.0f} chunks/s, peak RSS "
                        f"{run.peak_rss_mb:,.0f} MB, server CPU {run.server_cpu_s:.1f} s "
                        f"({run.cpu_us_per_chunk:,.0f} us/chunk), load CPU {run.load_cpu_s:.1f} s "
                        f"({run.load_share:.2f} of its cores), drain {run.drain_s:.1f} s; {run.check}"
                    )
                    busy = {name: cpu for name, cpu in run.server_procs.items() if cpu >= 0.05}
                    if len(busy) > 1:
                        log("  server CPU by process: " + ", ".join(f"{c:.1f} s {name}" for name, c in busy.items()))
                    runs.append(run)
                    shutil.rmtree(workdir, ignore_errors=True)
        if args.memory_passes > 1 and "big" in workloads and "ours" in servers:
            workdir = tmp_root / "memory-ours"
            workdir.mkdir()
            log(f"memory: ours, big, each robot sending the recording {args.memory_passes} times ...")
            run = run_once(
                ours(workdir),
                "big",
                data_dir / "big.rrd",
                args.robots,
                args.procs,
                int(infos["big"]["chunks"]),
                args.client,
                args.memory_passes,
                load_cpus=load_cpus,
            )
            log(f"  {run.wall_s:.2f} s, {run.mb_s:,.1f} MB/s, peak RSS {run.peak_rss_mb:,.0f} MB; {run.check}")
            runs.append(run)
            shutil.rmtree(workdir, ignore_errors=True)
    finally:
        shutil.rmtree(tmp_root, ignore_errors=True)

    report: dict[str, Any] = {
        "environment": {
            "python": platform.python_version(),
            "platform": platform.platform(),
            "cpus": os.cpu_count(),
            "load_average_1m_at_start": round(load, 2),
            "robots": args.robots,
            "procs": args.procs,
            "client": args.client,
            "stamped": args.stamped,
            "repeat": args.repeat,
            "workers": args.workers,
            "catalog": catalog,
            "compiled": compiled_status(),
            "server_cpus": args.server_cpus,
            "load_cpus": args.load_cpus,
            "rerun_binary": rerun_bin,
            "rerun_version": version,
            "rerun_memory_limit": args.rerun_memory_limit,
            "rerun_sdk": importlib.metadata.version("rerun-sdk"),
            "grpcio": importlib.metadata.version("grpcio"),
            "tmp": str(tmp_root.parent),
        },
        "runs": [
            {k: v for k, v in asdict(r).items() if k != "extra"}
            | {"cpu_us_per_chunk": round(r.cpu_us_per_chunk, 1), "load_share": round(r.load_share, 3)}
            | {"extra": r.extra}
            for r in runs
        ],
        "summary": summarize(runs, workloads),
        "memory": memory_verdict(runs),
        "rules": rules_cost(runs, workloads),
    }
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        print_report(report)
        for entry in report["rules"]:
            print(
                f"rules, {entry['workload']}: server CPU {entry['ours_us_per_chunk']:,.1f} us/chunk without, "
                f"{entry['rules_us_per_chunk']:,.1f} with ({entry['ratio']:.3f}x; target <= 1.10); medians "
                f"{entry['median_ours_us_per_chunk']:,.1f} and {entry['median_rules_us_per_chunk']:,.1f} "
                f"({entry['median_ratio']:.3f}x)"
            )
            if entry["worker_us_per_chunk"] is not None:
                print(
                    f"rules, {entry['workload']}: the rules' worker spent {entry['worker_us_per_chunk']:,.2f} us "
                    f"per chunk (median run; its own CPU clock), {entry['worker_share']:.1%} of the best "
                    "server CPU per chunk without rules"
                )


if __name__ == "__main__":
    main()
