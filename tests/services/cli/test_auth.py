"""The CLI against a real `fleet serve` with auth on: the admin token found beside the service,
`fleet tokens create|ls|revoke`, refusals in one line, and `fleet view`'s signed links opened by
the real `rerun` with no header."""

from __future__ import annotations

import datetime as dt
import json
import os
import shlex
import stat
import subprocess
from collections.abc import Iterator
from pathlib import Path
from urllib.parse import parse_qsl, urlencode, urlsplit

import httpx
import pytest

from services.rrd import ArrowMessage, StoreKind, iter_events
from services.rrd.chunk import chunk_meta
from tests.services.ingest.live_server import FLEET, LiveServer
from tests.services.rrd.recordings import Recording
from tests.subprocess_server import free_port

pytestmark = pytest.mark.sdk


@pytest.fixture(scope="module")
def depot(tmp_path_factory: pytest.TempPathFactory, recordings: dict[str, Recording]) -> Iterator[LiveServer]:
    """A depot with auth on (revocations seen at once), its data dir named as by default, holding
    the `points` recording (uploaded by the CLI with the admin token it finds in the data dir)."""
    home = tmp_path_factory.mktemp("cli-auth")
    live = LiveServer(home / "fleet-data", auth="on", auth_cache_s="0").start()
    try:
        uploaded = fleet(live, "upload", str(recordings["points"].path), env=as_admin(live))
        assert uploaded.returncode == 0, uploaded.stderr
        yield live
    finally:
        live.stop()


@pytest.fixture
def run_id(recordings: dict[str, Recording]) -> str:
    return str(recordings["points"].recordings[0]["recording_id"])


def fleet(
    live: LiveServer, *args: str, env: dict[str, str] | None = None, cwd: Path | None = None
) -> subprocess.CompletedProcess[str]:
    """`fleet ARGS` with no token but what `env` gives, run in an empty folder unless `cwd` (so no
    ./fleet-data is found by chance)."""
    clean = {k: v for k, v in os.environ.items() if k not in ("FLEET_TOKEN", "FLEET_DATA_DIR")}
    if cwd is None:
        cwd = live.data_dir.parent / "elsewhere"
        cwd.mkdir(exist_ok=True)
    return subprocess.run(
        [FLEET, *args],
        env={**clean, "FLEET_API_URL": live.url, **(env or {})},
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=120,
    )


def as_admin(live: LiveServer) -> dict[str, str]:
    return {"FLEET_DATA_DIR": str(live.data_dir)}


def one_line(result: subprocess.CompletedProcess[str]) -> str:
    assert result.returncode == 1 and result.stdout == "", result.stdout + result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    return lines[0]


def test_first_start_writes_the_admin_token_and_keeps_it_out_of_the_log(depot: LiveServer):
    path = depot.data_dir / "admin.token"
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    token = path.read_text().strip()
    log = depot.log.read_text()  # fleet serve's stdout and stderr, not a terminal: a log
    assert token not in log and token.rsplit(".", 1)[1] not in log
    assert log.count("first start") == 1 and str(path) in log  # where to find it instead
    depot.stop()
    depot.start()  # a second start: the token stays where it is, and nothing is said of it again
    assert path.read_text().strip() == token
    log = depot.log.read_text()
    assert token not in log and log.count("first start") == 1


def test_a_command_beside_the_service_finds_the_admin_token(depot: LiveServer, run_id: str):
    by_default = fleet(depot, "runs", "ls", cwd=depot.data_dir.parent)  # ./fleet-data, as `fleet serve` uses
    assert by_default.returncode == 0 and run_id in by_default.stdout, by_default.stderr
    named = fleet(depot, "runs", "ls", env=as_admin(depot))
    assert named.returncode == 0 and run_id in named.stdout, named.stderr


def test_without_a_token_every_command_says_so_in_one_line(depot: LiveServer, recordings: dict[str, Recording]):
    for args in (["runs", "ls"], ["tokens", "ls"], ["upload", str(recordings["points"].path)]):
        line = one_line(fleet(depot, *args))
        assert "FLEET_TOKEN" in line and "fleet tokens create" in line


def test_a_read_token_reads_refuses_admin_work_and_ends_when_revoked(
    depot: LiveServer, run_id: str, tmp_path: Path, rerun_bin: str
):
    admin = as_admin(depot)
    created = fleet(depot, "tokens", "create", "--scope", "read", "--name", "alice", "--expires", "1h", env=admin)
    assert created.returncode == 0, created.stderr
    token = created.stdout.strip()
    assert created.stdout == token + "\n"  # alone on stdout: TOKEN=$(fleet tokens create ...)
    (summary,) = created.stderr.strip().splitlines()
    assert "shown once" in summary and "read" in summary and token not in summary

    alice = {"FLEET_TOKEN": token, **admin}  # FLEET_TOKEN wins over the admin token file
    listed = fleet(depot, "runs", "ls", env=alice)
    assert listed.returncode == 0 and run_id in listed.stdout, listed.stderr
    out = tmp_path / "run.rrd"
    downloaded = fleet(depot, "download", run_id, "-o", str(out), env=alice)  # the header, no link
    assert downloaded.returncode == 0, downloaded.stderr
    assert subprocess.run([rerun_bin, "rrd", "verify", str(out)], capture_output=True).returncode == 0
    assert "'admin'" in one_line(fleet(depot, "runs", "rm", run_id, "--yes", env=alice))

    table = fleet(depot, "tokens", "ls", env=admin)
    assert table.returncode == 0 and "alice" in table.stdout
    answer = json.loads(fleet(depot, "tokens", "ls", "--json", env=admin).stdout)
    assert token not in table.stdout + table.stderr + json.dumps(answer)
    (record,) = [t for t in answer["tokens"] if t["subject"] == "alice"]
    assert record["id"] in table.stdout and record["scopes"] == ["read"] and record["revoked_at"] is None
    lifetime = dt.datetime.fromisoformat(record["expires_at"]) - dt.datetime.fromisoformat(record["created_at"])
    assert lifetime == dt.timedelta(hours=1)

    revoked = fleet(depot, "tokens", "revoke", record["id"], env=admin)
    assert revoked.returncode == 0 and "revoked" in revoked.stdout, revoked.stderr
    refused = one_line(fleet(depot, "runs", "ls", env=alice))  # FLEET_AUTH_CACHE_S=0: at once
    assert "revoked" in refused and "FLEET_TOKEN" in refused and "fleet tokens create" in refused
    assert record["id"] not in fleet(depot, "tokens", "ls", env=admin).stdout
    assert record["id"] in fleet(depot, "tokens", "ls", "--all", env=admin).stdout


def save_with_rerun(rerun_bin: str, url: str, out: Path) -> subprocess.CompletedProcess[str]:
    """`rerun --save OUT URL`: the real viewer's loader, no window; its own gRPC port a free loopback one."""
    return subprocess.run(
        [rerun_bin, "--save", str(out), "--bind", "127.0.0.1", "--port", str(free_port()), url],
        capture_output=True,
        text=True,
        timeout=120,
    )


def recording_entities(path: Path) -> set[str]:
    """The entity paths of the recording chunks a file holds (none if there is no file)."""
    if not path.exists():
        return set()
    return {
        chunk_meta(e).entity_path
        for e in iter_events(path)
        if isinstance(e, ArrowMessage) and e.store_id.kind == StoreKind.RECORDING
    }


def with_param(url: str, name: str, value: str | None = None, add: str | None = None) -> str:
    """`url` with parameter `name` set to `value`, or another `name=add` added."""
    parts = urlsplit(url)
    params = parse_qsl(parts.query)
    params = [(k, value if k == name and value is not None else v) for k, v in params]
    if add is not None:
        params.append((name, add))
    return parts._replace(query=urlencode(params)).geturl()


def test_view_hands_out_a_signed_link_that_rerun_opens_and_tampering_breaks(
    depot: LiveServer, run_id: str, tmp_path: Path, rerun_bin: str
):
    viewed = fleet(depot, "view", run_id, "--include", "/world/**", "--expires", "30m", env=as_admin(depot))
    assert viewed.returncode == 0, viewed.stderr
    _, url = shlex.split(viewed.stdout)
    params = dict(parse_qsl(urlsplit(url).query))
    assert {"sig", "expires", "by"} <= params.keys() and params["include"] == "/world/**"
    assert abs(int(params["expires"]) - (dt.datetime.now(dt.UTC).timestamp() + 1800)) < 120
    (said,) = viewed.stderr.strip().splitlines()
    assert "signed link" in said and "UTC" in said

    saved = tmp_path / "saved.rrd"
    opened = save_with_rerun(rerun_bin, url, saved)
    assert opened.returncode == 0, opened.stderr
    verified = subprocess.run([rerun_bin, "rrd", "verify", str(saved)], capture_output=True, text=True)
    assert verified.returncode == 0 and "1 file verified" in verified.stdout + verified.stderr
    entities = recording_entities(saved)
    assert any(p.startswith("/world/") for p in entities)
    assert all(p.startswith(("/world", "/__properties")) for p in entities)
    served = [line for line in depot.log.read_text().splitlines() if f"/v1/runs/{run_id}/recording.rrd" in line]
    assert served and params["sig"] not in depot.log.read_text()  # the access log shows the link without it

    for tampered in (with_param(url, "include", add="/x"), with_param(url, "expires", str(int(params["expires"]) + 1))):
        assert httpx.get(tampered, timeout=30).status_code == 403
        broken = tmp_path / "tampered.rrd"
        save_with_rerun(rerun_bin, tampered, broken)
        assert recording_entities(broken) == set()  # nothing of the run was served


def test_a_link_needs_no_header_but_the_plain_url_does(depot: LiveServer, run_id: str):
    viewed = fleet(depot, "view", run_id, env=as_admin(depot))
    _, url = shlex.split(viewed.stdout)
    assert httpx.get(url, timeout=30).status_code == 200
    assert httpx.get(f"{depot.url}/v1/runs/{run_id}/recording.rrd", timeout=30).status_code == 401


def test_view_follow_signs_a_link_that_follows_the_run(depot: LiveServer, run_id: str):
    viewed = fleet(depot, "view", run_id, "--follow", env=as_admin(depot))
    assert viewed.returncode == 0, viewed.stderr
    _, url = shlex.split(viewed.stdout)
    params = dict(parse_qsl(urlsplit(url).query))
    assert params["follow"] == "true" and "sig" in params
    answer = httpx.get(url, timeout=30)  # no header; the run is closed, so the stream ends
    assert answer.status_code == 200 and answer.content.startswith(b"RRF2")
    assert httpx.get(with_param(url, "follow", "false"), timeout=30).status_code == 403  # follow is signed too
