"""The shell and Python examples of README.md and docs/*.md, run as written against a real
`fleet serve` with auth on, so the docs cannot drift from the product.

Every fenced ```sh and ```python block is an example that must run. A block that needs what a test
cannot have (a robot, docker, kubernetes, a viewer window) says so in the doc, on the line before
its fence: `<!-- not-run: needs docker -->`; it is reported as skipped with that reason.

The blocks see the depot a reader of the README has after the quick start: the current directory
holds `fleet-data/` (the server's data dir, with its `admin.token`), `FLEET_API_URL` and
`FLEET_TOKEN` (the admin token) are set, and the runs the examples name are in it
(`run-2026-11-21-0001` of robot-7 with `/world/**` and a `log_time` timeline, `run-0042` of
`warehouse_bot` with `/robot/battery`, both sealed). The server listens on free ports, so the
default addresses the docs name (`localhost:8080`, `localhost:51234`) are pointed at it, and
`curl` runs with `--fail-with-body` so an error answer (a 401) fails the block.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx
import pytest

from tests.services.ingest.live_server import LiveServer

pytestmark = [pytest.mark.slow, pytest.mark.sdk]

ROOT = Path(__file__).resolve().parent.parent
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
LANGUAGES = {"sh": "sh", "python": "python"}
FENCE = re.compile(r"^(\s*)```(\w*)\s*$")
NOT_RUN = re.compile(r"^\s*<!--\s*not-run:(.*?)-->\s*$")
BLOCK_TIMEOUT_S = 60


@dataclass(frozen=True)
class Block:
    doc: str
    line: int  # of the opening fence, 1-based
    language: str
    code: str
    not_run: str | None  # the reason given in the doc, or None: the block runs

    @property
    def id(self) -> str:
        return f"{self.doc}:{self.line}"


def collect(path: Path) -> list[Block]:
    """The ```sh and ```python blocks of one Markdown file, each with its not-run reason if any."""
    lines = path.read_text().splitlines()
    blocks, i = [], 0
    while i < len(lines):
        fence = FENCE.match(lines[i])
        if fence is None:
            i += 1
            continue
        end = next(j for j in range(i + 1, len(lines)) if lines[j].strip().startswith("```"))
        if fence.group(2) in LANGUAGES:
            indent = len(fence.group(1))
            code = "\n".join(line[indent:] for line in lines[i + 1 : end]) + "\n"
            before = next((lines[k] for k in range(i - 1, -1, -1) if lines[k].strip()), "")
            marker = NOT_RUN.match(before)
            reason = marker.group(1).strip() if marker else None
            blocks.append(Block(str(path.relative_to(ROOT)), i + 1, fence.group(2), code, reason))
        i = end + 1
    return blocks


BLOCKS = [block for doc in DOCS for block in collect(doc)]

LOG_RUNS = """
import datetime as dt, sys
import rerun as rr
out, which = sys.argv[1], sys.argv[2]
if which == "nav":
    rr.init("nav", recording_id="run-2026-11-21-0001", spawn=False)
    rr.save(out)
    rr.send_property("fleet", rr.AnyValues(robot_id="robot-7"))
    t0 = dt.datetime(2026, 11, 21, 8, 14, tzinfo=dt.timezone.utc)
    for i in range(5):
        rr.set_time("log_time", timestamp=t0 + dt.timedelta(seconds=30 * i))
        rr.log("/world/camera/points", rr.Points3D([[i, 0, 0]]))
        rr.log("/world/robot", rr.Transform3D(translation=[i, 0, 0]))
        rr.log("/log", rr.TextLog("battery low" if i == 3 else "ok", level="ERROR" if i == 3 else "INFO"))
else:
    rr.init("warehouse_bot", recording_id="run-0042", spawn=False)
    rr.save(out)
    rr.send_property("fleet", rr.AnyValues(robot_id="robot-7"))
    for i in range(5):
        rr.set_time("frame", sequence=i)
        rr.log("/robot/battery", rr.Scalars(100.0 - i))
"""


RULES = """
[[metric]]
name = "distance_m"
kind = "path_length"
entity = "/world/robot"
"""


@dataclass(frozen=True)
class Depot:
    server: LiveServer
    cwd: Path
    env: dict[str, str]


@pytest.fixture(scope="module")
def depot(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Depot]:
    cwd = tmp_path_factory.mktemp("docs")
    server = LiveServer(cwd / "fleet-data", auth="on").start()
    try:
        token = (cwd / "fleet-data" / "admin.token").read_text().strip()
        headers = {"authorization": f"Bearer {token}"}
        # a metric the runs have from the start, as a depot with rules has (docs/catalog-server.md)
        answer = httpx.put(f"{server.url}/v1/rules", content=RULES, headers={**headers, "content-type": "text/plain"})
        assert answer.status_code == 200, answer.text
        for name in ("nav", "warehouse_bot"):
            rrd = cwd / f"{name}.rrd"
            subprocess.run([sys.executable, "-c", LOG_RUNS, str(rrd), name], check=True, timeout=120)
            answer = httpx.post(f"{server.url}/v1/uploads", content=rrd.read_bytes(), headers=headers, timeout=60)
            assert answer.status_code == 200, answer.text
        for run_id in ("run-2026-11-21-0001", "run-0042"):  # sealed: the SQL examples read the extracted tables
            answer = httpx.post(f"{server.url}/v1/runs/{run_id}/promote", headers=headers, timeout=120)
            assert answer.status_code == 200, answer.text
        shutil.copy(cwd / "nav.rrd", cwd / "robot.rrd")  # the file the `fleet rrd inspect` examples read
        yield Depot(server, cwd, _environment(cwd, server, token))
    finally:
        server.stop()


def _environment(cwd: Path, server: LiveServer, token: str) -> dict[str, str]:
    shims = cwd / "shims"
    shims.mkdir()
    curl = shims / "curl"  # an error answer fails the block, as a person reading it would see it fail
    curl.write_text(f'#!/bin/sh\nexec {shutil.which("curl")} --fail-with-body --silent --show-error "$@"\n')
    curl.chmod(0o755)
    env = {k: v for k, v in os.environ.items() if not k.startswith("FLEET_")}
    return {
        **env,
        "PATH": os.pathsep.join([str(shims), str(Path(sys.executable).parent), env.get("PATH", "")]),
        "PYTHONPATH": str(ROOT),
        "FLEET_API_URL": server.url,
        "FLEET_TOKEN": token,
    }


def _pointed_at(code: str, server: LiveServer) -> str:
    """The block with the docs' default addresses replaced by the test server's."""
    for host in ("localhost", "127.0.0.1"):
        code = code.replace(f"{host}:8080", f"{host}:{server.http_port}")
        code = code.replace(f"{host}:51234", f"{host}:{server.grpc_port}")
    return code


def test_every_example_is_found_and_every_skip_says_why():
    assert {b.doc for b in BLOCKS} >= {"README.md", "docs/analytics.md", "docs/catalog-server.md"}
    assert all(b.not_run != "" for b in BLOCKS), [b.id for b in BLOCKS if b.not_run == ""]
    assert [b for b in BLOCKS if b.not_run is None], "no runnable example left"


@pytest.mark.parametrize("block", BLOCKS, ids=[b.id for b in BLOCKS])
def test_doc_example_runs(block: Block, request: pytest.FixtureRequest):
    if block.not_run is not None:
        pytest.skip(f"{block.id}: not-run: {block.not_run}")
    depot: Depot = request.getfixturevalue("depot")  # only for a block that runs: a skip starts no server
    code = _pointed_at(block.code, depot.server)
    argv = ["bash", "-euo", "pipefail", "-c", code] if block.language == "sh" else [sys.executable, "-c", code]
    done = subprocess.run(argv, cwd=depot.cwd, env=depot.env, capture_output=True, text=True, timeout=BLOCK_TIMEOUT_S)
    assert done.returncode == 0, f"{block.id} failed:\n{code}\n--- stdout\n{done.stdout}\n--- stderr\n{done.stderr}"
