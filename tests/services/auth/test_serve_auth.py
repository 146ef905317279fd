"""`fleet serve` with auth off: refused on an address others reach unless --insecure, and saying
so when it starts."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import httpx
import pytest

from tests.services.ingest.live_server import FLEET
from tests.subprocess_server import ServerProcess, answers_http, free_port

pytestmark = pytest.mark.slow


def _env(tmp_path: Path) -> dict[str, str]:
    return {**os.environ, "FLEET_DATA_DIR": str(tmp_path / "data"), "FLEET_AUTH": "off"}


def _serve(tmp_path: Path, http_host: str, *flags: str) -> tuple[ServerProcess, int]:
    port = free_port()
    server = ServerProcess(
        [FLEET, "serve", "--http-addr", f"{http_host}:{port}", "--grpc-addr", f"127.0.0.1:{free_port()}", *flags],
        env=_env(tmp_path),
        log=tmp_path / "serve.out",
        errors_log=tmp_path / "serve.err",
        name="fleet serve",
        ready=answers_http(f"http://127.0.0.1:{port}/healthz"),
    )
    return server, port


def test_auth_off_on_a_public_address_is_refused_in_one_line_naming_insecure(tmp_path: Path):
    result = subprocess.run(
        [FLEET, "serve", "--http-addr", f"0.0.0.0:{free_port()}", "--grpc-addr", f"127.0.0.1:{free_port()}"],
        env=_env(tmp_path),
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode != 0
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert "--insecure" in lines[0] and "0.0.0.0" in lines[0] and "FLEET_AUTH=off" in lines[0]
    assert not (tmp_path / "data" / "catalog.duckdb").exists()  # refused before anything was made


@pytest.mark.parametrize(
    ("host", "flags", "says"),
    [("0.0.0.0", ["--insecure"], "on a public address (--insecure)"), ("127.0.0.1", [], "on loopback only")],
)
def test_auth_off_starts_where_allowed_and_says_so(tmp_path: Path, host: str, flags: list[str], says: str):
    server, port = _serve(tmp_path, host, *flags)
    try:
        server.start(timeout=60)
        answer = httpx.delete(f"http://127.0.0.1:{port}/v1/runs/no-such-run", timeout=10)
        assert answer.status_code == 404  # no token asked for
    finally:
        server.stop(grace=10)
    out = server.log.read_text()
    assert f"fleet: auth is off, {says}: every request is allowed, with no token" in out, out
    assert not (tmp_path / "data" / "admin.token").exists()
