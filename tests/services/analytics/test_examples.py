"""The worked examples of docs/analytics.md, run as the doc writes them: the ```sql block under each
"### N." heading is read from the doc file and sent to POST /v1/sql over runs logged with the
real SDK (three robots, two runs each, on known days) and promoted; every answer is exact.

What each run logged is in RUNS: `/battery` draining linearly by a known amount, `/joints/torque`
for six joints (joint 3 over 40 in one run only; joint 2 over 40 in another), `/robot/base` moving
along a known path (with a rotation-only pose in between, which has no translation to measure),
`/robot/arm` moving too (another entity), and `/logs` with known numbers of ERROR and CRITICAL lines.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from services.sealed.tiers import Tiers
from services.storage.objectstore import open_store
from tests.services.analytics.conftest import (
    DAY_NS,
    HOUR_NS,
    START_2026_03_01_NS,
    api,
    log_with_sdk,
    promote_all,
    sql_rows,
    upload_all,
)
from tests.services.retention.conftest import NodeFactory

pytestmark = pytest.mark.sdk

DOC = Path(__file__).resolve().parents[3] / "docs" / "analytics.md"
FRAMES, JOINTS = 5, 6
PATH = ((0, 0, 0), (3, 4, 0), (3, 4, 12), (0, 0, 12))  # 5 + 12 + 5 = 22 m at scale 1
PATH_LENGTH = 22.0


@dataclass(frozen=True)
class Run:
    id: str
    robot: str
    day: int  # days after 2026-03-01
    battery: float  # level at the start
    drain: float  # percent drained over the run
    joint3_peak: float
    scale: float  # of PATH
    errors: int
    criticals: int = 0
    joint2_peak: float = 20.0  # another joint: its peaks must not count as joint 3's


RUNS = (
    Run("ex-a1", "robot-a", 0, 100.0, 11.5, 39.5, 1.0, 3, joint2_peak=55.0),
    Run("ex-a2", "robot-a", 1, 90.0, 9.75, 38.0, 0.5, 0),
    Run("ex-b1", "robot-b", 0, 100.0, 5.0, 40.0, 1.5, 1),  # exactly 40: not "exceeded"
    Run("ex-b2", "robot-b", 0, 95.0, 7.5, 42.5, 2.0, 5),  # the same day as ex-b1
    Run("ex-c1", "robot-c", 1, 80.0, 10.0, 12.0, 2.5, 2, criticals=1),
    Run("ex-c2", "robot-c", 2, 70.0, 0.25, 30.0, 3.0, 0),
)

SCRIPT = """
PATH, FRAMES, JOINTS = {path!r}, {frames}, {joints}
for run_id, robot, start, battery, drain, j3, j2, scale, errors, criticals in {runs!r}:
    rec = recording(FOLDER + f"/{{run_id}}.rrd", run_id, robot, start)
    levels = ["ERROR"] * errors + ["CRITICAL"] * criticals + ["INFO", "WARN", "DEBUG"]
    for i in range(FRAMES):
        rec.set_time("frame", sequence=i)
        rec.log("/battery", rr.Scalars(battery - drain * i / (FRAMES - 1)))
        torques = [10.0 + j + 0.5 * i for j in range(JOINTS)]
        torques[3] = j3 if i == 2 else j3 - 5.0
        torques[2] = j2 if i == 1 else 10.0
        rec.log("/joints/torque", rr.Scalars(torques))
        if i < len(PATH):
            rec.log("/robot/base", rr.Transform3D(translation=[scale * c for c in PATH[i]],
                                                 quaternion=rr.Quaternion(xyzw=[0, 0, 0, 1])))
        if i == 1:  # a pose with a rotation only: no translation to measure
            rec.log("/robot/base", rr.Transform3D(quaternion=rr.Quaternion(xyzw=[0, 0, 0.6, 0.8])))
        rec.log("/robot/arm", rr.Transform3D(translation=[100.0 * i, 0, 0]))
    for n, level in enumerate(levels):
        rec.set_time("frame", sequence=n)
        rec.log("/logs", rr.TextLog(f"line {{n}}", level=level))
    finish(rec)
"""


@pytest.fixture(scope="module")
def recordings(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    folder = tmp_path_factory.mktemp("analytics-examples")
    runs = [
        (
            r.id,
            r.robot,
            START_2026_03_01_NS + r.day * DAY_NS + 9 * HOUR_NS,
            r.battery,
            r.drain,
            r.joint3_peak,
            r.joint2_peak,
            r.scale,
            r.errors,
            r.criticals,
        )
        for r in RUNS
    ]
    log_with_sdk(f"FOLDER = {str(folder)!r}\n" + SCRIPT.format(path=PATH, frames=FRAMES, joints=JOINTS, runs=runs))
    return [folder / f"{r.id}.rrd" for r in RUNS]


def doc_examples() -> dict[int, tuple[str, str]]:
    """{number: (title, sql)} of the "### N. title" sections of docs/analytics.md."""
    text = DOC.read_text()
    found = re.findall(r"^### (\d+)\. (.+?)\n+```sql\n(.*?)```", text, flags=re.MULTILINE | re.DOTALL)
    return {int(n): (title.strip(), sql.strip()) for n, title, sql in found}


def date(day: int) -> str:
    return f"2026-03-0{1 + day}"


def expected_answers() -> dict[int, list[dict[str, Any]]]:
    drains: dict[tuple[str, str], float] = {}
    for r in RUNS:
        drains[(r.robot, date(r.day))] = drains.get((r.robot, date(r.day)), 0.0) + r.drain
    errors = sorted(
        ((r.errors + r.criticals, r.id, r.robot) for r in RUNS if r.errors + r.criticals), key=lambda e: (-e[0], e[1])
    )
    return {
        1: [{"robot_id": robot, "date": day, "drain_percent": drain} for (robot, day), drain in sorted(drains.items())],
        2: [{"run_id": run, "robot_id": robot, "errors": n} for n, run, robot in errors],
        3: [{"run_id": r.id, "distance_m": PATH_LENGTH * r.scale} for r in sorted(RUNS, key=lambda r: r.id)],
        4: [{"run_id": r.id, "robot_id": r.robot, "peak_torque": r.joint3_peak} for r in RUNS if r.joint3_peak > 40],
    }


def test_the_doc_has_four_worked_examples():
    examples = doc_examples()
    assert sorted(examples) == [1, 2, 3, 4]
    assert [title for title, _ in examples.values()] == [
        "Battery drain per robot per day",
        "Error logs per run",
        "Distance driven per run",
        "Runs where joint 3 torque exceeded 40",
    ]
    assert all(sql.upper().startswith("SELECT") for _, sql in examples.values())


def test_worked_examples_answer_exactly(tmp_path: Path, make_node: NodeFactory, recordings: list[Path]):
    node = make_node(Tiers(open_store((tmp_path / "warm").as_uri()), open_store((tmp_path / "cold").as_uri())))
    upload_all(node, recordings)
    assert sorted(promote_all(node)) == sorted(r.id for r in RUNS)
    client = api(node)
    assert sql_rows(client, "SELECT id, robot_id, date FROM runs ORDER BY id") == [
        {"id": r.id, "robot_id": r.robot, "date": date(r.day)} for r in RUNS
    ]  # robots and days as logged
    expected = expected_answers()
    assert expected[4] == [{"run_id": "ex-b2", "robot_id": "robot-b", "peak_torque": 42.5}]  # the data's premise
    answers = {n: sql_rows(client, sql) for n, (_, sql) in doc_examples().items()}
    wrong = {n: (answers[n], expected[n]) for n in expected if answers.get(n) != expected[n]}
    assert not wrong, wrong
