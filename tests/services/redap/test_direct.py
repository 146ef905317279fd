"""Which candidate rows carry a presigned URL (services/redap/direct.py), and how they carry it; the
end-to-end read by Rerun's SDK from a bucket is in test_direct_reads.py."""

from __future__ import annotations

import urllib.parse
from collections.abc import Iterator
from pathlib import Path

import pyarrow as pa
import pytest
from pydantic import ValidationError
from sqlalchemy.orm import sessionmaker

from catalog.db import create_engine, upgrade
from services.redap import direct
from services.redap.candidate_table import candidate_batch, find_chunks_schema, query_dataset_schema
from services.redap.depot import Depot
from services.redap.pb import cloud_pb2
from services.redap.sources import IndexedRecordingSource
from services.sealed.index import IndexRow
from services.sealed.tiers import Tiers
from services.settings import DirectReads, load_settings
from services.storage.objectstore import PRESIGNED_TTL_MAX_S, open_store, supports_presigned
from tests.services.nodes import node_of

BUCKET = "fleet-warm"
SEALED = IndexedRecordingSource("run-1", prefix="robot-7/2026-11-30/run-1", digest="d" * 64, size=1000)


@pytest.fixture
def s3(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    from moto import mock_aws

    for name, value in (
        ("AWS_ACCESS_KEY_ID", "key-id"),
        ("AWS_SECRET_ACCESS_KEY", "the-secret"),
        ("AWS_DEFAULT_REGION", "us-east-1"),
    ):
        monkeypatch.setenv(name, value)
    with mock_aws():
        import boto3

        boto3.client("s3", region_name="us-east-1").create_bucket(Bucket=BUCKET)
        yield


def _depot(tmp_path: Path, reads: DirectReads, warm_url: str) -> Depot:
    settings = load_settings(
        data_dir=tmp_path / "data", scheduler=False, warm_url=warm_url, direct_reads=reads, direct_url_ttl_s=300
    )
    engine = create_engine(f"duckdb:///{tmp_path / 'catalog.duckdb'}")
    upgrade(engine)
    catalog = sessionmaker(engine)
    tiers = Tiers(open_store(warm_url), open_store((tmp_path / "cold").as_uri()))
    return Depot(node_of(tmp_path, catalog, settings=settings, tiers=tiers), hot=None)


def test_a_sealed_run_in_s3_gets_a_url_of_its_recording_that_expires(s3: None, tmp_path: Path):
    found = direct.direct_url(_depot(tmp_path, DirectReads.PRESIGNED, f"s3://{BUCKET}/warm"), SEALED)
    assert found is not None
    parts = urllib.parse.urlsplit(found.url)
    assert parts.path.endswith(f"/warm/{SEALED.prefix}/recording.rrd")
    query = urllib.parse.parse_qs(parts.query)
    assert query["X-Amz-Expires"] == ["300"] and "X-Amz-Signature" in query
    assert "the-secret" not in found.url


def test_no_url_when_direct_reads_are_off_or_the_run_is_hot(s3: None, tmp_path: Path):
    off = _depot(tmp_path / "off", DirectReads.OFF, f"s3://{BUCKET}/warm")
    assert direct.direct_url(off, SEALED) is None
    on = _depot(tmp_path / "on", DirectReads.PRESIGNED, f"s3://{BUCKET}/warm")
    assert direct.direct_url(on, IndexedRecordingSource("run-2")) is None  # a hot run: no sealed prefix


def test_presigned_reads_need_an_s3_warm_store(tmp_path: Path):
    with pytest.raises(ValidationError, match="direct_reads=presigned needs an s3:// warm_url"):
        load_settings(data_dir=tmp_path, direct_reads="presigned")
    with pytest.raises(ValidationError, match="direct_url_ttl_s"):
        load_settings(data_dir=tmp_path, warm_url=f"s3://{BUCKET}/w", direct_reads="presigned", direct_url_ttl_s=3600)
    assert not supports_presigned(open_store((tmp_path / "w").as_uri()))


def test_a_url_lasts_at_most_fifteen_minutes_and_names_the_endpoint_clients_reach(s3: None):
    store = open_store(f"s3://{BUCKET}/warm", presign_endpoint_url="https://bucket.example.com")
    assert supports_presigned(store)
    url = store.presigned_get("a/recording.rrd", PRESIGNED_TTL_MAX_S)
    assert url.startswith(f"https://bucket.example.com/{BUCKET}/warm/a/recording.rrd?")
    with pytest.raises(ValueError, match="lasts 1 to 900 s"):
        store.presigned_get("a/recording.rrd", PRESIGNED_TTL_MAX_S + 1)


@pytest.mark.parametrize(
    ("mode", "wanted"),
    [
        (cloud_pb2.DIRECT_URL_MODE_UNSPECIFIED, True),
        (cloud_pb2.DIRECT_URL_MODE_SIGNED, True),
        (cloud_pb2.DIRECT_URL_MODE_UNSIGNED, False),
        (cloud_pb2.DIRECT_URL_MODE_OMIT, False),
    ],
)
def test_find_chunks_asks_for_signed_urls_unless_it_says_otherwise(mode: int, wanted: bool):
    assert direct.wanted_by_find_chunks(cloud_pb2.FindChunksRequest(direct_url_mode=mode)) is wanted  # type: ignore[arg-type]


def test_query_dataset_asks_for_them_by_its_two_flags():
    assert direct.wanted_by_query_dataset(cloud_pb2.QueryDatasetRequest(generate_direct_urls=True))
    assert not direct.wanted_by_query_dataset(cloud_pb2.QueryDatasetRequest())
    unsigned = cloud_pb2.QueryDatasetRequest(generate_direct_urls=True, unsigned_direct_urls=True)
    assert not direct.wanted_by_query_dataset(unsigned)


def _rows(n: int) -> list[IndexRow]:
    return [
        IndexRow("chunk", "recording", 100 * i, 100, chunk_id=bytes([i]) * 16, entity_path="/a", is_static=True)
        for i in range(n)
    ]


@pytest.mark.parametrize("schema", [find_chunks_schema(), query_dataset_schema("frame")], ids=["find", "query"])
def test_each_row_names_its_segment_s_url_once_in_the_dictionary(schema: pa.Schema):
    url = direct.DirectUrl("https://bucket/warm/r/recording.rrd?X-Amz-Signature=abc", 1_800_000_000 * 10**9)
    batch = candidate_batch(schema, "run-1", _rows(3), {}, "frame", url)
    assert batch.schema.equals(schema)
    urls = batch.column(batch.schema.get_field_index("rerun_layer_direct_url"))
    assert urls.to_pylist() == [url.url] * 3 and len(urls.dictionary) == 1
    expiry = batch.column(batch.schema.get_field_index("rerun_layer_direct_url_expires_at"))
    assert expiry.to_pylist() == [url.expires_at_ns] * 3
    without = candidate_batch(schema, "run-1", _rows(3), {}, "frame")
    assert without.column(without.schema.get_field_index("rerun_layer_direct_url")).null_count == 3
