"""ReadMessages: recent history of live runs within a byte budget (a live run's store infos and
blueprints never dropped, oldest temporal first, closed runs gone), then live messages; and the
real Rerun CLI as a reader."""

from __future__ import annotations

import asyncio
import gc
import subprocess
from pathlib import Path

import pytest

from services.ingest.replay import COPY_BELOW, ReplayHub, read_response
from services.rrd.frames import MessageKind
from services.rrd.pb import log_msg_pb2, sdk_comms_pb2
from tests.services.ingest.live_server import LiveServer, start_robot
from tests.services.rrd.recordings import rerun_rrd_ok
from tests.subprocess_server import free_port


def test_responses_wrap_the_message_bytes():
    raw = log_msg_pb2.ArrowMsg(uncompressed_size=3, payload=b"abc").SerializeToString()
    response = sdk_comms_pb2.ReadMessagesResponse.FromString(read_response(2, raw))
    assert response.log_msg.WhichOneof("msg") == "arrow_msg"
    assert response.log_msg.arrow_msg.SerializeToString() == raw


def test_held_small_messages_cost_the_garbage_collector_nothing():
    """The history of one-row chunks is tens of thousands of entries: none may stay among the
    objects every full collection walks."""
    hub = ReplayHub(budget_bytes=64 << 20)
    request = bytearray(b"\x0a" + bytes(1200))  # as the front hands over a request
    for i in range(1000):
        hub.publish(f"run-{i % 4}", MessageKind.ARROW_MSG, memoryview(request)[1:], persistent=False, static=False)
    gc.collect()
    gc.collect()  # a tuple is left alone once what it holds is: the outer ones at the second pass
    entries = list(hub._temporal)
    assert len(entries) == 1000
    assert not any(gc.is_tracked(entry) for entry in entries)
    assert all(type(raw) is bytes and raw == bytes(1200) for _, (_, raw) in entries)
    request[1:] = b"\xff" * 1200  # the request's buffer reused: the history keeps what was sent
    history, _ = hub.subscribe()
    assert all(raw == bytes(1200) for _, raw in history)
    large = memoryview(bytes(COPY_BELOW))
    hub.publish("run-0", MessageKind.ARROW_MSG, large, persistent=False, static=False)
    assert hub._temporal[-1][1][1] is large  # a large message stays a view: no copy


def test_budget_drops_oldest_temporal_then_static_never_persistent():
    hub = ReplayHub(budget_bytes=300)
    hub.publish("run", 1, b"s" * 50, persistent=True, static=False)
    hub.publish("run", 2, b"a" * 100, persistent=False, static=True)
    for i in range(5):
        hub.publish("run", 2, bytes([i]) * 100, persistent=False, static=False)
    history, _ = hub.subscribe()
    bodies = [bytes(raw) for _, raw in history]
    assert bodies[0] == b"s" * 50  # the store info stays
    assert any(b == b"a" * 100 for b in bodies)  # static kept while temporal can go
    assert bytes([4]) * 100 in bodies[-1] and bytes([0]) * 100 not in b"".join(bodies)  # newest temporal kept
    assert hub.held_bytes <= 300
    hub.publish("run", 2, b"b" * 300, persistent=False, static=True)  # over budget even alone
    history, _ = hub.subscribe()
    assert bytes(history[0][1]) == b"s" * 50


def test_history_holds_live_runs_only_and_the_budget_is_a_bound():
    """Closed runs leave the history with their store infos and blueprints, so after hundreds of runs
    the budget still holds the recent history of the runs that are live now."""
    hub = ReplayHub(budget_bytes=10_000)
    for n in range(500):  # runs that came and went, each with a store info, a blueprint and data
        run = f"old-{n}"
        hub.publish(run, 1, b"i" * 40, persistent=True, static=False)
        hub.publish(run, 2, b"p" * 60, persistent=True, static=False)
        hub.publish(run, 2, b"d" * 100, persistent=False, static=False)
        hub.end_run(run)
    assert hub.held_bytes == 0 and hub.live_runs == 0
    hub.publish("now", 1, b"I" * 40, persistent=True, static=False)
    for i in range(50):
        hub.publish("now", 2, bytes([i]) * 100, persistent=False, static=False)
    history, _ = hub.subscribe()
    bodies = [bytes(raw) for _, raw in history]
    assert bodies[0] == b"I" * 40
    assert not any(b[:1] in (b"i", b"p", b"d") for b in bodies)  # nothing of a closed run is replayed
    assert len(bodies) == 51 and hub.held_bytes == 40 + 50 * 100  # all the live run's recent data fits
    hub.end_run("now")
    assert hub.subscribe()[0] == [] and hub.held_bytes == 0


def test_readers_get_live_messages_and_slow_ones_are_let_go():
    async def scenario() -> None:
        hub = ReplayHub(budget_bytes=10_000)
        _, queue = hub.subscribe()
        hub.publish("run", 2, b"x", persistent=False, static=False)
        assert await queue.get() == (2, b"x")
        for _ in range(5000):  # never read: the reader falls behind and is dropped
            hub.publish("run", 2, b"y", persistent=False, static=False)
        items = []
        while not queue.empty():
            items.append(queue.get_nowait())
        assert items[-1] is None

    asyncio.run(scenario())


@pytest.mark.sdk
def test_rerun_cli_reads_a_live_stream(tmp_path: Path, rerun_bin: str):
    server = LiveServer(tmp_path / "data").start()
    saved = tmp_path / "saved.rrd"
    # `rerun --save` also listens for SDKs (on 0.0.0.0:9876 by default): a free loopback port instead
    reader = subprocess.Popen(
        [rerun_bin, "--save", str(saved), "--bind", "127.0.0.1", "--port", str(free_port()), server.grpc_url],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    try:
        copy = tmp_path / "copy.rrd"
        robot = start_robot("live", server.grpc_url, str(copy), "replay-run")
        assert robot.stdout is not None and robot.stdin is not None
        assert robot.stdout.readline().strip() == "READY"
        robot.stdin.write("go\n")
        robot.stdin.flush()
        robot.communicate(timeout=120)
        hot = server.data_dir / "hot" / "replay-run" / "run.rrd"
        server.wait_for(lambda: hot.exists(), what="the run on disk")
    finally:
        server.stop()  # ends the reader's stream; rerun --save then writes its file
        reader.wait(timeout=60)
    assert saved.exists() and saved.stat().st_size > 0, reader.stderr.read() if reader.stderr else ""
    rerun_rrd_ok(rerun_bin, "compare", "--unordered", copy, saved)
