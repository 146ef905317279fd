"""This node's side of run ownership (see docs/scale-out.md).

A run's hot data has one home: the node that owns it in the catalog (`run_owners`). The first node
to receive a run claims it; a node receiving chunks of a run another live node owns relays them
there; a node that stops heart-beating for `lease_s` loses its runs to the next node that asks.
Every call here asks the catalog: call it off the event loop.
"""

from __future__ import annotations

import datetime as dt
import logging
import time
from dataclasses import dataclass

from sqlalchemy.orm import Session, sessionmaker

from catalog import nodes
from catalog.db import session_scope
from core.clock import utcnow
from core.errors import ConflictError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Lease:
    """This node owns the run, since the change of owner numbered `epoch`."""

    run_id: str
    epoch: int


@dataclass(frozen=True)
class Owner:
    """Another node, alive, owns the run: its chunks go there."""

    run_id: str
    node_id: str
    peer_addr: str


class Ownership:
    def __init__(
        self, catalog: sessionmaker[Session], node_id: str, peer_addr: str, lease_s: float, version: str
    ) -> None:
        self.catalog = catalog
        self.node_id = node_id
        self.peer_addr = peer_addr
        self.lease = dt.timedelta(seconds=lease_s)
        self.version = version
        self.started_at = utcnow()
        self.last_heartbeat: float | None = None  # time.monotonic() of the last one the catalog took

    @property
    def lease_s(self) -> float:
        return self.lease.total_seconds()

    def start(self) -> None:
        """Join the depot: wait for a process that heart-beat under this name (this node before a
        restart) to go quiet, and refuse to start if it does not (another live process has the name)."""
        deadline = time.monotonic() + self.lease_s + 2
        while True:
            with session_scope(self.catalog) as session:
                taken = nodes.node_alive(session, self.node_id, self.lease)
            if not taken:
                break
            if time.monotonic() > deadline:
                raise ConflictError(
                    f"a running depot process already uses the node name {self.node_id!r}: give each process "
                    "its own name (--node-id or FLEET_NODE_ID)"
                )
            log.info("waiting for the last process named %s to stop heart-beating", self.node_id)
            time.sleep(min(1.0, self.lease_s / 4))
        self.heartbeat()

    def heartbeat(self) -> None:
        with session_scope(self.catalog, write=True) as session:
            nodes.heartbeat(session, self.node_id, self.peer_addr, self.version, self.started_at)
        self.last_heartbeat = time.monotonic()

    def claim(self, run_id: str) -> Lease | Owner:
        """Own the run (it had no owner, or its owner's lease ran out), or learn who does."""
        with session_scope(self.catalog, write=True) as session:
            got = nodes.claim(session, run_id, self.node_id, self.lease)
        if got.taken_from is not None:
            log.warning("run %s taken over from node %s, which stopped heart-beating", run_id, got.taken_from)
        return Lease(run_id, got.epoch) if got.mine else Owner(run_id, got.node_id, got.peer_addr)

    def owner_elsewhere(self, run_id: str) -> Owner | None:
        """Another live node that owns the run (where its hot data is read), else None."""
        with session_scope(self.catalog) as session:
            found = nodes.live_owner(session, run_id, self.lease)
        if found is None or found.node_id == self.node_id:
            return None
        return Owner(run_id, found.node_id, found.peer_addr)

    def owner_down(self, run_id: str) -> Owner | None:
        """Another node that owns the run but no longer heart-beats (its hot data is on that node)."""
        with session_scope(self.catalog) as session:
            found = nodes.down_owner(session, run_id, self.lease)
        if found is None or found.node_id == self.node_id:
            return None
        return Owner(run_id, found.node_id, found.peer_addr)

    def holds(self, session: Session, lease: Lease) -> bool:
        """Within a caller's transaction: whether the lease still stands (locked until it commits)."""
        return nodes.holds(session, lease.run_id, self.node_id, lease.epoch)

    def release_in(self, session: Session, lease: Lease) -> bool:
        """Within a caller's transaction: give the run up."""
        return nodes.release(session, lease.run_id, self.node_id, lease.epoch)

    def release(self, lease: Lease, *, idle: bool = False) -> bool:
        """Give the run up; `idle`: only if no source here claimed it within the lease."""
        with session_scope(self.catalog, write=True) as session:
            return nodes.release(
                session, lease.run_id, self.node_id, lease.epoch, idle_for=self.lease if idle else None
            )

    def leases(self) -> dict[str, int]:
        """The runs the catalog says this node owns, with their epochs."""
        with session_scope(self.catalog) as session:
            return nodes.leases_of(session, self.node_id)
