"""The SDK's dataframe reader against the depot: `ds.reader(index="frame")`, with segment and content
filters, time filters and latest-at fill, returns the rows Rerun's own dataframe API reads from the
robot's file (`rr.chunk.RrdReader(path)...reader(...)`), modulo the `rerun_segment_id` column.

The same SDK code runs against Rerun's own `rerun server` on the same files (which shows what the
test asks is what Rerun answers), and against a real `fleet serve` that received the files by upload
and sealed them. Reading from the depot needs the whole catalog service (entries, segment table,
FetchChunks) besides the query calls."""

from __future__ import annotations

import functools
import os
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx
import pyarrow as pa
import pyarrow.compute as pc
import pytest

from tests.compat.sdk_venvs import sdk_bin
from tests.services.ingest.live_server import LiveServer
from tests.services.redap.client import reference_serving

pytestmark = pytest.mark.sdk

DATASET = "fleet_e2e"
RUNS = ("e2e-robot-run-a", "e2e-robot-run-b")
FRAMES = 40
CONTENTS = ["/world/robot/**", "/robot/battery"]
ROBOT = Path(__file__).parents[1] / "ingest" / "robot.py"


def _log_robot(path: Path, run_id: str, frames: int) -> Path:
    """The robot's file: what robot.py logs each frame (transform, lidar, camera, battery, text
    log) over `frames` frames, a static map, chunks of seven rows (so a time filter and latest-at
    fill cut through an entity's chunks), written by the real SDK in a process of its own."""
    script = f"""
import sys
sys.path.insert(0, {str(ROBOT.parent)!r})
import rerun as rr
from robot import log_frame
rec = rr.RecordingStream({DATASET!r}, recording_id={run_id!r})
rec.save({str(path)!r})
rec.send_property("fleet", rr.AnyValues(robot_id="robot-e2e"))
rec.log("/world/map", rr.Points3D([[0.0, 0.0, 0.0], [1.0, 1.0, 0.0]]), static=True)
for i in range({frames}):
    log_frame(rec, i)
rec.flush()
"""
    env = {**os.environ, "RERUN_FLUSH_NUM_ROWS": "7", "RERUN_FLUSH_TICK_SECS": "1000"}
    subprocess.run([sys.executable, "-c", script], check=True, timeout=120, env=env, capture_output=True)
    return path


@pytest.fixture(scope="module")
def robot_files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("robot-files")
    return {run: _log_robot(folder / f"{run}.rrd", run, FRAMES + 10 * n) for n, run in enumerate(RUNS)}


@pytest.fixture(scope="module")
def reference_url(
    robot_files: dict[str, Path], rerun_bin: str, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[str]:
    """Rerun's own server on the robot's files."""
    folder = tmp_path_factory.mktemp("reference-dataset")
    with reference_serving(rerun_bin, folder, {DATASET: robot_files.values()}) as client:
        yield f"rerun+http://127.0.0.1:{client.port}"


@pytest.fixture(scope="module")
def depot_access(robot_files: dict[str, Path], tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, str]]:
    """A real `fleet serve` with auth on that received the robot's files by upload and sealed them:
    its catalog URL, and a read token for it (a JWT whose allowed_hosts names 127.0.0.1)."""
    server = LiveServer(tmp_path_factory.mktemp("depot") / "data", auth="on").start()
    try:
        for run_id, path in robot_files.items():
            answer = httpx.post(
                f"{server.url}/v1/uploads", content=path.read_bytes(), headers=server.headers, timeout=120
            )
            assert answer.status_code == 200, answer.text
            server.wait_for(functools.partial(_promoted, server, run_id), timeout=60, what=f"{run_id} sealed")
        made = httpx.post(
            f"{server.url}/v1/tokens", json={"scopes": ["read"], "name": "analyst"}, headers=server.headers, timeout=30
        )
        assert made.status_code == 201, made.text
        yield f"rerun+http://127.0.0.1:{server.grpc_port}", made.json()["token"]
    finally:
        server.stop()


@pytest.fixture(scope="module")
def depot_url(depot_access: tuple[str, str]) -> str:
    return depot_access[0]


def _token(request: pytest.FixtureRequest, server: str) -> str | None:
    """The read token a client of `server` sends: the depot's; Rerun's own server takes none."""
    return request.getfixturevalue("depot_access")[1] if server == "depot" else None


def _promoted(server: LiveServer, run_id: str) -> bool:
    """Ask the depot to seal the run now; true once it is sealed (409 while the upload's run closes)."""
    answer = httpx.post(f"{server.url}/v1/runs/{run_id}/promote", headers=server.headers, timeout=60)
    return answer.status_code == 200 or (answer.status_code == 409 and "warm already" in answer.text)


SERVERS = ["reference", "depot"]


@pytest.fixture(params=SERVERS)
def dataset(request: pytest.FixtureRequest) -> Iterator[Any]:
    """The dataset as the SDK's `CatalogClient` sees it (the client outlives the test's dataframes:
    they read through it)."""
    import rerun as rr

    client = rr.catalog.CatalogClient(
        request.getfixturevalue(f"{request.param}_url"), token=_token(request, request.param)
    )
    yield client.get_dataset(DATASET)
    del client


# --- reading ------------------------------------------------------------------------------------


def _comparable(found: pa.Table) -> tuple[list[str], list[str]]:
    """Column names and rows (as sorted text) of a dataframe, without `rerun_segment_id`; times as
    integers (nanosecond timestamps do not fit Python's datetime)."""
    found = found.drop([c for c in found.column_names if c == "rerun_segment_id"])
    found = pa.table(
        {
            name: column.cast(pa.int64()) if pa.types.is_temporal(column.type) else column
            for name, column in zip(found.column_names, found.columns, strict=True)
        }
    )
    rows = sorted(repr(sorted(row.items())) for row in found.to_pylist())
    assert rows, "a comparison over no rows proves nothing"
    return sorted(found.column_names), rows  # Rerun's two readers order the index columns apart


def _local(path: Path, shape: Callable[[Any], Any], **reader: Any) -> pa.Table:
    """Rerun's own dataframe API on the robot's file."""
    import rerun as rr

    return shape(rr.chunk.RrdReader(path).stream().collect().reader("frame", **reader)).to_arrow_table()


def _window(lo: int, hi: int) -> Callable[[Any], Any]:
    from datafusion import col, lit

    return lambda frame: frame.filter((col("frame") >= lit(lo)) & (col("frame") < lit(hi)))


def _as_is(frame: Any) -> Any:
    return frame


def test_the_reader_returns_each_run_s_rows(dataset: Any, robot_files: dict[str, Path]):
    found = dataset.reader(index="frame").to_arrow_table()
    assert sorted(set(found["rerun_segment_id"].to_pylist())) == sorted(RUNS)
    for run_id, path in robot_files.items():
        ours = found.filter(pc.equal(found["rerun_segment_id"], run_id))
        assert _comparable(ours) == _comparable(_local(path, _as_is)), run_id


def test_segment_and_content_filters_return_the_rows_of_those(dataset: Any, robot_files: dict[str, Path]):
    run_id = RUNS[1]
    chosen = dataset.filter_segments([run_id]).filter_contents(CONTENTS)
    found = chosen.reader(index="frame").to_arrow_table()
    assert set(found["rerun_segment_id"].to_pylist()) == {run_id}
    assert not any(name.startswith("/robot/log") or name.startswith("/world/map") for name in found.column_names)
    assert _comparable(found) == _comparable(_local(robot_files[run_id], _as_is, contents=CONTENTS))


@pytest.mark.parametrize("fill", [False, True], ids=["rows", "latest-at-filled"])
def test_a_time_window_returns_the_rows_in_it(dataset: Any, robot_files: dict[str, Path], fill: bool):
    run_id = RUNS[0]
    window = _window(17, 30)  # starts inside a chunk of seven rows: latest-at needs the chunks before
    chosen = dataset.filter_segments([run_id]).filter_contents(CONTENTS)
    found = window(chosen.reader(index="frame", fill_latest_at=fill)).to_arrow_table()
    expected = _local(robot_files[run_id], window, contents=CONTENTS, fill_latest_at=fill)
    assert _comparable(found) == _comparable(expected)
    assert sorted(set(found["frame"].to_pylist())) == list(range(17, 30))


# --- an SDK that knows no FindChunks ------------------------------------------------------------

OLD_SDK = "0.36.2"  # the oldest client the catalog serves: it asks QueryDataset, never FindChunks
OLD_SDK_READS = f"""
import sys
import pyarrow as pa
import rerun as rr
from datafusion import col, lit

out = sys.argv[2]
dataset = rr.catalog.CatalogClient(sys.argv[1], token=sys.argv[3] or None).get_dataset({DATASET!r})
chosen = dataset.filter_segments([{RUNS[0]!r}]).filter_contents({CONTENTS!r})
window = (col("frame") >= lit(17)) & (col("frame") < lit(30))
for name, frame in (
    ("whole", dataset.reader(index="frame")),
    ("window", chosen.reader(index="frame", fill_latest_at=True).filter(window)),
):
    found = frame.to_arrow_table()
    with pa.ipc.new_file(f"{{out}}/{{name}}.arrow", found.schema) as sink:
        sink.write_table(found)
"""


def _old_sdk_python() -> Path:
    """The venv of rerun-sdk OLD_SDK with the `datafusion` its catalog needs (54, as for 0.41)."""
    python = sdk_bin(OLD_SDK, "python")
    if subprocess.run([str(python), "-c", "import datafusion"], capture_output=True, check=False).returncode:
        subprocess.run(
            [str(python), "-m", "pip", "install", "--quiet", "--disable-pip-version-check", "datafusion==54.0.0"],
            check=True,
            capture_output=True,
            timeout=600,
        )
    return python


@pytest.mark.parametrize("server", SERVERS)
def test_an_sdk_without_find_chunks_reads_the_same_rows(
    request: pytest.FixtureRequest, server: str, robot_files: dict[str, Path], tmp_path: Path
):
    url = request.getfixturevalue(f"{server}_url")
    done = subprocess.run(
        [str(_old_sdk_python()), "-c", OLD_SDK_READS, url, str(tmp_path), _token(request, server) or ""],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    whole = pa.ipc.open_file(tmp_path / "whole.arrow").read_all()
    for run_id, path in robot_files.items():
        ours = whole.filter(pc.equal(whole["rerun_segment_id"], run_id))
        assert _comparable(ours) == _comparable(_local(path, _as_is)), run_id
    window = pa.ipc.open_file(tmp_path / "window.arrow").read_all()
    expected = _local(robot_files[RUNS[0]], _window(17, 30), contents=CONTENTS, fill_latest_at=True)
    assert _comparable(window) == _comparable(expected)
