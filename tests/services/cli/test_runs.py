"""`fleet runs ls|show`, `fleet download`, `fleet view` against a real service."""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from click.testing import CliRunner

from core.timefmt import timeline_value
from services.rrd import ArrowMessage, StoreKind, iter_events
from services.rrd.chunk import chunk_meta
from tests.services.ingest.live_server import FLEET, LiveServer
from tests.services.rrd.recordings import Recording

pytestmark = pytest.mark.sdk


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory, recordings: dict[str, Recording]) -> Iterator[LiveServer]:
    live = LiveServer(Path(tmp_path_factory.mktemp("cli-runs")) / "data").start()
    for name in ("points", "transforms"):
        assert httpx.post(f"{live.url}/v1/uploads", content=recordings[name].data, timeout=60).status_code == 200
    yield live
    live.stop()


def fleet(server: LiveServer, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([FLEET, *args, "--api-url", server.url], capture_output=True, text=True, timeout=120)


def test_runs_ls_and_show(server: LiveServer, recordings: dict[str, Recording]):
    points = recordings["points"].recordings[0]["recording_id"]
    table = fleet(server, "runs", "ls")
    assert table.returncode == 0 and points in table.stdout
    listed = json.loads(fleet(server, "runs", "ls", "--json", "--entity", "/world/**").stdout)
    assert points in {r["id"] for r in listed["runs"]}
    shown = fleet(server, "runs", "show", points)
    assert shown.returncode == 0 and "/world" in shown.stdout
    assert json.loads(fleet(server, "runs", "show", points, "--json").stdout)["id"] == points
    missing = fleet(server, "runs", "show", "no-such-run")
    assert missing.returncode == 1 and len(missing.stderr.strip().splitlines()) == 1
    assert "no run 'no-such-run'" in missing.stderr


def test_download_with_filters(server: LiveServer, recordings: dict[str, Recording], tmp_path: Path, rerun_bin: str):
    run_id = recordings["points"].recordings[0]["recording_id"]
    out = tmp_path / "part.rrd"
    result = fleet(server, "download", run_id, "-o", str(out), "--include", "/world/**")
    assert result.returncode == 0, result.stderr
    paths = {
        chunk_meta(e).entity_path
        for e in iter_events(out)
        if isinstance(e, ArrowMessage) and e.store_id.kind == StoreKind.RECORDING
    }
    assert "/__properties" in paths  # the recording's properties stay unless excluded
    assert all(p == "/world" or p.startswith(("/world/", "/__properties")) for p in paths - {"/__properties"})
    assert any(p.startswith("/world/") for p in paths)
    assert subprocess.run([rerun_bin, "rrd", "verify", str(out)], capture_output=True).returncode == 0


def test_view_prints_the_rerun_command(server: LiveServer, recordings: dict[str, Recording]):
    run_id = recordings["points"].recordings[0]["recording_id"]
    result = fleet(server, "view", run_id, "--include", "/world/**")
    assert result.returncode == 0
    exe, url = shlex.split(result.stdout)
    assert Path(exe).name == "rerun" and url.endswith(f"/v1/runs/{run_id}/recording.rrd?include=%2Fworld%2F%2A%2A")


def test_runs_show_prints_times_as_people_read_them(server: LiveServer, recordings: dict[str, Recording]):
    run_id = recordings["points"].recordings[0]["recording_id"]
    run = json.loads(fleet(server, "runs", "show", run_id, "--json").stdout)
    types = {t["name"]: t["type"] for t in run["timelines"]}
    assert types["frame"] == "sequence" and types["sim"] == "duration" and types["log_time"] == "timestamp"
    out = fleet(server, "runs", "show", run_id).stdout
    rows = {
        line.split()[0]: line.split()[1:]
        for line in out.splitlines()
        if line.split()[:1] in (["frame"], ["sim"], ["log_time"])
    }
    assert rows["frame"] == ["sequence", "100", "105"]
    assert rows["sim"] == ["duration", "0s", "1.25s"]  # 250 ms steps, not nanoseconds
    day = run["started_at"][:10]
    assert re.fullmatch(rf"{day}T\d\d:\d\d:\d\d\.\d{{9}}Z", rows["log_time"][1]), rows["log_time"]
    started = re.search(r"started (\S+ \S+ UTC)", out)
    assert started is not None and started.group(1).startswith(day), out
    start_time = run["properties"]["recording"]["RecordingInfo:start_time"]  # epoch ns: a date, as in the console
    assert f"RecordingInfo:start_time={timeline_value('timestamp', start_time)}" in out, out
    assert str(start_time) not in out


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--timeline", "nonsense", "--start", "1"], "'nonsense' is not a timeline of this run"),
        (["--timeline", "frame", "--start", "yesterday"], "'yesterday' is not a sequence value"),
        (["--timeline", "log_time", "--start", "2026-13-45"], "is not a timestamp value"),
        (["--timeline", "frame", "--start", "5", "--end", "1"], "is before start"),
    ],
)
def test_view_refuses_what_the_service_would_refuse(
    server: LiveServer, recordings: dict[str, Recording], args: list[str], message: str
):
    run_id = recordings["points"].recordings[0]["recording_id"]
    result = fleet(server, "view", run_id, *args)
    assert result.returncode == 1 and result.stdout == ""  # no URL printed
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], result.stderr


def test_view_of_an_unknown_run_is_one_line(server: LiveServer):
    result = fleet(server, "view", "no-such-run")
    assert result.returncode == 1 and result.stdout == ""
    assert "no run 'no-such-run'" in result.stderr and len(result.stderr.strip().splitlines()) == 1


VENV_RERUN = Path(sys.executable).parent / "rerun"


def test_view_prints_a_rerun_command_that_works_without_activating_the_venv(
    server: LiveServer, recordings: dict[str, Recording]
):
    run_id = recordings["points"].recordings[0]["recording_id"]
    assert VENV_RERUN.is_file()
    bare = {**os.environ, "PATH": "/usr/bin:/bin"}  # the venv not activated: no `rerun` on PATH
    printed = subprocess.run(
        [FLEET, "view", run_id, "--api-url", server.url], env=bare, capture_output=True, text=True, timeout=120
    )
    assert printed.returncode == 0, printed.stderr
    assert shlex.split(printed.stdout)[0] == str(VENV_RERUN)
    activated = {**os.environ, "PATH": f"{VENV_RERUN.parent}:/usr/bin:/bin"}
    printed = subprocess.run(
        [FLEET, "view", run_id, "--api-url", server.url], env=activated, capture_output=True, text=True, timeout=120
    )
    assert shlex.split(printed.stdout)[0] == "rerun"


def test_view_open_runs_the_rerun_of_its_own_venv(
    server: LiveServer, recordings: dict[str, Recording], monkeypatch: pytest.MonkeyPatch
):
    """`--open` finds the viewer installed beside `fleet` even when PATH has none (the viewer
    itself is not started here: the call that would start it records what it was asked to run)."""
    from services.cli import runs as runs_cli

    run_id = recordings["points"].recordings[0]["recording_id"]
    monkeypatch.setenv("PATH", "/usr/bin:/bin")
    started: list[list[str]] = []

    def call(argv: list[str]) -> int:
        started.append(argv)
        return 0

    monkeypatch.setattr(subprocess, "call", call)
    result = CliRunner().invoke(runs_cli.view, [run_id, "--open", "--api-url", server.url])
    assert result.exit_code == 0, result.output
    assert started == [[str(VENV_RERUN), f"{server.url}/v1/runs/{run_id}/recording.rrd"]]


def test_download_and_view_warn_of_a_filter_that_matches_no_entity(
    server: LiveServer, recordings: dict[str, Recording], tmp_path: Path
):
    run_id = recordings["points"].recordings[0]["recording_id"]
    warning = "warning: exclude /world matches no entity of the run (its subtree is /world/**)"
    got = fleet(server, "download", run_id, "-o", str(tmp_path / "run.rrd"), "--exclude", "/world")
    assert got.returncode == 0 and warning in got.stderr, got.stderr
    got = fleet(server, "view", run_id, "--exclude", "/world")
    assert got.returncode == 0 and warning in got.stderr and "warning" not in got.stdout, got.stderr
    got = fleet(server, "download", run_id, "-o", str(tmp_path / "run.rrd"), "--exclude", "/world/**")
    assert got.returncode == 0 and "warning" not in got.stderr, got.stderr
