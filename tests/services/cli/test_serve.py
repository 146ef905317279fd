import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx

FLEET = str(Path(sys.executable).with_name("fleet"))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _wait_healthy(url: str, proc: subprocess.Popen[bytes], timeout: float = 30.0) -> httpx.Response:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        assert proc.poll() is None, proc.stderr.read().decode() if proc.stderr else "exited"
        try:
            return httpx.get(url, timeout=1.0)
        except httpx.TransportError:
            time.sleep(0.05)  # polling for the condition, bounded by the deadline
    raise AssertionError(f"{url} did not answer within {timeout}s")


def test_serve_answers_health_on_the_configured_address(tmp_path):
    port = _free_port()
    env = {**os.environ, "FLEET_DATA_DIR": str(tmp_path / "data")}
    proc = subprocess.Popen([FLEET, "serve", "--http-addr", f"127.0.0.1:{port}"], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        response = _wait_healthy(f"http://127.0.0.1:{port}/healthz", proc)
        assert response.status_code == 200
        assert response.json()["status"] == "ok"
        assert httpx.get(f"http://127.0.0.1:{port}/openapi.json").status_code == 200
        assert (tmp_path / "data" / "catalog.duckdb").is_file()
    finally:
        proc.terminate()
        out, _ = proc.communicate(timeout=10)
    assert b"created the embedded catalog" in out  # said once, on first start


def test_serve_refuses_a_postgres_catalog_that_is_behind(empty_postgres_url: str, tmp_path):
    result = subprocess.run([FLEET, "serve", "--data-dir", str(tmp_path), "--catalog-url", empty_postgres_url],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 1
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "fleet db upgrade" in lines[0], result.stderr


def test_serve_help_documents_every_setting():
    out = subprocess.run([FLEET, "serve", "--help"], capture_output=True, text=True, check=True).stdout
    from services.settings import Settings

    # every setting but the CLI's own (where commands reach the service) is a serve flag
    names = [name for name in Settings.model_fields if name != "api_url"]
    assert "FLEET_CONFIG" in out
    for name in names:
        assert f"FLEET_{name.upper()}" in out, name


def test_bad_address_is_one_clear_error(tmp_path):
    result = subprocess.run([FLEET, "serve", "--data-dir", str(tmp_path), "--http-addr", "nonsense"],
                            capture_output=True, text=True, timeout=30)
    assert result.returncode != 0
    assert "HOST:PORT" in result.stderr
    assert "Traceback" not in result.stderr
