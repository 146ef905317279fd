"""The SeaweedFS the integration suites start (`tests/seaweedfs.py`): a port taken between being
chosen and being bound (its gRPC ports lie among those the kernel hands to outgoing connections)
makes it start again on other ports, rather than fail the suite."""

from __future__ import annotations

import socket
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests import seaweedfs


@pytest.mark.s3server
@pytest.mark.slow
def test_a_port_taken_before_weed_binds_it_is_traded_for_a_free_one(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        busy = taken.getsockname()[1]
        chosen = seaweedfs._port_pair
        first: Iterator[int] = iter([busy])  # the S3 port of the first try: taken meanwhile
        calls: list[int] = []

        def pair() -> int:
            calls.append(1)
            return next(first, None) or chosen()

        monkeypatch.setattr(seaweedfs, "_port_pair", pair)
        server = seaweedfs.SeaweedFS(tmp_path / "weed").start(timeout=60)
        try:
            assert server.s3 != busy
            server.client().create_bucket(Bucket="ports")
            assert len(calls) == 8  # four ports a try, two tries
        finally:
            server.stop()
