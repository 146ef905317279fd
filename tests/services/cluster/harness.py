"""Several `fleet serve` nodes as real processes on one Postgres catalog and one SeaweedFS bucket,
sharing one signing key, for the tests of a depot made of interchangeable nodes: starting and killing
them, tokens and uploads, what the catalog and the bucket hold of each run, and, when something is
off, a diagnosis naming the run, what was expected, and what each node said last."""

from __future__ import annotations

import collections
import datetime as dt
import io
import os
import re
import secrets
import subprocess
import sys
import time
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import httpx
import sqlalchemy as sa

from catalog.models import JobExecution, RetentionEvent, RunObject
from services.rrd import ArrowMessage, iter_events
from services.sealed.index import CHUNK, from_parquet
from tests.balancer import Balancer
from tests.seaweedfs import SeaweedFS
from tests.services.agent.harness import AgentProcess, Link, download, same_recording
from tests.services.ingest.live_server import LiveServer
from tests.waiting import holds_within

ROBOT = str(Path(__file__).with_name("robot.py"))
WARM_PREFIX = "warm"  # the warm store's prefix in the bucket (FLEET_WARM_URL s3://BUCKET/warm)
TOKEN = re.compile(r"eyJ[\w-]+\.[\w-]+\.[\w-]+")  # a JWT (the admin token a first start prints): never quoted
LOG_LINES = 25  # lines of each node's log quoted in a diagnosis

# What every node of a test runs with: short leases and quick promotion so a test takes a minute or
# two, the retention job every second so its runs on different nodes have every chance to overlap.
NODE_SETTINGS = {
    "auth": "on",
    "peer_addr": "127.0.0.1:0",
    "lease_s": "2",
    "workers": "1",
    "close_after_s": "5",
    "promote_after_s": "4",
    "promote_interval_s": "0.5",
    "retention_interval_s": "1",
    "catalog_flush_s": "0.5",
}


def bearer(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


class Node:
    """One `fleet serve` of the cluster, named by its node id."""

    def __init__(self, name: str, server: LiveServer) -> None:
        self.name = name
        self.server = server
        self.killed_at: dt.datetime | None = None
        self.pid: int | None = None

    @property
    def url(self) -> str:
        return self.server.url

    @property
    def grpc_url(self) -> str:
        return self.server.grpc_url

    def start(self) -> Node:
        self.server.start()
        self.pid = self.server.proc.pid
        return self

    def kill(self) -> None:
        """SIGKILL, not restarted: the node's hot disk is as good as gone."""
        self.server.kill()
        self.killed_at = dt.datetime.now(dt.UTC)

    def get(self, path: str, **params: Any) -> httpx.Response:
        return httpx.get(f"{self.url}{path}", headers=self.server.headers, params=params, timeout=30)

    def run(self, run_id: str) -> dict[str, Any] | None:
        """GET /v1/runs/RUN on this node; None if it answers 404 or is down."""
        try:
            answer = self.get(f"/v1/runs/{run_id}")
        except httpx.TransportError:
            return None
        return cast(dict[str, Any], answer.json()) if answer.status_code == 200 else None

    def log_text(self) -> str:
        try:
            return self.server.log.read_text(errors="replace")
        except OSError:
            return ""

    def errors(self) -> list[str]:
        """Errors the node logged (an exception escaping a handler, a job failing): none is expected."""
        return [line for line in self.log_text().splitlines() if line.startswith(("ERROR:", "Traceback"))]

    def said(self, lines: int = LOG_LINES) -> str:
        """The end of the node's log, without the access log's lines."""
        text = self.log_text()
        kept = [TOKEN.sub("<token>", line) for line in text.splitlines() if "HTTP/1.1" not in line]
        return "\n".join(f"    {line}" for line in kept[-lines:])


@dataclass
class Cluster:
    """Nodes sharing `catalog_url`, the bucket on `weed`, and one signing key."""

    root: Path
    catalog_url: str
    weed: SeaweedFS
    bucket: str
    settings: dict[str, str] = field(default_factory=dict)
    nodes: dict[str, Node] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self._key = secrets.token_urlsafe(48)  # the signing key all nodes share (in their environment only)
        self.engine = sa.create_engine(self.catalog_url)

    def add(self, name: str, **overrides: str) -> Node:
        server = LiveServer(
            self.root / name,
            **{
                **NODE_SETTINGS,
                "node_id": name,
                "auth_key": self._key,
                "catalog_url": self.catalog_url,
                "warm_url": f"s3://{self.bucket}/{WARM_PREFIX}",
                "cold_url": f"s3://{self.bucket}/cold",
                "s3_endpoint_url": self.weed.endpoint,
                **self.settings,
                **overrides,
            },
        )
        self.nodes[name] = Node(name, server)
        return self.nodes[name]

    def start(self, *names: str) -> list[Node]:
        """Start the named nodes at once; each is ready when it answers /healthz."""
        with ThreadPoolExecutor(len(names)) as pool:
            return list(pool.map(lambda n: self.nodes[n].start(), names))

    def stop(self) -> None:
        for node in self.nodes.values():
            if node.server.process.running:
                node.server.kill()  # the catalog and the bucket are dropped next: nothing to shut down for
        self.engine.dispose()

    def alive(self) -> list[Node]:
        return [n for n in self.nodes.values() if n.server.process.running]

    def ingest_token(self, robot: str) -> str:
        """An ingest token for `robot`, made on the first live node (valid on all: one key)."""
        node = self.alive()[0]
        answer = httpx.post(
            f"{node.url}/v1/tokens",
            json={"scopes": ["ingest"], "robot": robot, "name": f"{robot} ingest"},
            headers=node.server.headers,
            timeout=30,
        )
        assert answer.status_code == 201, f"token for {robot} on {node.name}: {answer.status_code} {answer.text}"
        return str(answer.json()["token"])

    # --- what the catalog and the bucket hold ----------------------------------------------------

    def promotions(self, run_id: str) -> list[tuple[dt.datetime, str, str]]:
        """The run's promote events: (when, by whom, detail)."""
        query = sa.select(RetentionEvent.occurred_at, RetentionEvent.actor, RetentionEvent.detail).where(
            RetentionEvent.run_id == run_id, RetentionEvent.action == "promote"
        )
        with self.engine.connect() as conn:
            return [(r[0], r[1], r[2]) for r in conn.execute(query.order_by(RetentionEvent.occurred_at))]

    def sealed_object(self, run_id: str, name: str) -> bytes:
        with self.engine.connect() as conn:
            key = conn.execute(
                sa.select(RunObject.key).where(RunObject.run_id == run_id, RunObject.name == name)
            ).scalar_one_or_none()
        assert key is not None, f"run {run_id}: no {name} in run_objects"
        body = self.weed.client().get_object(Bucket=self.bucket, Key=f"{WARM_PREFIX}/{key}")["Body"]
        return cast(bytes, body.read())

    def sealed_chunk_ids(self, run_id: str) -> tuple[list[bytes], list[str]]:
        """The chunk ids of the run's sealed recording.rrd and of its chunks.parquet, as the bucket holds them."""
        recording = self.sealed_object(run_id, "recording.rrd")
        in_recording = [
            e.chunk_id for e in iter_events(io.BytesIO(recording)) if isinstance(e, ArrowMessage) and e.chunk_id
        ]
        in_index = [
            r.chunk_id.hex()
            for r in from_parquet(self.sealed_object(run_id, "chunks.parquet"))
            if r.kind == CHUNK and r.chunk_id
        ]
        return in_recording, in_index

    def job_overlaps(self, job: str) -> tuple[int, list[str]]:
        """Runs of `job` (job_runs) whose times overlap across nodes: (runs seen, overlaps described).
        A run still open when its node was killed ended with it (its lock went with its connection)."""
        with self.engine.connect() as conn:
            rows = conn.execute(
                sa.select(JobExecution.node, JobExecution.started_at, JobExecution.finished_at, JobExecution.outcome)
                .where(JobExecution.job == job)
                .order_by(JobExecution.started_at)
            ).all()
        now = dt.datetime.now(dt.UTC)
        spans = [
            (node, start, finished or self._ended(node) or now, outcome) for node, start, finished, outcome in rows
        ]
        overlaps = []
        for i, (node, start, end, _) in enumerate(spans):
            for other, o_start, o_end, _ in spans[i + 1 :]:
                if other != node and o_start < end and start < o_end:
                    overlaps.append(
                        f"{job} on {node} {start:%H:%M:%S.%f}-{end:%H:%M:%S.%f} and on {other} "
                        f"{o_start:%H:%M:%S.%f}-{o_end:%H:%M:%S.%f}"
                    )
        return len(spans), overlaps

    def _ended(self, job_node: str) -> dt.datetime | None:
        """When the node a job_runs row names was killed (rows name a node by id, or host:pid)."""
        for node in self.nodes.values():
            if node.killed_at and (job_node == node.name or job_node.endswith(f":{node.pid}")):
                return node.killed_at
        return None

    # --- a diagnosis ------------------------------------------------------------------------------

    def diagnosis(self, run_ids: Iterable[str]) -> str:
        """Each run as every live node and the catalog see it, and the end of every node's log."""
        lines = []
        for run_id in run_ids:
            lines.append(f"run {run_id}:")
            for node in self.alive():
                run = node.run(run_id)
                seen = (
                    "404"
                    if run is None
                    else " ".join(f"{k}={run.get(k)}" for k in ("status", "tier", "owner", "chunks", "robot_id"))
                )
                lines.append(f"  {node.name}: {seen}")
            for when, actor, detail in self.promotions(run_id):
                lines.append(f"  promoted {when:%H:%M:%S.%f} by {actor}: {detail}")
            sealers = [n.name for n in self.nodes.values() if f"promoted run {run_id}:" in n.log_text()]
            lines.append(f"  nodes whose log says they promoted it: {', '.join(sealers) or 'none'}")
        for node in self.nodes.values():
            state = f"killed at {node.killed_at:%H:%M:%S.%f}" if node.killed_at else "running"
            lines.append(f"{node.name} ({state}, log {node.server.log}):\n{node.said()}")
        return "\n".join(lines)


class Problems:
    """What a test found wrong, gathered so that one failure reports all of them with the diagnosis."""

    def __init__(self) -> None:
        self.found: list[str] = []

    def check(self, ok: bool, what: str) -> bool:
        if not ok:
            self.found.append(what)
        return ok

    def attempt(self, what: str, step: Callable[[], object]) -> None:
        """Run a step whose failure (an AssertionError) is a problem found, not the end of the test."""
        try:
            step()
        except AssertionError as exc:
            self.found.append(f"{what}: {exc}")

    def report(self, cluster: Cluster, run_ids: Iterable[str]) -> None:
        if self.found:
            listed = "\n".join(f"- {p}" for p in self.found)
            raise AssertionError(f"{len(self.found)} problem(s):\n{listed}\n\n{cluster.diagnosis(run_ids)}")


def upload(node: Node, copy: Path, token: str, *, wait_s: float = 60) -> dict[str, Any]:
    """POST the file (as it stands now) to the node with the robot's ingest token, as a robot's
    upload job does: again after a 503 UNAVAILABLE (a run whose owner is gone, until its lease
    runs out), for up to `wait_s` seconds."""
    body = copy.read_bytes()
    deadline = time.monotonic() + wait_s
    while True:
        answer = httpx.post(f"{node.url}/v1/uploads", content=body, headers=bearer(token), timeout=120)
        if answer.status_code == 200:
            return cast(dict[str, Any], answer.json())
        if answer.status_code != 503 or time.monotonic() > deadline:
            raise AssertionError(f"upload of {copy.name} to {node.name}: {answer.status_code} {answer.text[:500]}")
        time.sleep(0.5)  # a robot's upload job backs off before asking again


def chunks_in(path: Path) -> list[bytes]:
    return [e.chunk_id for e in iter_events(path) if isinstance(e, ArrowMessage) and e.chunk_id]


def served_equals_copy(node: Node, run_id: str, copy: Path, rerun_bin: str, tmp_path: Path) -> tuple[bool, str]:
    """The run as the node serves it equals the robot's FileSink copy (`rerun rrd compare
    --unordered`), the fleet property set apart on both sides: the depot keeps it without its token."""
    try:
        served = download(node.server, run_id, tmp_path / f"{run_id}-{node.name}-served.rrd")
    except httpx.HTTPStatusError as exc:  # a problem found (with the answer's reason), not the end of the test
        token_file = node.server.data_dir / "admin.token"
        raise AssertionError(
            f"GET /v1/runs/{run_id}/recording.rrd on {node.name} answered {exc.response.status_code}: "
            f"{exc.response.text[:500]} (admin token file there: {token_file.is_file()})"
        ) from None
    sides = []
    for path in (copy, served):
        out = path.with_name(f"{path.stem}-no-fleet.rrd")
        subprocess.run(
            [rerun_bin, "rrd", "filter", "--drop-entity", "/__properties/fleet", str(path), "-o", str(out)],
            check=True,
            capture_output=True,
            timeout=120,
        )
        sides.append(out)
    return same_recording(rerun_bin, sides[0], sides[1])


def duplicates(ids: Iterable[Any]) -> dict[Any, int]:
    return {i: n for i, n in collections.Counter(ids).items() if n > 1}


class SdkRobot:
    """robot.py (the real SDK to a node, with a FileSink copy) in its own process, driven over stdin and
    stdout; its token reaches it in its environment."""

    def __init__(self, url: str, copy: Path, run_id: str, robot: str, token: str, steps: int, frames: int) -> None:
        self.copy, self.run_id, self.token = copy, run_id, token
        self.proc = subprocess.Popen(
            [sys.executable, ROBOT, url, str(copy), run_id, robot, str(steps), str(frames)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env={**os.environ, "FLEET_TOKEN": token},
        )

    def expect(self, line: str) -> None:
        assert self.proc.stdout is not None
        got = self.proc.stdout.readline().strip()
        if got != line:
            self.proc.kill()
            _, err = self.proc.communicate(timeout=30)
            raise AssertionError(f"robot {self.run_id} said {got!r}, not {line!r}: {err[-2000:]}")

    def go_on(self) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write("\n")
        self.proc.stdin.flush()

    def finish(self) -> None:
        _, err = self.proc.communicate(timeout=60)
        assert self.proc.returncode == 0, f"robot {self.run_id} exited {self.proc.returncode}: {err[-2000:]}"

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=30)


class BalancedLink:
    """An agent's link to the depot through a load balancer for each of its two connections (gRPC
    and REST), each trying `nodes` in order."""

    def __init__(self, nodes: list[Node]) -> None:
        self.nodes = nodes
        self.grpc = Balancer([("127.0.0.1", n.server.grpc_port) for n in nodes])
        self.rest = Balancer([("127.0.0.1", n.server.http_port) for n in nodes])

    def grpc_connections(self) -> dict[str, int]:
        """Connections the gRPC balancer forwarded, per node."""
        return {n.name: self.grpc.connections.get(("127.0.0.1", n.server.grpc_port), 0) for n in self.nodes}

    def agent(self, spool: Path, token: str, **settings: str) -> AgentProcess:
        """`fleet agent` with the robot's token, its depot and API behind the balancers (AgentProcess
        reads only the link's two ports)."""
        return AgentProcess(spool, cast(Link, self), token=token, **settings)

    def close(self) -> None:
        self.grpc.close()
        self.rest.close()


def hot_holders(cluster: Cluster, run_id: str) -> list[str]:
    """The live nodes with a hot copy of the run on their disk."""
    return [n.name for n in cluster.alive() if (n.server.data_dir / "hot" / run_id).exists()]


def settled(cluster: Cluster, run_id: str) -> bool:
    """The catalog has the run warm and no live node holds a hot copy of it any more."""
    run = cluster.alive()[0].run(run_id)
    return run is not None and run.get("tier") == "warm" and not hot_holders(cluster, run_id)


def wait_settled(cluster: Cluster, run_ids: list[str], problems: Problems, timeout: float) -> list[str]:
    """Wait until every run has settled; the runs that did are returned, the others are problems."""
    holds_within(lambda: all(settled(cluster, r) for r in run_ids), timeout)
    done = []
    for run_id in run_ids:
        run = cluster.alive()[0].run(run_id)
        tier = None if run is None else run.get("tier")
        holders = hot_holders(cluster, run_id)
        if problems.check(
            tier == "warm" and not holders,
            f"run {run_id} not settled after {timeout:g} s: expected warm in the catalog and no hot copy left; "
            f"the catalog says tier {tier!r}, hot copies on {holders or 'no node'}",
        ):
            done.append(run_id)
    return done


def verify_sealed(
    cluster: Cluster, problems: Problems, run_id: str, copy: Path, node: Node, rerun_bin: str, tmp_path: Path
) -> None:
    """A sealed run as it should be: served by `node` equal to the robot's copy, every chunk once in the
    bucket's recording.rrd and chunks.parquet, promoted once."""
    same, said = served_equals_copy(node, run_id, copy, rerun_bin, tmp_path)
    problems.check(same, f"run {run_id} served by {node.name} differs from the robot's FileSink copy: {said.strip()}")
    in_recording, in_index = cluster.sealed_chunk_ids(run_id)
    twice = duplicates(in_recording)
    problems.check(
        not twice,
        f"run {run_id}: {len(twice)} chunk id(s) more than once in the sealed recording.rrd "
        f"(e.g. {next(iter(twice)).hex() if twice else ''}), {len(in_recording)} chunks in all",
    )
    problems.check(
        not duplicates(in_index), f"run {run_id}: chunks.parquet lists {len(duplicates(in_index))} chunk id(s) twice"
    )
    promotions = cluster.promotions(run_id)
    problems.check(
        len(promotions) == 1,
        f"run {run_id} promoted {len(promotions)} times, expected once: "
        + "; ".join(f"{when:%H:%M:%S.%f} by {actor}: {detail}" for when, actor, detail in promotions),
    )


def expect_owner(problems: Problems, node: Node, run_id: str, owner: str, when: str) -> None:
    """`GET /v1/runs/RUN` on `node` names `owner` as the hot run's owner (a run sealed already has none)."""
    shown = node.run(run_id) or {}
    problems.check(
        shown.get("owner") == owner or shown.get("tier") == "warm",
        f"GET /v1/runs/{run_id} on {node.name} {when}: owner {shown.get('owner')!r} (tier {shown.get('tier')!r}), "
        f"expected {owner!r}",
    )


def check_logs(cluster: Cluster, problems: Problems) -> None:
    """The live nodes logged no error: a dead peer, a relay refused, a lease taken over are all expected
    and said as warnings; an error is something the node did not handle."""
    for node in cluster.alive():
        found = node.errors()
        problems.check(
            not found, f"{node.name} logged {len(found)} error(s), e.g. {found[:3]} (the log: {node.server.log})"
        )
