"""The S3 backends the storage tests run over: moto (in-process) and a real S3-compatible server
(SeaweedFS) started once for the package on loopback. The fixtures are registered in conftest.py."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from tests.seaweedfs import seaweedfs

BUCKET = "fleet-warm"
REGION = "us-east-1"
S3_BACKENDS = ["s3-moto", pytest.param("s3-seaweedfs", marks=[pytest.mark.s3server, pytest.mark.slow])]


@dataclass(frozen=True)
class S3Target:
    """Where a test's store lives: open it with open_store(url, endpoint_url=..., region=REGION)."""

    url: str
    endpoint_url: str | None


@pytest.fixture(scope="package")
def seaweed_endpoint(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    import boto3

    with seaweedfs(tmp_path_factory.mktemp("seaweedfs")) as endpoint:
        # One bucket, a prefix per test: each SeaweedFS bucket reserves volumes of its own.
        boto3.client(
            "s3", endpoint_url=endpoint, region_name=REGION, aws_access_key_id="test", aws_secret_access_key="test"
        ).create_bucket(Bucket=BUCKET)
        yield endpoint


def s3_target_for(
    backend: str, request: pytest.FixtureRequest, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> Iterator[S3Target]:
    """The body of an S3 fixture parametrized over S3_BACKENDS (moto's mock lasts while it runs)."""
    for name, value in (
        ("AWS_ACCESS_KEY_ID", "test"),
        ("AWS_SECRET_ACCESS_KEY", "test"),
        ("AWS_DEFAULT_REGION", REGION),
    ):
        monkeypatch.setenv(name, value)
    if backend == "s3-seaweedfs":
        yield S3Target(f"s3://{BUCKET}/{tmp_path.name}", request.getfixturevalue("seaweed_endpoint"))
        return
    from moto import mock_aws

    with mock_aws():
        import boto3

        boto3.client("s3", region_name=REGION).create_bucket(Bucket=BUCKET)
        yield S3Target(f"s3://{BUCKET}/depot", None)


@pytest.fixture(params=S3_BACKENDS)
def s3_target(request: pytest.FixtureRequest, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[S3Target]:
    yield from s3_target_for(request.param, request, tmp_path, monkeypatch)
