"""gRPC: rerun-sdk 0.22's service (rerun.sdk_comms.v0) is answered with a refusal that says what to do."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import grpc
import pytest

from services.ingest.grpc_handler import LEGACY_REFUSAL, LEGACY_SERVICE_NAME
from tests.services.ingest.live_server import LiveServer

pytestmark = pytest.mark.slow  # starts a real `fleet serve`


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    live = LiveServer(Path(tmp_path_factory.mktemp("grpc")) / "data").start()
    yield live
    live.stop()


@pytest.mark.parametrize("method", ["WriteMessages", "ReadMessages"])
def test_sdk_0_22_calls_are_refused_with_the_fix(server: LiveServer, method: str):
    with grpc.insecure_channel(f"127.0.0.1:{server.grpc_port}") as channel:
        path = f"/{LEGACY_SERVICE_NAME}/{method}"
        with pytest.raises(grpc.RpcError) as refused:
            if method == "WriteMessages":
                channel.stream_unary(path)(iter([b"\x0a\x00"]), timeout=30)
            else:
                list(channel.unary_stream(path)(b"", timeout=30))
    assert refused.value.code() == grpc.StatusCode.FAILED_PRECONDITION  # type: ignore[attr-defined]
    assert refused.value.details() == LEGACY_REFUSAL  # type: ignore[attr-defined]
    assert "oldest supported rerun-sdk is 0.23" in LEGACY_REFUSAL and "pip install -U rerun-sdk" in LEGACY_REFUSAL
    assert server.proc is not None and server.proc.poll() is None
