"""Two nodes on one Postgres catalog and one bucket (SeaweedFS) sealing runs at the same moment: each
copies its runs into the same Iceberg tables, their commits racing. Every run's rows are there once:
none lost to a commit that lost, none doubled by one made again."""

from __future__ import annotations

import json
from pathlib import Path

import httpx
import pyarrow.compute as pc
import pytest

from services.lakehouse.tables import open_lakehouse
from services.storage.objectstore import open_store
from tests.services.analytics.conftest import log_with_sdk
from tests.services.cluster.conftest import BUCKET, cluster, cluster_catalog_url, weed  # noqa: F401 - fixtures
from tests.services.cluster.harness import WARM_PREFIX, Cluster, Node, Problems, check_logs
from tests.services.lakehouse.test_outside_engines import SCRIPT

pytestmark = [pytest.mark.sdk, pytest.mark.slow, pytest.mark.postgres, pytest.mark.s3server]

RUNS = {f"pair-run-{k}": f"robot-{k % 3}" for k in range(6)}


def sql_counts(node: Node, table: str) -> dict[str, int]:
    query = {"query": f"SELECT run_id, count(*) AS n FROM {table} GROUP BY run_id"}
    answer = httpx.post(f"{node.url}/v1/sql", json=query, headers=node.server.headers, timeout=60)
    assert answer.status_code == 200, answer.text
    return {run: n for run, n in answer.json()["rows"]}


def test_two_nodes_sealing_at_once_copy_every_run_once(cluster: Cluster, tmp_path: Path) -> None:  # noqa: F811
    folder = tmp_path / "sdk"
    folder.mkdir()
    truth = log_with_sdk(f"FOLDER = {str(folder)!r}\n" + SCRIPT.format(runs=json.dumps(RUNS)), flush_rows=8)
    a, b = (cluster.add(name, promote_after_s="1", lakehouse_sync_s="0.5") for name in ("node-a", "node-b"))
    cluster.start("node-a", "node-b")
    for k, run in enumerate(sorted(RUNS)):
        node = (a, b)[k % 2]  # three runs filed (and sealed) by each node
        answer = httpx.post(
            f"{node.url}/v1/uploads", content=(folder / f"{run}.rrd").read_bytes(), headers=node.server.headers
        )
        assert answer.status_code == 200, answer.text

    expected = {table: {run: truth[run][table] for run in RUNS} for table in ("scalars", "text_logs")}
    a.server.wait_for(lambda: sql_counts(a, "scalars") == expected["scalars"], 180, "every run's rows, once")
    for node in (a, b):
        for table in ("scalars", "text_logs"):
            assert sql_counts(node, table) == expected[table], (node.name, table)
    for node in (a, b):  # both nodes sealed runs, so both wrote the tables
        assert "promoted run pair-run-" in node.log_text(), node.name
    assert all(len(cluster.promotions(run)) == 1 for run in RUNS)

    warm = open_store(f"s3://{BUCKET}/{WARM_PREFIX}", endpoint_url=cluster.weed.endpoint, region="us-east-1")
    lake = open_lakehouse(cluster.catalog_url, warm)
    try:
        for table in ("scalars", "text_logs"):
            rows = lake.table(table).scan(selected_fields=("run_id",)).to_arrow()["run_id"]
            counts = {c["values"]: c["counts"] for c in pc.value_counts(rows).to_pylist()}
            assert counts == expected[table], table
        runs = lake.table("runs").scan(selected_fields=("id", "tier")).to_arrow().to_pylist()
        assert sorted((r["id"], r["tier"]) for r in runs) == [(run, "warm") for run in sorted(RUNS)]
    finally:
        lake.close()
    problems = Problems()
    check_logs(cluster, problems)
    problems.report(cluster, RUNS)
