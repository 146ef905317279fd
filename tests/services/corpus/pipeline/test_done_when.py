"""The corpus as a user sees it, through one `fleet serve` (auth on, Postgres, its scheduler on): a
robot streams the scene with the real rerun-sdk, another run is uploaded; rules applied with
`fleet rules apply` give each run the events and metrics computed here from what the scene logged,
live while hot and final once sealed, and again after a rules change and `fleet rules backfill`
(replaced, never doubled); a webhook receiver on loopback is told of each intervention and each seal
once, signed; tag, metric and event filters keep the same runs over REST, the CLI, SQL, the console
and the catalog protocol's segment table; the dashboard's numbers are its SQL over `run_metrics`."""

from __future__ import annotations

import datetime as dt
import hashlib
import hmac
import json
import re
import threading
from collections import Counter
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from functools import partial
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any
from urllib.parse import urlencode

import httpx
import pytest

from services.console.interventions import Metrics, dashboard_sql
from tests.services.console.test_corpus_search import CELL, ROW, Cells, assert_same, shown
from tests.services.console.test_sessions import log_in
from tests.services.corpus.pipeline import scene as expect
from tests.services.corpus.pipeline.conftest import Served, ServeFactory, log_scene
from tests.services.redap.test_corpus_segments import TAGS
from tests.waiting import wait_for

pytestmark = [pytest.mark.slow, pytest.mark.sdk, pytest.mark.postgres]

BUSY, CALM = "done-when-busy", "done-when-calm"  # streamed (three interventions); uploaded (none)
CALM_TAGS = "day-shift, dock-2"
DATASET = "corpus_scene"  # the scene's application id
INTERVENTION, SEALED = "event:intervention", "run.sealed"


# --- a webhook receiver on loopback ------------------------------------------------------------------


@dataclass
class Receiver:
    """Every POST it was sent: its headers (names in lower case) and body."""

    posts: list[tuple[dict[str, str], bytes]] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)
    port: int = 0

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}/fleet-hook"

    def of(self, occurrence: str) -> list[tuple[dict[str, str], bytes]]:
        with self.lock:
            return [(h, b) for h, b in self.posts if h.get("x-fleet-occurrence") == occurrence]

    def counts(self) -> Counter[str]:
        with self.lock:
            return Counter(h.get("x-fleet-occurrence", "") for h, _ in self.posts)

    def delivery_ids(self) -> set[str]:
        with self.lock:
            return {h["x-fleet-delivery"] for h, _ in self.posts}


@pytest.fixture
def receiver() -> Iterator[Receiver]:
    got = Receiver()

    class Hook(BaseHTTPRequestHandler):
        def do_POST(self) -> None:
            body = self.rfile.read(int(self.headers.get("Content-Length", "0")))
            with got.lock:
                got.posts.append(({k.lower(): v for k, v in self.headers.items()}, body))
            self.send_response(204)
            self.end_headers()

        def log_message(self, *args: Any) -> None:
            pass

    server = ThreadingHTTPServer(("127.0.0.1", 0), Hook)
    got.port = server.server_address[1]
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield got
    finally:
        server.shutdown()
        server.server_close()
        thread.join(timeout=10)


# --- what the scene must give, computed from what it logged --------------------------------------


@dataclass(frozen=True)
class Found:
    """A run's events by kind, sorted: (start, end) on sim_time, the scene's clock; a robot's event
    (on log_time, the wall clock when it was logged) as (timeline, label); and its metrics."""

    events: dict[str, list[tuple[Any, Any]]]
    metrics: dict[str, Any]

    def matches(self, other: Found) -> bool:
        return self.events == other.events and self.metrics == pytest.approx(other.metrics)


def v1_values(frames: int, drops: expect.Drops, sw_version: str) -> Found:
    interventions = expect.expected_interventions(frames, drops)
    events: dict[str, list[tuple[Any, Any]]] = {
        "intervention": list(interventions),
        "stuck": [(t, t) for t in expect.expected_stuck(frames)],
        "hard_brake": [("log_time", "brake!")] if frames > expect.BRAKE_FRAME else [],
    }
    metrics = {
        "distance_m": expect.expected_distance(frames),
        "interventions": float(len(interventions)),
        "temp_mean": expect.expected_temp_mean(frames),
        "sw_version": sw_version,
    }
    return Found({k: v for k, v in events.items() if v}, metrics)


BUSY_HALF = v1_values(expect.HALF, expect.DROPS, expect.SW_VERSION)  # the second drop is still under way
BUSY_V1 = v1_values(expect.FRAMES, expect.DROPS, expect.SW_VERSION)
CALM_V1 = v1_values(expect.CALM_FRAMES, (), expect.CALM_SW_VERSION)
BUSY_V2 = Found(
    {"intervention": expect.expected_interventions(), "hard_brake": BUSY_V1.events["hard_brake"]},
    {"temp_max": expect.expected_temp_max()},
)
CALM_V2 = Found({}, {"temp_max": expect.expected_temp_max(expect.CALM_FRAMES)})


# --- the depot as its users reach it -------------------------------------------------------------------


@dataclass
class User:
    depot: Served
    reader: str
    writer: str
    seen: str = ""  # what the last look at a run's evaluation saw

    def get(self, path: str, token: str | None = None, *, missing: bool = False, **params: Any) -> Any:
        """The answer's JSON; None for a 404 when `missing` (a run not in the catalog yet)."""
        headers = {"Authorization": f"Bearer {token or self.reader}"}
        answer = httpx.get(f"{self.depot.url}{path}", params=params or None, headers=headers, timeout=60)
        if missing and answer.status_code == 404:
            return None
        assert answer.status_code == 200, answer.text
        return answer.json()

    def sql(self, query: str) -> list[list[Any]]:
        headers = {"Authorization": f"Bearer {self.reader}"}
        answer = httpx.post(f"{self.depot.url}/v1/sql", json={"query": query}, headers=headers, timeout=60)
        assert answer.status_code == 200, answer.text
        return list(answer.json()["rows"])

    def run(self, run_id: str) -> dict[str, Any]:
        return dict(self.get(f"/v1/runs/{run_id}"))

    def found(self, run_id: str) -> Found:
        events: dict[str, list[tuple[Any, Any]]] = {}
        for e in self.get(f"/v1/runs/{run_id}/events")["events"]:
            on_scene = e["timeline"] == "sim_time"
            events.setdefault(e["kind"], []).append((e["start"], e["end"]) if on_scene else (e["timeline"], e["label"]))
        return Found({k: sorted(v) for k, v in events.items()}, self.run(run_id)["metrics"])

    def evaluated(self, run_id: str, want: Found, state: str, version: int) -> Found | None:
        """What REST says of the run once its evaluation is `state` at `version` and gives `want`."""
        run = self.get(f"/v1/runs/{run_id}", missing=True)
        evaluation = run["evaluation"] if run is not None else None
        found = self.found(run_id) if evaluation is not None else None
        self.seen = f"evaluation {evaluation}, {found}"
        if evaluation is None or (evaluation["state"], evaluation["rules_version"]) != (state, version):
            return None
        return found if found is not None and found.matches(want) else None

    def wait_evaluated(self, run_id: str, want: Found, state: str, version: int) -> None:
        what = f"{run_id}'s {state} values at rules version {version}: {want}"
        condition = lambda: self.evaluated(run_id, want, state, version)  # noqa: E731
        wait_for(condition, timeout=60, what=what, detail=lambda: f"REST said: {self.seen}\n{self.depot.server.said()}")


def apply_rules(user: User, path: Path, text: str, version: int) -> None:
    path.write_text(text)
    out = user.depot.fleet(user.writer, "rules", "apply", str(path))
    assert out.stdout.startswith(f"rules version {version} applied by "), out.stdout


def add_webhook(depot: Served, receiver: Receiver) -> tuple[str, str]:
    """`fleet webhooks add` (admin): the webhook's id and its secret, printed alone on stdout."""
    out = depot.fleet(depot.admin, "webhooks", "add", receiver.url, "--on", INTERVENTION, "--on", SEALED)
    secret = out.stdout.strip()
    found = re.search(r"webhook (wh-[0-9a-f]+) ", out.stderr)
    assert secret and "\n" not in secret and found, out
    return found.group(1), secret


def signed(secret: str, posts: list[tuple[dict[str, str], bytes]]) -> list[dict[str, Any]]:
    """The bodies, each checked against its X-Fleet-Signature."""
    for headers, body in posts:
        mac = hmac.new(secret.encode(), body, hashlib.sha256).hexdigest()
        assert hmac.compare_digest(headers["x-fleet-signature"], f"sha256={mac}")
        assert headers["content-type"] == "application/json"
    return [json.loads(body) for _, body in posts]


def told_once(user: User, receiver: Receiver, webhook: str, secret: str, intervention_ids: set[str]) -> None:
    """Each intervention and each seal sent once, signed, and the outbox holds nothing more."""
    assert receiver.counts() == {INTERVENTION: 3, SEALED: 2}
    events = signed(secret, receiver.of(INTERVENTION))
    assert {e["event_id"] for e in events} == intervention_ids
    assert {(e["run_id"], e["kind"]) for e in events} == {(BUSY, "intervention")}
    assert sorted(r["run_id"] for r in signed(secret, receiver.of(SEALED))) == sorted([BUSY, CALM])
    deliveries = user.get(f"/v1/webhooks/{webhook}/deliveries", user.depot.admin, limit=100)["deliveries"]
    assert len(deliveries) == 5 and {d["state"] for d in deliveries} == {"delivered"}
    assert receiver.delivery_ids() == {d["id"] for d in deliveries}


# --- search everywhere --------------------------------------------------------------------------------


@dataclass(frozen=True)
class Search:
    """A search as each surface writes it, and the runs it must keep."""

    query: list[tuple[str, str]]  # GET /v1/runs and /console/runs parameters; `fleet runs ls --NAME VALUE`
    sql: str  # over run_metrics / run_tags / events: the run ids kept
    segments: Callable[[], Any]  # a DataFusion condition on the segment table
    keeps: list[str]


def metric_column(name: str) -> Any:
    from datafusion import col, lit
    from datafusion import functions as f

    return f.array_element(col(f"property:depot:metric:{name}"), lit(1))


def has_tag(tag: str) -> Any:
    from datafusion import col, lit
    from datafusion import functions as f

    return f.array_has(col(TAGS), lit(tag))


def number(value: float | str) -> Any:
    from datafusion import lit

    return lit(value)


def v1_searches() -> list[Search]:
    metric = "SELECT run_id FROM run_metrics WHERE name = '{}' AND {}"
    tagged = "SELECT run_id FROM run_tags WHERE tag = '{}'"
    # The segment table has no events: a run has an intervention when its event_count metric says so.
    return [
        Search([("tag", "night-shift")], tagged.format("night-shift"), lambda: has_tag("night-shift"), [BUSY]),
        Search([("tag", "reviewed")], tagged.format("reviewed"), lambda: has_tag("reviewed"), [CALM]),
        Search(
            [("metric", "distance_m<20")],
            metric.format("distance_m", "value < 20"),
            lambda: metric_column("distance_m") < number(20.0),
            [CALM],
        ),
        Search(
            [("metric", "sw_version=2.3.1")],
            metric.format("sw_version", "text_value = '2.3.1'"),
            lambda: metric_column("sw_version") == number("2.3.1"),
            [BUSY],
        ),
        Search(
            [("event", "intervention")],
            "SELECT DISTINCT run_id FROM events WHERE kind = 'intervention'",
            lambda: metric_column("interventions") >= number(1.0),
            [BUSY],
        ),
        Search(
            [("event", "stuck"), ("tag", "dock-2"), ("metric", "interventions=0")],
            "SELECT run_id FROM events WHERE kind = 'stuck' INTERSECT "
            + tagged.format("dock-2")
            + " INTERSECT "
            + metric.format("interventions", "value = 0"),
            lambda: has_tag("dock-2") & (metric_column("interventions") == number(0.0)),
            [CALM],
        ),
    ]


def v2_searches() -> list[Search]:
    return [
        Search(
            [("metric", "temp_max>23")],
            "SELECT run_id FROM run_metrics WHERE name = 'temp_max' AND value > 23 AND rules_version = 2",
            lambda: metric_column("temp_max") > number(23.0),
            [BUSY],
        ),
        Search(
            [("tag", "reviewed")],
            "SELECT run_id FROM run_tags WHERE tag = 'reviewed'",
            lambda: has_tag("reviewed"),
            [CALM],
        ),
    ]


def cli_ids(user: User, query: list[tuple[str, str]]) -> list[str]:
    args = [arg for name, value in query for arg in (f"--{name}", value)]
    out = user.depot.fleet(user.reader, "runs", "ls", "--json", *args)
    return [run["id"] for run in json.loads(out.stdout)["runs"]]


def console_ids(browser: httpx.Client, query: list[tuple[str, str]]) -> list[str]:
    page = browser.get(f"/console/runs?{urlencode(query)}")
    assert page.status_code == 200, page.text
    return ROW.findall(page.text)


def segment_ids(user: User, condition: Any) -> list[str]:
    import rerun as rr
    from datafusion import col

    client = rr.catalog.CatalogClient(f"rerun+http://127.0.0.1:{user.depot.server.grpc_port}", token=user.reader)
    table = client.get_dataset(DATASET).segment_table()
    rows = table.filter(condition).select(col("rerun_segment_id")).to_arrow_table()
    return sorted(rows.column("rerun_segment_id").to_pylist())


def assert_everywhere(user: User, browser: httpx.Client, searches: list[Search]) -> None:
    with ThreadPoolExecutor(4) as pool:  # a CLI process takes seconds to start: side by side
        by_cli = list(pool.map(lambda s: cli_ids(user, s.query), searches))
    for search, cli in zip(searches, by_cli, strict=True):
        rest = [run["id"] for run in user.get(f"/v1/runs?{urlencode(search.query)}")["runs"]]
        assert sorted(rest) == sorted(search.keeps), search.query
        assert cli == rest, search.query
        assert console_ids(browser, search.query) == rest, search.query
        assert sorted(row[0] for row in user.sql(search.sql)) == sorted(rest), search.sql
        assert segment_ids(user, search.segments()) == sorted(rest), search.query


# --- the dashboard ------------------------------------------------------------------------------------


def dashboard_expected(user: User) -> Cells:
    """Per ISO week of each run's start and version: runs, distance, interventions, their ratio."""
    cells: Cells = {}
    for run_id, want in ((BUSY, BUSY_V1), (CALM, CALM_V1)):
        year, week, _ = dt.datetime.fromisoformat(user.run(run_id)["started_at"]).isocalendar()
        count, distance = want.metrics["interventions"], want.metrics["distance_m"]
        key = (f"{year}-W{week:02d}", want.metrics["sw_version"])
        cells[key] = (1, distance, count, distance / count if count else None)
    return cells


def assert_dashboard(user: User, browser: httpx.Client) -> None:
    page = browser.get("/console/dashboards/interventions")
    assert page.status_code == 200, page.text
    on_page = shown(page.text)
    assert len(CELL.findall(page.text)) == 2
    by_sql: Cells = {(r[0], r[1]): (r[2], r[3], r[4], r[5]) for r in user.sql(dashboard_sql(Metrics()))}
    assert_same(on_page, by_sql)
    assert_same(on_page, dashboard_expected(user))


# --- the test -----------------------------------------------------------------------------------------


def test_done_when(serve: ServeFactory, receiver: Receiver, tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    monkeypatch.delenv("REDAP_TOKEN", raising=False)  # the SDK sends the token the test gives it
    depot = serve(
        scheduler="true",
        webhook_hosts=f"127.0.0.1:{receiver.port}",
        webhook_interval_s="0.2",
        promote_interval_s="3600",
        promote_below_free_bytes="0",
        retention_interval_s="3600",
        rules_backfill_interval_s="3600",
    )
    user = User(depot, depot.token("read"), depot.token("write"))
    robot_token = depot.token("ingest", robot="robot-c")
    rules = tmp_path / "rules.toml"
    apply_rules(user, rules, expect.RULES_V1, 1)
    # Before the robot streams: half its scene sent, it waits, and only new chunks wake the live rules.
    live_v1 = "live rules: now version 1"
    depot.server.wait_for(lambda: live_v1 in depot.server.log.read_text(errors="replace"), what=live_v1)
    webhook, secret = add_webhook(depot, receiver)

    # Live: half the scene streamed, then all of it, while the run is hot.
    robot = depot.stream_scene(BUSY, robot_token)
    assert robot.stdout is not None and robot.stdin is not None
    try:
        assert robot.stdout.readline().strip() == "READY"
        user.wait_evaluated(BUSY, BUSY_HALF, "live", 1)
        wait_for(lambda: receiver.counts()[INTERVENTION] == 1, timeout=30, what="the first intervention told")
        robot.stdin.write("go\n")
        robot.stdin.flush()
        assert robot.wait(timeout=120) == 0
    finally:
        robot.kill()
    user.wait_evaluated(BUSY, BUSY_V1, "live", 1)
    assert user.run(BUSY)["tier"] == "hot"
    calm = tmp_path / "calm.rrd"
    log_scene(str(calm), CALM, CALM_TAGS, calm=True)
    headers = {"Authorization": f"Bearer {robot_token}"}
    uploaded = httpx.post(f"{depot.url}/v1/uploads", content=calm.read_bytes(), headers=headers, timeout=60)
    assert uploaded.status_code in (200, 201, 202), uploaded.text

    # Sealed: final values, each intervention and seal told once.
    for run_id in (BUSY, CALM):
        wait_for(partial(depot.promoted, run_id, user.writer), timeout=60, what=f"{run_id} promoted")
    user.wait_evaluated(BUSY, BUSY_V1, "final", 1)
    user.wait_evaluated(CALM, CALM_V1, "final", 1)
    ids = {e["id"] for e in user.get(f"/v1/runs/{BUSY}/events")["events"] if e["kind"] == "intervention"}
    wait_for(lambda: receiver.counts() == {INTERVENTION: 3, SEALED: 2}, timeout=30, what="the webhook told")
    told_once(user, receiver, webhook, secret, ids)

    # Tags and search: the same runs on every surface.
    tagged = depot.fleet(user.writer, "runs", "tag", CALM, "reviewed")
    assert "reviewed  added by test-write" in tagged.stdout, tagged.stdout
    tags = {t["tag"]: t["added_by"] for t in user.run(CALM)["tags"]}
    assert tags == {"day-shift": "robot", "dock-2": "robot", "reviewed": "test-write"}
    with httpx.Client(base_url=depot.url, timeout=60) as browser:
        log_in(browser, user.reader)  # the console's session
        assert_everywhere(user, browser, v1_searches())
        assert_dashboard(user, browser)

        # A rules change and its backfill: values replaced, nothing doubled, nobody told again.
        apply_rules(user, rules, expect.RULES_V2, 2)
        out = depot.fleet(user.writer, "rules", "backfill")
        assert "2 runs evaluated, 0 skipped (cold)" in out.stdout and "0 failed" in out.stdout, out.stdout
        user.wait_evaluated(BUSY, BUSY_V2, "final", 2)
        user.wait_evaluated(CALM, CALM_V2, "final", 2)
        events = user.get(f"/v1/runs/{BUSY}/events")["events"]
        assert {e["id"] for e in events if e["kind"] == "intervention"} == ids  # the same events, found again
        assert {(e["source"], e["severity"], e["rules_version"]) for e in events if e["kind"] == "intervention"} == {
            ("rule intervention@2", "error", 2)
        }
        assert user.run(BUSY)["metrics_rules_version"] == 2
        assert user.sql("SELECT name, rules_version, count(*) FROM run_metrics GROUP BY name, rules_version") == [
            ["temp_max", 2, 2]
        ]
        kinds = user.sql("SELECT kind, count(*) FROM events GROUP BY kind ORDER BY kind")
        assert kinds == [["hard_brake", 1], ["intervention", 3]]
        assert {t["tag"] for t in user.run(CALM)["tags"]} == {"day-shift", "dock-2", "reviewed"}  # people's stay
        assert_everywhere(user, browser, v2_searches())
        told_once(user, receiver, webhook, secret, ids)
