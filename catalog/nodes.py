"""Catalog reads and writes of the depot's processes and of which one owns each hot run.

Every time here is the catalog's own clock (`now()` of the database), so nodes whose clocks
disagree still agree on whose heartbeat is stale. A node owns a run while its heartbeat is fresher
than the lease; another node may then take the run over, raising its epoch, so that the node that
lost it can tell (its sealing commit checks node and epoch, `holds`).
"""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass

import sqlalchemy as sa
from sqlalchemy.dialects.postgresql import insert
from sqlalchemy.orm import Session

from catalog.db import locks_rows
from catalog.models import DepotNode, RunOwner


@dataclass(frozen=True)
class Claim:
    """Who owns a run after a node asked for it: itself (`mine`), or another node that is alive."""

    run_id: str
    node_id: str
    epoch: int
    peer_addr: str
    mine: bool
    taken_from: str | None = None  # the node whose lease had run out, when this claim took it over


@dataclass(frozen=True)
class NodeRow:
    id: str
    peer_addr: str
    version: str
    started_at: dt.datetime
    heartbeat_at: dt.datetime
    alive: bool
    runs_owned: int


def _utc(value: dt.datetime) -> dt.datetime:
    return value.replace(tzinfo=dt.UTC) if value.tzinfo is None else value.astimezone(dt.UTC)


def db_now(session: Session) -> dt.datetime:
    """The catalog's clock."""
    value = session.execute(sa.select(sa.func.now())).scalar_one()
    assert isinstance(value, dt.datetime)
    return _utc(value)


def heartbeat(session: Session, node_id: str, peer_addr: str, version: str, started_at: dt.datetime) -> dt.datetime:
    """Say this node is alive now (and where it is reached); returns the catalog's time."""
    now = db_now(session)
    row = session.get(DepotNode, node_id, with_for_update=locks_rows(session))
    if row is None:
        session.execute(
            insert(DepotNode)
            .values(id=node_id, peer_addr=peer_addr, version=version, started_at=started_at, heartbeat_at=now)
            .on_conflict_do_nothing()
        )
    else:
        row.peer_addr, row.version, row.started_at, row.heartbeat_at = peer_addr, version, started_at, now
    return now


def node_alive(session: Session, node_id: str, lease: dt.timedelta) -> bool:
    """Whether a process heart-beats under this name."""
    return _alive(session.get(DepotNode, node_id), db_now(session), lease)


def _alive(node: DepotNode | None, now: dt.datetime, lease: dt.timedelta) -> bool:
    return node is not None and now - _utc(node.heartbeat_at) < lease


def claim(session: Session, run_id: str, node_id: str, lease: dt.timedelta) -> Claim:
    """The run's owner, made `node_id` if the run has none or its owner's lease ran out."""
    now = db_now(session)
    session.execute(
        insert(RunOwner).values(run_id=run_id, node_id=node_id, epoch=1, since=now).on_conflict_do_nothing()
    )
    row = session.get(RunOwner, run_id, with_for_update=locks_rows(session), populate_existing=True)
    assert row is not None
    if row.node_id == node_id:
        row.since = now  # claimed again just now: not idle (see `release`)
        return Claim(run_id, node_id, row.epoch, "", mine=True)
    owner = session.get(DepotNode, row.node_id)
    if _alive(owner, now, lease):
        assert owner is not None
        return Claim(run_id, owner.id, row.epoch, owner.peer_addr, mine=False)
    taken_from = row.node_id
    row.node_id, row.epoch, row.since = node_id, row.epoch + 1, now
    return Claim(run_id, node_id, row.epoch, "", mine=True, taken_from=taken_from)


def holds(session: Session, run_id: str, node_id: str, epoch: int) -> bool:
    """Whether `node_id` still owns the run with this epoch (locked until the transaction ends, so a
    takeover waits for a sealing commit that checked it)."""
    row = session.get(RunOwner, run_id, with_for_update=locks_rows(session), populate_existing=True)
    return row is not None and row.node_id == node_id and row.epoch == epoch


def release(session: Session, run_id: str, node_id: str, epoch: int, *, idle_for: dt.timedelta | None = None) -> bool:
    """Give the run up (sealed, or nothing of it is hot here); False if it was not ours any more.
    `idle_for`: only if it was not claimed (again) within that long, so that a source that just
    claimed the run and has not filed its first chunk yet keeps it."""
    row = session.get(RunOwner, run_id, with_for_update=locks_rows(session), populate_existing=True)
    if row is None or row.node_id != node_id or row.epoch != epoch:
        return False
    if idle_for is not None and _utc(row.since) >= db_now(session) - idle_for:
        return False
    session.delete(row)
    session.flush()
    return True


def leases_of(session: Session, node_id: str) -> dict[str, int]:
    """The runs `node_id` owns, with their epochs."""
    rows = session.execute(sa.select(RunOwner.run_id, RunOwner.epoch).where(RunOwner.node_id == node_id))
    return {run_id: epoch for run_id, epoch in rows}


def owner_of(session: Session, run_ids: list[str]) -> dict[str, str]:
    """The node owning each of these runs (runs nobody owns are left out)."""
    if not run_ids:
        return {}
    rows = session.execute(sa.select(RunOwner.run_id, RunOwner.node_id).where(RunOwner.run_id.in_(run_ids)))
    return {run_id: node for run_id, node in rows}


def live_owner(session: Session, run_id: str, lease: dt.timedelta) -> Claim | None:
    """The run's owner if one owns it and heart-beats; nothing is changed."""
    row = session.get(RunOwner, run_id)
    if row is None:
        return None
    owner = session.get(DepotNode, row.node_id)
    if not _alive(owner, db_now(session), lease):
        return None
    assert owner is not None
    return Claim(run_id, owner.id, row.epoch, owner.peer_addr, mine=False)


def down_owner(session: Session, run_id: str, lease: dt.timedelta) -> Claim | None:
    """The run's owner if one owns it and has stopped heart-beating (its hot copy is out of reach
    until it is back); nothing is changed."""
    row = session.get(RunOwner, run_id)
    if row is None:
        return None
    owner = session.get(DepotNode, row.node_id)
    if owner is None or _alive(owner, db_now(session), lease):
        return None
    return Claim(run_id, owner.id, row.epoch, owner.peer_addr, mine=False)


def nodes(session: Session, lease: dt.timedelta) -> list[NodeRow]:
    """Every node the catalog knows, alive or not, with how many runs each owns."""
    now = db_now(session)
    owned = {
        node: count
        for node, count in session.execute(sa.select(RunOwner.node_id, sa.func.count()).group_by(RunOwner.node_id))
    }
    return [
        NodeRow(
            n.id,
            n.peer_addr,
            n.version,
            _utc(n.started_at),
            _utc(n.heartbeat_at),
            _alive(n, now, lease),
            int(owned.get(n.id, 0)),
        )
        for n in session.scalars(sa.select(DepotNode).order_by(DepotNode.id))
    ]
