"""A full disk: promotion refuses to start rather than fill it, and a node whose disk filled up
anyway still starts (the space held in reserve is given to the catalog), answers, and refuses new
data cleanly. On a small tmpfs of its own, with the real `fleet serve`."""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from services.hot.reserve import RESERVE_FILE
from tests.services.ingest.live_server import LiveServer
from tests.services.retention.conftest import log_run

pytestmark = [pytest.mark.sdk, pytest.mark.slow]

DISK = 160 << 20
RESERVE = 24 << 20


@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[Path]:
    mount = tmp_path / "disk"
    mount.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={DISK}", "tmpfs", str(mount)], capture_output=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here (needs root): {done.stderr.decode().strip()}")
    try:
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], capture_output=True)


def fill(disk: Path, leave: int) -> Path:
    """A file that leaves about `leave` bytes free on the disk (0: fill it to the last byte)."""
    filler = disk / "filler"
    with open(filler, "ab") as fh:
        while (free := shutil.disk_usage(disk).free) > leave:
            try:
                fh.write(b"\0" * min(free - leave, 4 << 20))
                fh.flush()
            except OSError:
                break
    return filler


def upload(server: LiveServer, path: Path) -> httpx.Response:
    return httpx.post(f"{server.url}/v1/uploads", content=path.read_bytes(), timeout=60)


def test_promotion_refuses_to_fill_the_disk_and_a_full_disk_still_starts(small_disk: Path, tmp_path: Path):
    data = small_disk / "data"
    settings = {
        "min_free_bytes": str(32 << 20),
        "reserve_bytes": str(RESERVE),
        "promote_after_s": "3600",
        "durability": "always",
    }
    server = LiveServer(data, **settings).start()
    try:
        assert (data / RESERVE_FILE).stat().st_size == RESERVE  # held from the first start
        run = log_run(tmp_path / "big.rrd", "big-run", frames=40, entities=4, points=20_000)  # ~15 MB
        assert upload(server, run).status_code == 200
        size = (data / "hot" / "big-run" / "run.rrd").stat().st_size
        # room for neither the sealed copy nor the warm copy (the warm store is on this disk too)
        fill(small_disk, leave=RESERVE + size)
        free_before = shutil.disk_usage(small_disk).free
        refused = httpx.post(f"{server.url}/v1/runs/big-run/promote", timeout=60)
        assert refused.status_code == 507, refused.text
        assert "FLEET_RESERVE_BYTES" in refused.json()["message"]
        assert shutil.disk_usage(small_disk).free >= free_before - (1 << 20)  # nothing half-written left
        assert not (data / "hot" / "big-run" / "seal").exists()

        fill(small_disk, leave=0)  # another program fills the disk to the last byte
        server.kill()
    finally:
        server.stop()
    assert shutil.disk_usage(small_disk).free < 1 << 20

    restarted = LiveServer(data, **settings).start()  # the node starts on the full disk
    try:
        assert not (data / RESERVE_FILE).exists()  # the reserve was given to the catalog
        listed = httpx.get(f"{restarted.url}/v1/runs", timeout=30)
        assert listed.status_code == 200 and [r["id"] for r in listed.json()["runs"]] == ["big-run"]
        refused = upload(restarted, run)  # the same chunks: nothing new to write, so it is answered
        assert refused.status_code == 200 and refused.json()["chunks_new"] == 0
        other = log_run(tmp_path / "other.rrd", "other-run", frames=3)
        full = upload(restarted, other)
        assert full.status_code == 507 and "FLEET_MIN_FREE_BYTES" in full.json()["message"]

        (small_disk / "filler").unlink()  # space freed: the run is promoted, the reserve held again
        done = httpx.post(f"{restarted.url}/v1/runs/big-run/promote", timeout=120)
        assert done.status_code == 200, done.text
        assert httpx.get(f"{restarted.url}/v1/runs/big-run", timeout=30).json()["tier"] == "warm"
        restarted.wait_for(lambda: (data / RESERVE_FILE).exists(), what="the reserve held again")
    finally:
        restarted.stop()
        with contextlib.suppress(OSError):
            os.remove(small_disk / "filler")
