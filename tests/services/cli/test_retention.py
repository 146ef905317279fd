"""`fleet retention plan|run`, `fleet runs pin|restore`, `fleet catalog rebuild` against a real service."""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from tests.services.ingest.live_server import FLEET, LiveServer
from tests.services.rrd.recordings import Recording, rerun_rrd_ok

pytestmark = pytest.mark.sdk


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    """Embedded defaults; no scheduler, so nothing moves unless a command asks for it."""
    live = LiveServer(
        Path(tmp_path_factory.mktemp("cli-retention")) / "data", scheduler="false", promote_after_s="0"
    ).start()
    yield live
    live.stop()


def fleet(server: LiveServer, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([FLEET, *args, "--api-url", server.url], capture_output=True, text=True, timeout=120)


def run_json(server: LiveServer, run_id: str) -> dict[str, Any]:
    answer = httpx.get(f"{server.url}/v1/runs/{run_id}", timeout=10)
    assert answer.status_code == 200, answer.text
    body: dict[str, Any] = answer.json()
    return body


def test_plan_then_run_promotes_with_progress(
    server: LiveServer, recordings: dict[str, Recording], tmp_path: Path, rerun_bin: str
):
    rec = recordings["points"]
    run_id = rec.recordings[0]["recording_id"]
    uploaded = subprocess.run(
        [FLEET, "upload", str(rec.path), "--api-url", server.url], capture_output=True, text=True, timeout=120
    )
    assert uploaded.returncode == 0 and f"runs {run_id}" in uploaded.stdout, uploaded.stderr

    plan = fleet(server, "retention", "plan")
    assert plan.returncode == 0, plan.stderr
    row = next(line for line in plan.stdout.splitlines() if run_id in line)
    assert row.split()[0] == "promote" and "hot" in row.split()
    assert "closed and idle for" in row and "(promote after 0m00s)" in row  # the reason, as the service gives it

    as_json = json.loads(fleet(server, "retention", "plan", "--json").stdout)
    (action,) = [a for a in as_json["actions"] if a["run"] == run_id]
    assert action["action"] == "promote" and action["tier"] == "hot" and action["bytes"] > 0
    assert action["reason"].startswith("closed and idle for")
    assert fleet(server, "retention", "plan", "--action", "archive").stdout.strip() == "nothing is due"

    done = fleet(server, "retention", "run")
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "1 done, 0 failed"
    assert f"ok promote {run_id}: sealed" in done.stderr  # one progress line per run

    warm = fleet(server, "runs", "ls", "--tier", "warm")
    assert warm.returncode == 0 and run_id in warm.stdout
    assert run_id not in fleet(server, "runs", "ls", "--tier", "hot").stdout
    assert fleet(server, "retention", "plan").stdout.strip() == "nothing is due"
    again = fleet(server, "retention", "run")
    assert again.returncode == 0 and again.stdout.strip() == "0 done, 0 failed"

    # what the warm tier serves is the recording that was uploaded
    out = tmp_path / "warm.rrd"
    assert fleet(server, "download", run_id, "-o", str(out)).returncode == 0
    rerun_rrd_ok(rerun_bin, "compare", "--unordered", rec.path, out)


def _sealed(server: LiveServer, rec: Recording) -> str:
    """Upload and promote one recording; its run id."""
    run_id: str = rec.recordings[0]["recording_id"]
    assert httpx.post(f"{server.url}/v1/uploads", content=rec.data, timeout=60).status_code == 200
    assert fleet(server, "retention", "run", "--action", "promote").returncode == 0
    assert run_json(server, run_id)["tier"] == "warm"
    return run_id


def test_pin_and_unpin(server: LiveServer, recordings: dict[str, Recording]):
    run_id = _sealed(server, recordings["scalars"])
    pinned = fleet(server, "runs", "pin", run_id)
    assert pinned.returncode == 0, pinned.stderr
    assert pinned.stdout.startswith(f"{run_id}: pinned by ") and "@" in pinned.stdout
    shown = run_json(server, run_id)
    assert shown["pinned"] is True and shown["lifecycle"]["pinned_by"] == pinned.stdout.split(" by ")[1].strip()
    assert [e["action"] for e in shown["events"]][-1] == "pin"
    # the sealed run's own record says so too (what a catalog rebuild reads)
    prefix = shown["lifecycle"]["prefix"]
    assert json.loads((server.data_dir / "warm" / prefix / "run.json").read_text())["pinned"] is True

    unpinned = fleet(server, "runs", "pin", run_id, "--unpin")
    assert unpinned.returncode == 0 and unpinned.stdout.startswith(f"{run_id}: unpinned by ")
    shown = run_json(server, run_id)
    assert shown["pinned"] is False and shown["lifecycle"]["pinned_by"] is None
    assert json.loads((server.data_dir / "warm" / prefix / "run.json").read_text())["pinned"] is False


def test_restore_of_a_warm_run_is_one_clear_line(server: LiveServer, recordings: dict[str, Recording]):
    run_id = _sealed(server, recordings["textlogs"])
    result = fleet(server, "runs", "restore", run_id)
    assert result.returncode == 1
    assert len(result.stderr.strip().splitlines()) == 1, result.stderr
    assert result.stderr.startswith("Error: ") and "is warm, not cold" in result.stderr
    assert "Traceback" not in result.stderr
    missing = fleet(server, "runs", "pin", "no-such-run")
    assert missing.returncode == 1 and len(missing.stderr.strip().splitlines()) == 1
    assert "no-such-run" in missing.stderr


def test_rebuild_on_a_populated_catalog_adds_nothing(server: LiveServer, recordings: dict[str, Recording]):
    _sealed(server, recordings["transforms"])
    sealed = [r for r in httpx.get(f"{server.url}/v1/runs", timeout=10).json()["runs"] if r["tier"] != "hot"]
    result = fleet(server, "catalog", "rebuild")
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == f"0 runs added, {len(sealed)} already present, 0 skipped"
    assert all(f"ok present {r['id']}: already in the catalog" in result.stderr for r in sealed)


def test_plan_says_when_hot_runs_will_be_promoted_and_promote_seals_one_now(
    tmp_path: Path, recordings: dict[str, Recording]
):
    live = LiveServer(tmp_path / "data", scheduler="false", promote_after_s="600").start()
    try:
        uploaded = httpx.post(f"{live.url}/v1/uploads", content=recordings["points"].path.read_bytes(), timeout=60)
        run_id = uploaded.json()["runs"][0]
        plan = fleet(live, "retention", "plan")
        assert plan.returncode == 0, plan.stderr
        assert "nothing is due" in plan.stdout and "later:" in plan.stdout
        assert run_id in plan.stdout and " UTC" in plan.stdout and "idle" in plan.stdout
        done = fleet(live, "runs", "promote", run_id)
        assert done.returncode == 0, done.stderr
        assert done.stdout.startswith(f"{run_id}: warm: sealed ")
        assert run_json(live, run_id)["tier"] == "warm"
        again = fleet(live, "runs", "promote", run_id)  # one line, exit 1
        assert again.returncode == 1 and again.stderr.count("\n") == 1 and "warm already" in again.stderr
    finally:
        live.stop()


def test_scrub_secrets_finds_nothing_in_runs_filed_today(server: LiveServer, recordings: dict[str, Recording]):
    """What ingest files now holds no secret-like field: a dry run and a scrub say every hot and
    warm run is clean and change nothing (the finding and rewriting are tested in tests/services/retention)."""
    _sealed(server, recordings["properties"])
    runs = [r for r in httpx.get(f"{server.url}/v1/runs", timeout=10).json()["runs"] if r["tier"] in ("hot", "warm")]
    for args in (("--dry-run",), ()):
        result = fleet(server, "catalog", "scrub-secrets", *args)
        assert result.returncode == 0, result.stderr
        assert result.stdout.strip() == f"0 runs scrubbed, 0 found (dry run), {len(runs)} clean, 0 skipped"
        assert all(f"ok clean {r['id']} ({r['tier']}): no secret-like property field" in result.stderr for r in runs)


SITE_KEY = "SITEKEY-SCRUBME-789"


def test_scrub_secrets_removes_a_field_made_secret_after_its_runs_were_filed(tmp_path: Path, rerun_bin: str):
    """Runs filed before a field counted as secret (FLEET_SECRET_FIELDS widened later, as rerun-sdk
    0.23 tokens were filed before ingest read that SDK's field metadata): the scrub finds the field
    without printing it, seals the run again without it, and a download no longer holds it, from
    the recording or the run's properties; `rerun rrd verify` accepts the download; a second scrub
    finds nothing."""
    from tests.services.retention.test_scrub import chunk_bodies

    source, run_id = tmp_path / "site.rrd", "scrub-site-run"
    script = f"""
import rerun as rr
rr.init("scrub_site", recording_id={run_id!r}, spawn=False)
rr.save({str(source)!r})
rr.send_property("site", rr.AnyValues(site_key={SITE_KEY!r}, site_name="lab"))
for i in range(3):
    rr.set_time("frame", sequence=i)
    rr.log("/world/points", rr.Points3D([[i, 0, 0]]))
"""
    subprocess.run([sys.executable, "-c", script], check=True, timeout=120)
    data = tmp_path / "data"
    before = LiveServer(data, scheduler="false", promote_after_s="0", secret_fields="password").start()
    try:
        assert httpx.post(f"{before.url}/v1/uploads", content=source.read_bytes(), timeout=60).status_code == 200
        assert fleet(before, "runs", "promote", run_id).returncode == 0
        assert SITE_KEY in json.dumps(run_json(before, run_id))  # filed as sent
    finally:
        before.stop()
    live = LiveServer(data, scheduler="false", promote_after_s="0", secret_fields="password,site_key").start()
    try:
        held = tmp_path / "held.rrd"
        assert fleet(live, "download", run_id, "-o", str(held)).returncode == 0
        assert any(SITE_KEY.encode() in body for body in chunk_bodies(held).values())

        dry = fleet(live, "catalog", "scrub-secrets", "--dry-run")
        assert dry.returncode == 0, dry.stderr
        assert f"ok found {run_id} (warm): secret-like fields in 1 property chunks (site)" in dry.stderr
        assert SITE_KEY not in dry.stdout + dry.stderr and dry.stdout.startswith("0 runs scrubbed, 1 found")

        done = fleet(live, "catalog", "scrub-secrets")
        assert done.returncode == 0, done.stderr
        assert f"ok scrubbed {run_id} (warm)" in done.stderr and done.stdout.startswith("1 runs scrubbed")
        got = tmp_path / "got.rrd"
        assert fleet(live, "download", run_id, "-o", str(got)).returncode == 0
        bodies, kept = chunk_bodies(got), chunk_bodies(held)
        assert set(bodies) == set(kept) and not any(SITE_KEY.encode() in body for body in bodies.values())
        assert sum(bodies[c] != kept[c] for c in kept) == 1 and any(b"lab" in body for body in bodies.values())
        rerun_rrd_ok(rerun_bin, "verify", got)
        page = run_json(live, run_id)
        assert SITE_KEY not in json.dumps(page) and page["properties"]["site"] == {"site_name": "lab"}

        again = fleet(live, "catalog", "scrub-secrets")
        assert again.returncode == 0 and again.stdout.startswith("0 runs scrubbed, 0 found"), again.stderr
    finally:
        live.stop()
