"""Uploading the closed MCAP files: the request the depot gets (its route, run, application, the
robot's token, the file's bytes streamed whole), each file once across restarts and again once it
changed, and what each kind of answer does (kept, refused for good, retried). The depot's HTTP side
here is httpx's MockTransport; `test_bag_uploads.py` runs the same against the real `fleet serve`."""

from __future__ import annotations

import asyncio
import json
import os
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from services.agent import link as link_module
from services.agent.bags import ROSBAG2, Bag, BagScanner, Stamp
from services.agent.bagsend import (
    FAILED,
    PIECE,
    UPLOADED,
    BagRejected,
    BagSender,
    depot_client,
    depot_error,
    timeout_for,
    upload_bag,
)
from services.agent.link import Backoff, DepotRefused, LinkDown
from services.agent.state import AgentState
from tests.services.agent.mcap_files import write_bag, write_mcap

API = "http://depot.test:8080"
TOKEN = "robot.token.value"


class Depot:
    """What the agent's uploads reach: each request kept, answered by `answer` (200 by default)."""

    def __init__(self) -> None:
        self.requests: list[tuple[httpx.Request, bytes]] = []
        self.answer: Callable[[httpx.Request, bytes], httpx.Response] = self.filed

    def filed(self, request: httpx.Request, body: bytes) -> httpx.Response:
        run = request.url.params["run_id"]
        held = any(b == body for _, b in self.requests[:-1])
        imported = {"id": f"imp-{len(self.requests)}", "state": "filed", "already_held": held}
        return httpx.Response(200, json={"runs": [run], "chunks_new": 1, "chunks_duplicate": 0, "import": imported})

    async def handle(self, request: httpx.Request) -> httpx.Response:
        body = await request.aread()
        self.requests.append((request, body))
        return self.answer(request, body)

    def client(self) -> httpx.AsyncClient:
        return depot_client(API, TOKEN, transport=httpx.MockTransport(self.handle))


def refusal(status: int, code: str, message: str) -> Callable[[httpx.Request, bytes], httpx.Response]:
    return lambda _request, _body: httpx.Response(status, json={"error": {"code": code, "message": message}})


@pytest.fixture
def depot() -> Depot:
    return Depot()


@pytest.fixture
def state(tmp_path: Path) -> Iterator[AgentState]:
    opened = AgentState(tmp_path / "spool")
    yield opened
    opened.close()


@pytest.fixture
def watched(tmp_path: Path) -> Path:
    folder = tmp_path / "watched"
    folder.mkdir()
    return folder


@pytest.fixture(autouse=True)
def _no_waiting(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(link_module, "REFUSED_RETRY_S", 0.0)


def sender(watched: Path, state: AgentState, depot: Depot, **kwargs: Any) -> BagSender:
    made = BagSender([watched], state, depot.client(), idle_s=30.0, **kwargs)
    made.backoff = Backoff(0.0, 0.0)  # the curve is core.backoff's (tested there): no waiting here
    return made


def step(made: BagSender) -> None:
    asyncio.run(made.step())


def test_a_closed_bag_is_uploaded_whole_with_its_run_and_the_robots_token(
    watched: Path, state: AgentState, depot: Depot
):
    files = write_bag(watched / "rosbag2_2024_01_31-12_00_00", splits=2)
    made = sender(watched, state, depot)
    step(made)
    assert [body for _, body in depot.requests] == [f.read_bytes() for f in files]  # in split order
    for request, body in depot.requests:
        assert request.method == "POST" and request.url.path == "/v1/uploads"
        assert dict(request.url.params) == {"run_id": "rosbag2_2024_01_31-12_00_00", "application": ROSBAG2}
        assert request.headers["content-type"] == "application/octet-stream"
        assert request.headers["content-length"] == str(len(body))
        assert request.headers["authorization"] == f"Bearer {TOKEN}"
        assert request.headers["x-fleet-user"] == "fleet-agent"
    records = state.bags()
    assert sorted(records) == sorted(os.path.realpath(f) for f in files)
    for path, record in records.items():
        st = os.stat(path)
        assert (record.state, record.run_id, record.application) == (UPLOADED, "rosbag2_2024_01_31-12_00_00", ROSBAG2)
        assert (record.inode, record.size, record.mtime_ns) == (st.st_ino, st.st_size, st.st_mtime_ns)
        assert record.import_id is not None and record.import_id.startswith("imp-") and record.error is None
    counts = made.counts
    assert (counts.pending, counts.uploaded, counts.failed, counts.uploads) == (0, 2, 0, 2)
    assert counts.bytes_uploaded == sum(f.stat().st_size for f in files) and counts.error is None


def test_each_file_is_uploaded_once_across_restarts_and_again_once_it_changed(
    watched: Path, state: AgentState, depot: Depot
):
    (file,) = write_bag(watched / "bag")
    step(sender(watched, state, depot))
    step(sender(watched, state, depot))  # a restarted agent: the state says it was sent
    assert len(depot.requests) == 1
    write_mcap(file, messages=7)  # rewritten after its upload (recorded again under the same name)
    restarted = sender(watched, state, depot)
    step(restarted)
    assert len(depot.requests) == 2 and depot.requests[1][1] == file.read_bytes()
    assert state.bags()[os.path.realpath(file)].size == file.stat().st_size
    assert restarted.counts.uploaded == 1


def test_a_bag_the_depot_refuses_is_failed_and_not_sent_again_until_it_changes(
    watched: Path, state: AgentState, depot: Depot, caplog: pytest.LogCaptureFixture
):
    (file,) = write_bag(watched / "bag")
    depot.answer = refusal(400, "INVALID_ARGUMENT", "not a valid MCAP file: bad record at byte 44")
    made = sender(watched, state, depot)
    step(made)
    step(made)
    step(sender(watched, state, depot))
    assert len(depot.requests) == 1
    record = state.bags()[os.path.realpath(file)]
    assert record.state == FAILED and record.import_id is None
    assert record.error == "400 INVALID_ARGUMENT: not a valid MCAP file: bad record at byte 44"
    assert (made.counts.failed, made.counts.uploaded, made.counts.pending) == (1, 0, 0)
    assert "the depot refused" in caplog.text and "bad record at byte 44" in caplog.text
    st = file.stat()
    os.utime(file, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000_000))  # `touch`: try again
    depot.answer = depot.filed
    step(made)
    assert len(depot.requests) == 2 and state.bags()[os.path.realpath(file)].state == UPLOADED
    assert (made.counts.failed, made.counts.uploaded) == (0, 1)


@pytest.mark.parametrize(
    "answer",
    [
        refusal(503, "UNAVAILABLE", "the run's node does not answer yet"),
        refusal(500, "INTERNAL", "boom"),
        refusal(507, "RESOURCE_EXHAUSTED", "the hot tier is full"),
        refusal(429, "RESOURCE_EXHAUSTED", "slow down"),
        lambda _r, _b: httpx.Response(502, text="<html>bad gateway</html>"),
    ],
)
def test_the_depot_unable_to_take_it_now_is_retried(
    watched: Path, state: AgentState, depot: Depot, answer: Callable[[httpx.Request, bytes], httpx.Response]
):
    (file,) = write_bag(watched / "bag")
    depot.answer = answer
    made = sender(watched, state, depot)
    step(made)
    assert state.bags() == {} and made.counts.pending == 1 and made.counts.error
    assert made.backoff.failures == 1
    depot.answer = depot.filed
    step(made)
    assert len(depot.requests) == 2 and state.bags()[os.path.realpath(file)].state == UPLOADED
    assert made.counts.error is None and made.backoff.failures == 0


def test_no_answer_is_retried_and_the_rest_waits(watched: Path, state: AgentState, depot: Depot):
    write_bag(watched / "bag", splits=3)
    answers = iter([httpx.ConnectError("connection refused"), None, httpx.ReadTimeout("timed out")])

    def flaky(request: httpx.Request, body: bytes) -> httpx.Response:
        problem = next(answers, None)
        if problem is not None:
            raise problem
        return depot.filed(request, body)

    depot.answer = flaky
    made = sender(watched, state, depot)
    step(made)
    assert len(depot.requests) == 1 and state.bags() == {}  # the first failed: the others wait
    assert "ConnectError" in (made.counts.error or "")
    step(made)
    assert len(state.bags()) == 1 and len(depot.requests) == 3  # one sent, the next timed out
    step(made)
    assert len(state.bags()) == 3 and made.counts.uploaded == 3


def test_a_refused_token_is_not_held_against_the_bag(watched: Path, state: AgentState, depot: Depot):
    write_bag(watched / "bag")
    depot.answer = refusal(401, "UNAUTHENTICATED", "the token was revoked")
    made = sender(watched, state, depot)
    step(made)
    assert state.bags() == {} and made.counts.error == "refused: 401 UNAUTHENTICATED: the token was revoked"
    depot.answer = depot.filed  # a new token
    step(made)
    assert made.counts.uploaded == 1 and made.counts.error is None


def test_a_file_that_is_no_mcap_is_failed_without_being_sent(watched: Path, state: AgentState, depot: Depot):
    (watched / "notes.mcap").write_text("just some notes\n" * 10)
    made = sender(watched, state, depot)
    now = [0.0]
    made.scanner = BagScanner(30.0, clock=lambda: now[0])
    step(made)
    now[0] = 31.0
    step(made)
    assert depot.requests == []
    (record,) = state.bags().values()
    assert record.state == FAILED and "not an MCAP file" in (record.error or "")


def test_files_deleted_after_their_upload_are_forgotten(watched: Path, state: AgentState, depot: Depot, tmp_path: Path):
    files = write_bag(watched / "bag", splits=2)
    made = sender(watched, state, depot)
    step(made)
    files[0].unlink()
    step(made)
    assert list(state.bags()) == [os.path.realpath(files[1])]
    (tmp_path / "unmounted").mkdir()
    other = write_bag(tmp_path / "unmounted" / "bag2")
    elsewhere = BagSender([tmp_path / "unmounted"], state, depot.client(), idle_s=30.0)
    step(elsewhere)
    (tmp_path / "unmounted" / "bag2" / other[0].name).unlink()
    (tmp_path / "unmounted" / "bag2" / "metadata.yaml").unlink()
    (tmp_path / "unmounted" / "bag2").rmdir()
    (tmp_path / "unmounted").rmdir()  # the watched folder itself is gone: what it held is kept
    step(elsewhere)
    assert os.path.realpath(other[0]) in state.bags()


def test_a_file_gone_after_the_scan_does_not_hold_back_the_others(
    watched: Path, state: AgentState, depot: Depot, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
):
    files = write_bag(watched / "bag", splits=2)
    made = sender(watched, state, depot)
    scan = made.scanner.scan

    def scan_then_delete(*args: Any) -> Any:
        found = scan(*args)
        files[0].unlink()  # the robot cleans up between the scan and the upload
        return found

    monkeypatch.setattr(made.scanner, "scan", scan_then_delete)
    step(made)
    assert list(state.bags()) == [os.path.realpath(files[1])] and made.backoff.failures == 0
    assert f"{os.path.realpath(files[0])} could not be read" in caplog.text


def test_on_answer_is_told_when_the_depot_answers(watched: Path, state: AgentState, depot: Depot):
    write_bag(watched / "bag")
    told: list[bool] = []
    step(sender(watched, state, depot, on_answer=lambda: told.append(True)))
    assert told == [True]


# --- one upload -----------------------------------------------------------------------------------


def bag_of(path: Path, run_id: str = "run") -> Bag:
    return Bag(str(path), run_id, ROSBAG2, Stamp.of(os.stat(path)), True, "idle")


def test_upload_streams_the_file_in_pieces_and_only_the_bytes_it_had(tmp_path: Path, depot: Depot):
    path = tmp_path / "big.mcap"
    data = os.urandom(3 * PIECE + 17)
    path.write_bytes(data)
    bag = bag_of(path)
    with open(path, "ab") as fh:
        fh.write(b"appended after the scan")  # sent next time, as another file
    answer = asyncio.run(upload_bag(depot.client(), bag))
    assert answer["import"]["state"] == "filed"
    assert depot.requests[0][1] == data


def test_upload_of_a_file_gone_or_shorter_raises_oserror(tmp_path: Path, depot: Depot):
    path = write_mcap(tmp_path / "a.mcap")
    bag = bag_of(path)
    path.write_bytes(b"short")
    with pytest.raises(OSError):
        asyncio.run(upload_bag(depot.client(), bag))
    path.unlink()
    with pytest.raises(FileNotFoundError):
        asyncio.run(upload_bag(depot.client(), bag))


@pytest.mark.parametrize(
    ("status", "raised"),
    [
        *[(status, BagRejected) for status in (400, 404, 409, 413, 415, 422)],  # this bag: failed for good
        *[(status, DepotRefused) for status in (401, 403)],  # the robot's token: retried slowly
        *[(status, LinkDown) for status in (408, 429, 500, 503, 507)],  # not now: retried with backoff
    ],
)
def test_answers_map_to_what_the_agent_does(tmp_path: Path, depot: Depot, status: int, raised: type[Exception]):
    bag = bag_of(write_mcap(tmp_path / "a.mcap"))
    depot.answer = refusal(status, "CODE", "why")
    with pytest.raises(raised, match="why"):
        asyncio.run(upload_bag(depot.client(), bag))


def test_depot_errors_read_in_either_shape():
    nested = httpx.Response(400, json={"error": {"code": "INVALID_ARGUMENT", "message": "bad"}, "offset": 3})
    flat = httpx.Response(400, json={"code": "NOT_AN_RRD", "message": "expected RRF2"})
    assert depot_error(nested) == "400 INVALID_ARGUMENT: bad"
    assert depot_error(flat) == "400 NOT_AN_RRD: expected RRF2"
    assert depot_error(httpx.Response(413, text="too large")) == "413: too large"
    assert depot_error(httpx.Response(400, content=json.dumps([1]).encode())).startswith("400")


def test_big_files_get_longer_to_be_answered():
    small, big = timeout_for(1000), timeout_for(10_000_000_000)
    assert big.read is not None and small.read is not None and big.read > small.read + 900
    assert big.write == small.write and big.connect == small.connect
