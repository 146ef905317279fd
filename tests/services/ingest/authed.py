"""An auth-on `fleet serve` for the tests of who may stream runs in: its admin token, tokens made on
it, what it holds; and recordings written by the real rerun-sdk with a token in their fleet property."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx

from services.rrd.pb import sdk_comms_pb2
from tests.services.ingest.live_server import LiveServer
from tests.services.ingest.secrets_scan import places_holding
from tests.services.rrd.malformed import Seed

RECORD_SCRIPT = """
import sys
import numpy as np
import rerun as rr

path, run_id, robot, token, frames, where = sys.argv[1:7]
rec = rr.RecordingStream("fleet_auth", recording_id=run_id)
rec.save(path)
fleet = {**({"robot_id": robot} if robot != "-" else {}), **({"token": token} if token != "-" else {})}
if fleet and where == "first":
    rec.send_property("fleet", rr.AnyValues(**fleet))
    rec.flush()
for i in range(int(frames)):
    rec.set_time("frame", sequence=i)
    rec.log("/robot/battery", rr.Scalars([100.0 - i]))
    rec.log("/robot/camera", rr.Image(np.random.default_rng(i).integers(0, 255, (128, 128, 3), dtype=np.uint8)))
    rec.flush()
if fleet and where == "last":
    rec.send_property("fleet", rr.AnyValues(**fleet))
rec.flush()
"""


def recorded_requests(
    path: Path, run_id: str, *, robot: str = "-", token: str = "-", frames: int = 3, token_last: bool = False
) -> list[bytes]:
    """A recording by the real SDK (frames of a 48 KiB noise image and a scalar, each its own chunk), with
    `robot_id` and `token` in its fleet property ("-": left out), logged before the frames or after
    them; as the WriteMessagesRequests its GrpcSink would send."""
    args = [str(path), run_id, robot, token, str(frames), "last" if token_last else "first"]
    done = subprocess.run([sys.executable, "-c", RECORD_SCRIPT, *args], capture_output=True, timeout=120, check=False)
    assert done.returncode == 0, done.stderr.decode(errors="replace")
    return Seed.read(path).grpc_requests()


def chunks_in(requests: list[bytes]) -> int:
    """How many chunks (ArrowMsgs) the requests carry."""
    return sum(sdk_comms_pb2.WriteMessagesRequest.FromString(r).log_msg.HasField("arrow_msg") for r in requests)


@dataclass(frozen=True)
class Made:
    id: str
    token: str

    @property
    def signature(self) -> str:
        """The JWT's last part: the bytes that make it a token."""
        return self.token.rsplit(".", 1)[1]


class AuthedDepot:
    def __init__(self, live: LiveServer) -> None:
        self.live = live
        self.admin = (live.data_dir / "admin.token").read_text().strip()

    def get(self, path: str, token: str | None = None, **params: Any) -> httpx.Response:
        return httpx.get(f"{self.live.url}{path}", headers=self.bearer(token or self.admin), params=params, timeout=30)

    @staticmethod
    def bearer(token: str) -> dict[str, str]:
        return {"Authorization": f"Bearer {token}"}

    def token(self, *scopes: str, robot: str | None = None, expires_in_s: float | None = None) -> Made:
        body = {"scopes": list(scopes), "robot": robot, "name": robot or "-".join(scopes), "expires_in_s": expires_in_s}
        answer = httpx.post(f"{self.live.url}/v1/tokens", json=body, headers=self.bearer(self.admin), timeout=30)
        assert answer.status_code == 201, answer.text
        return Made(answer.json()["id"], answer.json()["token"])

    def revoke(self, made: Made) -> None:
        answer = httpx.delete(f"{self.live.url}/v1/tokens/{made.id}", headers=self.bearer(self.admin), timeout=30)
        assert answer.status_code == 200, answer.text

    def run(self, run_id: str) -> dict[str, Any] | None:
        """The run as GET /v1/runs/RUN shows it to an admin; None if the catalog has no such run."""
        answer = self.get(f"/v1/runs/{run_id}")
        if answer.status_code == 404:
            return None
        assert answer.status_code == 200, answer.text
        found: dict[str, Any] = answer.json()
        return found

    def wait_for_run(self, run_id: str, chunks: int = 1, last_frame: int | None = None) -> dict[str, Any]:
        """The run once the catalog shows at least `chunks` of its chunks (and its frame timeline
        up to `last_frame`)."""

        def filed() -> bool:
            run = self.run(run_id) or {}
            frames = [t["max"] for t in run.get("timelines", []) if t["name"] == "frame"]
            return run.get("chunks", 0) >= chunks and (last_frame is None or frames == [last_frame])

        self.live.wait_for(filed, what=f"run {run_id} filed")
        found = self.run(run_id)
        assert found is not None
        return found

    def listed(self, run_id: str) -> bool:
        """GET /v1/runs (as an admin) lists the run."""
        answer = self.get("/v1/runs", limit=1000)
        assert answer.status_code == 200, answer.text
        return run_id in {r["id"] for r in answer.json()["runs"]}

    def hot_folder(self, run_id: str) -> Path:
        return self.live.data_dir / "hot" / run_id

    def kept_nothing_of(self, run_id: str) -> bool:
        """No hot folder, no catalog row, not listed."""
        return not self.hot_folder(run_id).exists() and self.run(run_id) is None and not self.listed(run_id)

    def metric(self, name: str) -> float:
        """An unlabelled metric from /metrics (which takes a read token)."""
        for line in self.get("/metrics").text.splitlines():
            if line.startswith(name + " "):
                return float(line.split()[1])
        raise AssertionError(f"no metric {name}")

    def failures(self, surface: str, reason: str) -> float:
        """fleet_auth_failures_total{surface, reason} from /metrics."""
        for line in self.get("/metrics").text.splitlines():
            labels = (f'surface="{surface}"', f'reason="{reason}"')
            if line.startswith("fleet_auth_failures_total{") and all(label in line for label in labels):
                return float(line.rsplit(" ", 1)[1])
        return 0.0

    def places_holding(self, *secrets: str, open_catalog: bool = False) -> list[str]:
        """Every file under the data dir (catalog, hot tier, warm and cold tiers, ...), and the
        server's log, that holds one of `secrets`, looked for inside compressed chunks, Parquet and
        (`open_catalog`, once the server is stopped) the DuckDB catalog's rows too."""
        files = [p for p in self.live.data_dir.rglob("*") if p.is_file()] + [self.live.log]
        return places_holding(files, list(secrets), open_catalogs=open_catalog)
