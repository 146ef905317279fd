"""Webhooks through the real `fleet serve`, its schedule and the `fleet webhooks` commands: a robot
(the real SDK) streams, then goes quiet with its stream open; the receiver on loopback is told
`robot.silent` once, signed with the secret `fleet webhooks add` printed."""

from __future__ import annotations

import hashlib
import hmac
import json
import os
import subprocess
from pathlib import Path

import pytest

from tests.services.ingest.live_server import FLEET, LiveServer, start_robot
from tests.services.webhooks.conftest import Receiver
from tests.waiting import wait_for

pytestmark = [pytest.mark.sdk, pytest.mark.slow]
RUN = "silent-e2e-run"


def fleet(server: LiveServer, *args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "FLEET_DATA_DIR": str(server.data_dir)}  # its admin token, if auth is on
    return subprocess.run(
        [FLEET, "webhooks", *args, "--api-url", server.url], capture_output=True, text=True, timeout=120, env=env
    )


def test_a_quiet_robot_is_told_of_once_signed_and_logged(tmp_path: Path, receiver: Receiver):
    server = LiveServer(
        tmp_path / "data", webhook_hosts=f"127.0.0.1:{receiver.port}", silent_after_s="2", webhook_interval_s="0.5"
    ).start()
    robot = None
    try:
        added = fleet(server, "add", receiver.url, "--on", "robot.silent", "--on", "run.sealed")
        assert added.returncode == 0, added.stderr
        secret = added.stdout.strip()
        assert secret.startswith("whsec_") and "shown once" in added.stderr
        webhook_id = added.stderr.split()[1]
        listed = fleet(server, "ls", "--json")
        assert json.loads(listed.stdout)["webhooks"][0]["id"] == webhook_id and secret not in listed.stdout

        robot = start_robot("live", server.grpc_url, str(tmp_path / "copy.rrd"), RUN)
        assert robot.stdout is not None and robot.stdout.readline().strip() == "READY"  # then quiet, stream open
        wait_for(lambda: receiver.got, timeout=60, what="robot.silent at the receiver")
        (got,) = receiver.got
        assert (
            got.headers["x-fleet-signature"]
            == "sha256=" + hmac.new(secret.encode(), got.body, hashlib.sha256).hexdigest()
        )
        body = json.loads(got.body)
        assert (body["occurrence"], body["run_id"]) == ("robot.silent", RUN)

        shown = fleet(server, "deliveries", webhook_id, "--json")
        (delivery,) = json.loads(shown.stdout)["deliveries"]
        assert (delivery["state"], delivery["attempts"], delivery["last_status"]) == ("delivered", 1, 200)
        table = fleet(server, "deliveries", webhook_id)
        assert "robot.silent" in table.stdout and "delivered" in table.stdout
        assert len(receiver.got) == 1  # once per silence, however many passes ran since
        assert secret not in server.log.read_text(errors="replace")

        removed = fleet(server, "rm", webhook_id)
        assert removed.returncode == 0 and f"{webhook_id} ({receiver.url}): removed" in removed.stdout
        assert fleet(server, "rm", webhook_id).returncode == 1
    finally:
        if robot is not None:
            robot.kill()
            robot.wait(timeout=30)
        server.stop()
