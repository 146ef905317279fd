"""`fleet serve --workers N` (services/workers.py) and the host's /metrics across workers."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from pydantic import SecretStr

from core.errors import InvalidArgumentError
from services.api.worker_metrics import merge_expositions
from services.cluster.relay import request_of
from services.rrd.decoder import iter_events
from services.rrd.messages import ArrowMessage
from services.settings import load_settings
from services.workers import worker_count, worker_settings
from tests.conftest import fresh_catalog
from tests.services.ingest.live_server import LiveServer

PG = "postgresql+psycopg://postgres@127.0.0.1:5432/fleet"


def test_the_embedded_catalog_runs_one_worker_and_refuses_more(tmp_path: Path) -> None:
    assert worker_count(load_settings(data_dir=tmp_path, workers=0)) == 1
    assert worker_count(load_settings(data_dir=tmp_path, workers=1)) == 1
    with pytest.raises(InvalidArgumentError, match=r"needs a Postgres catalog \(FLEET_CATALOG_URL=postgresql"):
        worker_count(load_settings(data_dir=tmp_path, workers=2))


def test_a_shared_catalog_runs_one_worker_per_core_unless_told(tmp_path: Path) -> None:
    assert worker_count(load_settings(data_dir=tmp_path, catalog_url=PG, workers=0)) == (os.cpu_count() or 1)
    assert worker_count(load_settings(data_dir=tmp_path, catalog_url=PG, workers=3)) == 3


def test_each_worker_is_a_node_of_its_own_with_the_depots_key(tmp_path: Path) -> None:
    settings = load_settings(data_dir=tmp_path, catalog_url=PG, node_id="rack1", peer_addr="0.0.0.0:51235")
    key = SecretStr("s" * 40)
    first, second = worker_settings(settings, 0, key), worker_settings(settings, 1, key)
    assert (first.data_dir, second.data_dir) == (tmp_path / "workers" / "w0", tmp_path / "workers" / "w1")
    assert (first.node_id, second.node_id) == ("rack1-w0", "rack1-w1")
    assert (first.peer_addr, second.peer_addr) == ("0.0.0.0:51235", "0.0.0.0:51236")
    assert first.auth_key is not None and first.auth_key.get_secret_value() == "s" * 40
    assert first.catalog_url == PG and first.warm_url == settings.warm_url  # shared, not per worker
    assert worker_settings(load_settings(data_dir=tmp_path, catalog_url=PG), 1, key).peer_addr == "127.0.0.1:0"


def test_metrics_of_the_workers_are_added_up() -> None:
    one = (
        "# HELP fleet_ingest_chunks_new_total New chunks\n# TYPE fleet_ingest_chunks_new_total counter\n"
        "fleet_ingest_chunks_new_total 10.0\n"
        "# HELP fleet_hot_runs Hot runs\n# TYPE fleet_hot_runs gauge\nfleet_hot_runs 2.0\n"
        '# HELP fleet_build_info Release\n# TYPE fleet_build_info gauge\nfleet_build_info{version="1"} 1.0\n'
        "# HELP t Time\n# TYPE t histogram\n"
        't_bucket{le="1.0",route="/a"} 3.0\nt_bucket{le="+Inf",route="/a"} 4.0\nt_count{route="/a"} 4.0\n'
        't_sum{route="/a"} 2.5\n'
    )
    two = one.replace(" 10.0", " 5.0").replace("fleet_hot_runs 2.0", "fleet_hot_runs 1.0")
    merged = merge_expositions([one, two]).decode()
    assert "fleet_ingest_chunks_new_total 15.0" in merged
    assert "fleet_hot_runs 3.0" in merged
    assert 'fleet_build_info{version="1"} 1.0' in merged  # taken once
    assert 't_bucket{le="1.0",route="/a"} 6.0' in merged and 't_sum{route="/a"} 5.0' in merged
    assert merged.count("# TYPE fleet_hot_runs gauge") == 1


ROBOT_SCRIPT = """
import sys, rerun as rr
for run_id in sys.argv[2:]:
    rec = rr.RecordingStream("workers", recording_id=run_id)
    rec.set_sinks(rr.FileSink(f"{sys.argv[1]}/{run_id}.rrd"))
    for i in range(50):
        rec.set_time("step", sequence=i)
        rec.log("/metrics/speed", rr.Scalars(float(i)))
    rec.flush()
"""


@pytest.fixture
def depot(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[LiveServer]:
    with fresh_catalog("postgres", request, tmp_path) as url:
        server = LiveServer(tmp_path / "depot", workers="2", node_id="host", catalog_url=url, lease_s="2")
        try:
            yield server.start()
        finally:
            server.kill()
            for pid in _children(server):
                os.kill(pid, signal.SIGKILL)


def _children(server: LiveServer) -> list[int]:
    path = Path(f"/proc/{server.proc.pid}/task/{server.proc.pid}/children")
    return [int(p) for p in path.read_text().split()] if path.exists() else []


def _nodes(server: LiveServer) -> dict[str, dict[str, object]]:
    return {n["id"]: n for n in httpx.get(f"{server.url}/v1/nodes", timeout=10).json()["nodes"]}


@pytest.mark.slow
@pytest.mark.sdk
@pytest.mark.postgres
def test_workers_share_the_ports_count_as_one_and_come_back(depot: LiveServer, tmp_path: Path) -> None:
    depot.wait_for(
        lambda: all(_nodes(depot).get(n, {}).get("alive") for n in ("host-w0", "host-w1")), what="both workers"
    )
    runs = [f"run-{i}" for i in range(6)]
    env = {**os.environ, "RERUN_FLUSH_NUM_ROWS": "1"}
    subprocess.run([sys.executable, "-c", ROBOT_SCRIPT, str(tmp_path), *runs], check=True, env=env)
    chunks = 0
    for run in runs:
        path = tmp_path / f"{run}.rrd"
        chunks += sum(isinstance(e, ArrowMessage) for e in iter_events(path))
        requests = [r for r in (request_of(e) for e in iter_events(path)) if r is not None]
        assert depot.write_messages(requests)[0].name == "OK"
        again = httpx.post(f"{depot.url}/v1/uploads", content=path.read_bytes(), timeout=60).json()
        assert again["chunks_new"] == 0, again  # whichever worker it reached, the owner had them all
    # Whichever worker answers the scrape, the figures are the host's.
    for _ in range(4):
        assert depot.metric("fleet_ingest_chunks_new_total") == chunks

    def catalogued() -> list[dict[str, object]] | None:
        # Each run's row is written by its owner's next catalog flush; until then only the worker
        # filing it answers (from its hot view), so a run found once may still be missing from the other.
        answers = [httpx.get(f"{depot.url}/v1/runs/{run}", timeout=10) for run in runs]
        return [a.json() for a in answers] if all(a.status_code == 200 for a in answers) else None

    owners = {answer["owner"] for answer in depot.wait_for(catalogued, what="every run in the catalog")}
    assert owners <= {"host-w0", "host-w1", None}

    started = {i: n["started_at"] for i, n in _nodes(depot).items()}
    workers = [pid for pid in _children(depot) if b"resource_tracker" not in Path(f"/proc/{pid}/cmdline").read_bytes()]
    assert len(workers) == 2
    os.kill(workers[0], signal.SIGKILL)

    def restarted() -> bool:
        now = _nodes(depot)
        return all(n["alive"] for n in now.values()) and any(now[i]["started_at"] != t for i, t in started.items())

    depot.wait_for(restarted, timeout=60, what="the killed worker to be started again")
    workers = [pid for pid in _children(depot) if b"resource_tracker" not in Path(f"/proc/{pid}/cmdline").read_bytes()]
    depot.stop()
    assert depot.proc.returncode == 0
    assert not [pid for pid in workers if Path(f"/proc/{pid}").exists()]
