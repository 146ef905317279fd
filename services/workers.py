"""`fleet serve --workers N`: N depot processes on this host sharing its two ports.

Python spends more per message than the work itself, so one process uses about one core. The
parent binds both ports (refusing at once, with one line, if either is taken), makes the first
admin token, and starts N workers that accept on those same sockets (the kernel hands each new
connection to one of them). Each worker is a node of its own on the shared catalog: its own hot tier
(`DATA_DIR/workers/wI`), node name (`NAME-wI`) and peer port, with the same run ownership as nodes on
other hosts, so a robot's stream and its upload may land on different workers. A worker that dies
is started again (it recovers its hot tier); the parent stops them all on SIGTERM or SIGINT.

The embedded DuckDB catalog has a single writer process: with it there is one process, as before
(`--workers` above 1 is refused, naming the fix).
"""

from __future__ import annotations

import asyncio
import logging
import multiprocessing
import os
import signal
import socket
import time
from multiprocessing.process import BaseProcess
from pathlib import Path
from types import FrameType

from pydantic import SecretStr
from sqlalchemy.orm import sessionmaker

from catalog.db import create_engine
from core.errors import InvalidArgumentError
from services.auth.bootstrap import announce_admin, ensure_admin_token, open_auth
from services.auth.keys import load_signing_keys
from services.server import claim_ports, node_id, shared_catalog
from services.settings import Settings
from services.startup import split_addr, worker_socket_path

log = logging.getLogger("fleet")

WORKERS_DIR = "workers"
RESTART_DELAY_S = 1.0
STOP_GRACE_S = 30.0


def worker_count(settings: Settings) -> int:
    """FLEET_WORKERS, or one per core on a shared catalog (one on the embedded catalog)."""
    shared = shared_catalog(settings)
    if settings.workers == 0:
        return (os.cpu_count() or 1) if shared else 1
    if settings.workers > 1 and not shared:
        raise InvalidArgumentError(
            f"--workers {settings.workers} needs a Postgres catalog (FLEET_CATALOG_URL=postgresql+psycopg://...): "
            "the embedded DuckDB catalog has a single writer process; leave --workers out, or set it to 1"
        )
    return settings.workers


def worker_settings(settings: Settings, index: int, key: SecretStr) -> Settings:
    """Worker `index`'s settings: its own hot tier, node name and peer port; the depot's signing key."""
    host, port = split_addr(settings.peer_addr)
    peer = f"{host}:{port + index if port else 0}"
    return settings.model_copy(
        update={
            "data_dir": settings.data_dir / WORKERS_DIR / f"w{index}",
            "node_id": f"{node_id(settings)}-w{index}",
            "peer_addr": f"[{host}]:{peer.rsplit(':', 1)[1]}" if ":" in host else peer,
            "auth_key": key,
            "workers": 1,
        }
    )


def run_worker(settings: Settings, sockets: tuple[socket.socket, socket.socket], siblings: list[Path]) -> None:
    """A worker process's life (started by `run_workers`)."""
    from services.rrd import limits
    from services.server import serve
    from services.startup import hold_data_dir

    logging.basicConfig(level=logging.INFO, format=f"%(levelname)s:     [{settings.node_id}] %(name)s: %(message)s")
    logging.getLogger("apscheduler").setLevel(logging.ERROR)
    limits.configure(settings.max_chunk_bytes, settings.decompress_budget_bytes)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent says when to stop (SIGTERM)
    with hold_data_dir(settings.data_dir):
        asyncio.run(serve(settings, sockets, siblings))


class Supervisor:
    """The parent: starts the workers, starts again one that dies, stops them all when asked."""

    def __init__(
        self, settings: Settings, count: int, ports: tuple[socket.socket, socket.socket] | None = None
    ) -> None:
        self.settings = settings
        self.ports = ports
        self.count = count
        self.stopping = False
        self.context = multiprocessing.get_context("spawn")  # no fork of a process holding threads
        self.procs: dict[int, BaseProcess] = {}

    def run(self) -> None:
        sockets = self.ports or claim_ports(self.settings)
        key = self._signing_key()
        for sock in sockets:
            sock.setblocking(False)
        signal.signal(signal.SIGTERM, self._stop)
        signal.signal(signal.SIGINT, self._stop)
        try:
            for index in range(self.count):
                self._start(index, sockets, key)
            self._watch(sockets, key)
        finally:
            self._stop_all()
            for sock in sockets:
                sock.close()

    def _signing_key(self) -> SecretStr:
        """The key every worker signs and checks tokens with; the first admin token made once, here."""
        key = SecretStr(load_signing_keys(self.settings).current.secret.decode())
        engine = create_engine(self.settings.catalog_url, self.settings.catalog_timeout_s)
        try:
            auth = open_auth(self.settings.model_copy(update={"auth_key": key}), sessionmaker(engine))
            announce_admin(ensure_admin_token(auth, self.settings.data_dir), self.settings.data_dir)
        finally:
            engine.dispose()
        return key

    def _start(self, index: int, sockets: tuple[socket.socket, socket.socket], key: SecretStr) -> None:
        siblings = [
            worker_socket_path(worker_settings(self.settings, other, key).data_dir)
            for other in range(self.count)
            if other != index
        ]
        proc = self.context.Process(
            target=run_worker,
            args=(worker_settings(self.settings, index, key), sockets, siblings),
            name=f"fleet-w{index}",
        )
        proc.start()
        self.procs[index] = proc

    def _watch(self, sockets: tuple[socket.socket, socket.socket], key: SecretStr) -> None:
        while not self.stopping:
            time.sleep(0.5)
            for index, proc in list(self.procs.items()):
                if not proc.is_alive() and not self.stopping:
                    log.error("worker %d stopped (exit code %s): starting it again", index, proc.exitcode)
                    time.sleep(RESTART_DELAY_S)
                    self._start(index, sockets, key)

    def _stop(self, signum: int, frame: FrameType | None) -> None:
        self.stopping = True

    def _stop_all(self) -> None:
        self.stopping = True
        for proc in self.procs.values():
            if proc.is_alive() and proc.pid is not None:
                os.kill(proc.pid, signal.SIGTERM)
        deadline = time.monotonic() + STOP_GRACE_S
        for proc in self.procs.values():
            proc.join(max(0.0, deadline - time.monotonic()))
            if proc.is_alive():
                proc.kill()
                proc.join()


def run_workers(settings: Settings, count: int, ports: tuple[socket.socket, socket.socket] | None = None) -> None:
    """`ports`: the gRPC and REST ports if the caller claimed them already (`fleet serve` does)."""
    Supervisor(settings, count, ports).run()
