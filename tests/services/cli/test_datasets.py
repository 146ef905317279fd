"""`fleet datasets create|ls|show` and `fleet runs rm --force` against the app in this process (the
REST client the commands open is the test's): what --event means with and without a window, the
tables and JSON printed, a used run's delete refused then forced."""

from __future__ import annotations

import contextlib
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import click
import pytest
from click.testing import CliRunner

from sdk_client.rest import FleetClient
from services.cli.datasets import selection_body
from services.cli.main import cli
from tests.services.auth.conftest import Depot
from tests.services.corpus.conftest import sdk
from tests.services.datasets.conftest import depot, upload, writer

__all__ = ["depot"]  # the datasets suites' fixture, used here as is


def test_event_with_a_window_names_the_windows_events():
    windowed = selection_body(event=("intervention",), before=5.0, after=2.0)
    assert windowed["event_window"] == {"event": ["intervention"], "before_s": 5.0, "after_s": 2.0}
    assert windowed["event"] == []
    plain = selection_body(event=("intervention",))
    assert "event_window" not in plain and plain["event"] == ["intervention"]
    both = selection_body(event=("bump",), window_event=("grasp",), after=1.0)
    assert both["event_window"]["event"] == ["grasp", "bump"] and both["event"] == []
    filtered = selection_body(event=("bump",), window_event=("grasp",))
    assert filtered["event_window"]["event"] == ["grasp"] and filtered["event"] == ["bump"]
    with pytest.raises(click.UsageError, match="--event KIND"):
        selection_body(before=5.0)


def test_split_and_properties_are_parsed():
    body = selection_body(split_text="train=0.9,val=0.1", prop=("fleet.robot_id=robot-7",), seed=4)
    assert body["split"] == {"train": 0.9, "val": 0.1} and body["seed"] == 4
    assert body["properties"] == {"fleet.robot_id": "robot-7"}


def _run(monkeypatch: pytest.MonkeyPatch, fleet: FleetClient, *args: str) -> Any:
    @contextlib.contextmanager
    def same(api_url: str) -> Iterator[FleetClient]:
        yield fleet

    for module in ("services.cli.datasets", "services.cli.runs", "services.cli.dataset_exports"):
        monkeypatch.setattr(f"{module}.client", same)
    return CliRunner().invoke(cli, list(args), terminal_width=200)


def test_create_ls_show(depot: Depot, monkeypatch: pytest.MonkeyPatch):
    upload(depot, "run-a")
    upload(depot, "run-b")
    alice = writer(depot)
    alice.annotate("run-a", "frame", 600, kind="intervention")
    made = _run(monkeypatch, alice, "datasets", "create", "picks", "--event", "intervention", "--before", "5",
                "--after", "2", "--include", "/robot/**", "--split", "train=0.5,val=0.5", "--seed", "1")  # fmt: skip
    assert made.exit_code == 0, made.output
    assert made.output.startswith("picks@1: 1 episodes from 1 runs")
    whole = _run(monkeypatch, alice, "datasets", "create", "picks", "--json")
    assert whole.exit_code == 0 and json.loads(whole.output)["ref"] == "picks@2"

    listed = _run(monkeypatch, alice, "datasets", "ls")
    assert listed.exit_code == 0 and "picks@2" in listed.output, listed.output
    versions = _run(monkeypatch, alice, "datasets", "show", "picks")
    assert "picks@1" in versions.output and "picks@2" in versions.output
    one = _run(monkeypatch, alice, "datasets", "show", "picks@1")
    assert one.exit_code == 0, one.output
    assert "run-a" in one.output and "595" in one.output and "602" in one.output and "run-b" not in one.output
    shown = json.loads(_run(monkeypatch, alice, "datasets", "show", "picks@1", "--json").output)
    assert shown["selection"]["event_window"] == {"event": ["intervention"], "before_s": 5.0, "after_s": 2.0}
    bad = _run(monkeypatch, alice, "datasets", "show", "picks@x")
    assert bad.exit_code != 0 and "'version'" in str(bad.exception)


def test_runs_rm_refuses_a_used_run_then_forces(depot: Depot, monkeypatch: pytest.MonkeyPatch):
    upload(depot, "run-a", seal=True)
    writer(depot).create_dataset("picks")
    admin = sdk(depot, depot.token("admin"))
    refused = _run(monkeypatch, admin, "runs", "rm", "run-a", "--yes")
    assert refused.exit_code != 0 and "used by dataset picks@1" in str(refused.exception)
    forced = _run(monkeypatch, admin, "runs", "rm", "run-a", "--yes", "--force")
    assert forced.exit_code == 0, forced.output
    assert writer(depot).dataset_version("picks", 1)["episodes_page"][0]["missing"] is True


def test_export_to_a_folder_and_as_the_depot_s_job(depot: Depot, monkeypatch: pytest.MonkeyPatch, tmp_path: Path):
    from tests.services.datasets.test_export import snapshot

    snapshot(depot, tmp_path, ["run-a"])
    alice = writer(depot)
    options = ("--observation", "/joints", "--action", "/cmd", "--camera", "/camera/front=observation.images.front")
    here = _run(monkeypatch, alice, "datasets", "export", "drives@1", "--to", str(tmp_path / "out"), *options)
    assert here.exit_code == 0, here.output
    assert "1 of 1 episodes exported, 30 frames" in here.output and "hot_run" in here.output
    assert json.loads((tmp_path / "out" / "meta" / "info.json").read_text())["total_frames"] == 30
    bad = _run(monkeypatch, alice, "datasets", "export", "drives@1", "--to", str(tmp_path / "x"), "--camera", "front")
    assert bad.exit_code == 2 and "ENTITY=observation.images.NAME" in bad.output
    refused = _run(monkeypatch, alice, "datasets", "export", "drives@1", "--to", "s3://b/p", *options)
    assert "FLEET_EXPORT_URLS" in str(refused.exception)  # `fleet` prints it as one line (services.cli.main)
    listed = _run(monkeypatch, alice, "datasets", "exports", "--json")
    assert listed.exit_code == 0 and json.loads(listed.output) == []
