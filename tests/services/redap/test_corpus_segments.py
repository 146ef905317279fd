"""The corpus in the catalog protocol's segment table: `property:depot:metric:NAME` per metric
(float64, or utf8 for a text metric) and `property:depot:tags`, read through the real rerun-sdk
`CatalogClient` and filtered with DataFusion, keeping the runs `GET /v1/runs` keeps."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pyarrow as pa
import pytest
from sqlalchemy.orm import Session

from catalog.db import session_scope
from services.redap import segments
from services.redap.depot import Depot
from services.runs import service
from services.runs.service import RunFilter
from tests.services.redap.catalog_node import CatalogGrpc
from tests.services.redap.depots import catalog_depot, entry_of
from tests.services.redap.test_segments import READER
from tests.services.runs.corpus_scene import APP, IDS, expected, write_scene

TAGS = "property:depot:tags"
DISTANCE = "property:depot:metric:distance_m"
VERSION = "property:depot:metric:sw_version"
TEMP = "property:depot:metric:temp_c"


@pytest.fixture
def depot(fresh_catalog_url: str) -> Iterator[Depot]:
    with catalog_depot(fresh_catalog_url) as made:
        with session_scope(made.catalog, write=True) as session:
            write_scene(session)
        yield made


def rest_ids(depot: Depot, **flt: Any) -> list[str]:
    with session_scope(depot.catalog) as session:
        return [r.id for r in _runs(session, flt)]


def _runs(session: Session, flt: dict[str, Any]) -> list[Any]:
    runs, _ = service.list_runs(session, RunFilter(sort="id", **flt))
    return runs


def test_the_segment_table_has_a_column_per_metric_and_the_tags(depot: Depot):
    answer = segments.table_schema(depot, READER, entry_of(depot, APP))
    schema = pa.ipc.read_schema(pa.py_buffer(answer.schema.arrow_schema))
    assert schema.field(DISTANCE).type == pa.list_(pa.float64())
    assert schema.field(TEMP).type == pa.list_(pa.float64())
    assert schema.field(VERSION).type == pa.list_(pa.utf8())  # a text metric
    assert schema.field(TAGS).type == pa.list_(pa.utf8())
    metadata = {k.decode(): v.decode() for k, v in (schema.field(DISTANCE).metadata or {}).items()}
    assert metadata == {
        "rerun:component": "metric:distance_m",
        "rerun:entity_path": "/__properties/depot",
        "rerun:kind": "data",
    }
    names = [n for n in schema.names if n.startswith("property:")]
    assert names == sorted(names)  # among the property columns, by name


@pytest.mark.sdk
def test_the_sdk_filters_segments_on_metrics_and_tags_as_rest_does(depot: Depot):
    import rerun as rr
    from datafusion import col, lit
    from datafusion import functions as f

    server = CatalogGrpc(depot)
    server.start()
    try:
        client = rr.catalog.CatalogClient(f"rerun+http://127.0.0.1:{server.port}")
        table = client.get_dataset(APP).segment_table()

        def kept(condition: Any) -> list[str]:
            rows = table.filter(condition).select(col("rerun_segment_id")).to_arrow_table()
            return sorted(rows.column("rerun_segment_id").to_pylist())

        distance = f.array_element(col(DISTANCE), lit(1))
        assert kept(distance > lit(100.0)) == rest_ids(depot, metric=["distance_m>100"]) == ["r-1", "r-4"]
        assert kept(distance <= lit(100.0)) == rest_ids(depot, metric=["distance_m<=100"])
        version = f.array_element(col(VERSION), lit(1))
        assert kept(version == lit("2.3")) == rest_ids(depot, metric=["sw_version=2.3"]) == ["r-1", "r-3"]
        night = f.array_has(col(TAGS), lit("night-shift"))
        assert kept(night) == rest_ids(depot, tag=["night-shift"]) == expected({"tag": ["night-shift"]})
        both = night & f.array_has(col(TAGS), lit("dock-2")) & (distance >= lit(100.0))
        assert kept(both) == rest_ids(depot, tag=["night-shift", "dock-2"], metric=["distance_m>=100"]) == ["r-1"]

        whole = table.to_arrow_table()
        rows = {r["rerun_segment_id"]: r for r in whole.to_pylist()}
        assert sorted(rows) == IDS
        assert rows["r-1"][TAGS] == ["dock-2", "night-shift"] and rows["r-3"][TAGS] is None
        assert rows["r-3"][TEMP] == [-3.5] and rows["r-5"][DISTANCE] is None
    finally:
        server.stop()
