"""The viewer page's status line follows the Rerun web viewer (static/viewer.js): "ready" when the
viewer started, "loaded" once it says it opened the run. Run in Node with a stand-in for the page
and for the viewer's widget.js that sends what the real one sends (its "ready", then its events as
JSON); the browser test (test_viewer.py) checks the same against the real viewer."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest

from services.console.web import static_dir

HARNESS = """
const events = %(events)s;
const element = { dataset: { url: "/v1/runs/r/recording.rrd?sig=x", widget: %(widget)s }, clientHeight: 600 };
const status = { textContent: "Starting the Rerun web viewer…" };
globalThis.document = {
  baseURI: "http://127.0.0.1/console/runs/r/viewer",
  getElementById: (id) => (id === "viewer" ? element : id === "viewer-status" ? status : null),
};
globalThis.__events = events;
await import(%(script)s);
await new Promise((done) => setTimeout(done, 50));
console.log(JSON.stringify({ state: element.dataset.state, status: status.textContent }));
"""

WIDGET = """
export default {
  render({ model }) {
    // as the real viewer: "ready" once its wasm has started, its events after that
    setTimeout(() => globalThis.__events.forEach((event) => model.send(event)), 0);
  },
};
"""


def page_after(tmp_path: Path, events: list[str]) -> dict[str, str]:
    node = shutil.which("node")
    if node is None:
        pytest.skip("node is not installed: the browser test checks the viewer page's status")
    widget = tmp_path / "widget.mjs"
    widget.write_text(WIDGET)
    harness = tmp_path / "harness.mjs"
    script = (Path(static_dir()) / "viewer.js").as_uri()
    harness.write_text(
        HARNESS % {"events": json.dumps(events), "widget": json.dumps(widget.as_uri()), "script": json.dumps(script)}
    )
    done = subprocess.run([node, str(harness)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    answer: dict[str, str] = json.loads(done.stdout.strip().splitlines()[-1])
    return answer


def test_the_status_says_loaded_once_the_viewer_opened_the_run(tmp_path: Path) -> None:
    opened = json.dumps({"type": "recording_open", "recording_id": "r", "source": "http"})
    page = page_after(tmp_path, ["ready", json.dumps({"type": "play"}), opened])
    assert page["state"] == "loaded"
    assert "loading" not in page["status"].lower() and "loaded" in page["status"].lower()


def test_until_then_it_says_it_is_loading(tmp_path: Path) -> None:
    page = page_after(tmp_path, ["ready", json.dumps({"type": "selection_change"}), "not json"])
    assert page["state"] == "ready"
    assert "loading the run" in page["status"]
