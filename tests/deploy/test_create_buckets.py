"""deploy/create_buckets.py, the compose file's bucket one-shot: which buckets it makes, and making
them on a real S3-compatible server (SeaweedFS), twice, with versioning on."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType

import pytest

from tests.deploy.deploy_files import DEPLOY
from tests.seaweedfs import SeaweedFS


def load() -> ModuleType:
    spec = importlib.util.spec_from_file_location("create_buckets", DEPLOY / "create_buckets.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_bucket_names_are_the_distinct_s3_buckets() -> None:
    names = load().bucket_names
    assert names("s3://fleet-warm/warm", "s3://fleet-cold/cold") == ["fleet-warm", "fleet-cold"]
    assert names("s3://one/warm", "s3://one/cold") == ["one"]
    assert names("file:///var/lib/fleet/warm", "s3://cold") == ["cold"]


@pytest.mark.s3server
@pytest.mark.slow
def test_creates_the_buckets_once_with_versioning(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    server = SeaweedFS(tmp_path / "s3").start()
    try:
        for name, value in {
            "FLEET_WARM_URL": "s3://fleet-warm/warm",
            "FLEET_COLD_URL": "s3://fleet-cold/cold",
            "FLEET_S3_ENDPOINT_URL": server.endpoint,
            "FLEET_S3_REGION": "us-east-1",
            "AWS_ACCESS_KEY_ID": "test",
            "AWS_SECRET_ACCESS_KEY": "test",
        }.items():
            monkeypatch.setenv(name, value)
        module = load()
        assert module.main(["--versioning", "--wait", "30"]) == 0
        assert module.main(["--versioning", "--wait", "30"]) == 0  # a second run finds them: still success
        out = capsys.readouterr().out
        assert "created bucket fleet-warm" in out and "bucket fleet-warm already there, versioning on" in out
        client = server.client()
        for bucket in ("fleet-warm", "fleet-cold"):
            client.head_bucket(Bucket=bucket)  # raises unless it is there
            assert client.get_bucket_versioning(Bucket=bucket)["Status"] == "Enabled"
    finally:
        server.stop()


def test_a_store_that_never_answers_is_reported(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("FLEET_WARM_URL", "s3://fleet-warm/warm")
    monkeypatch.setenv("FLEET_S3_ENDPOINT_URL", "http://127.0.0.1:9")  # discard: nothing listens
    monkeypatch.setenv("AWS_ACCESS_KEY_ID", "test")
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", "test")
    with pytest.raises(SystemExit, match="did not answer"):
        load().main(["--wait", "0"])
