"""Run ownership in the catalog (`catalog.nodes`), identical on DuckDB and Postgres."""

from __future__ import annotations

import datetime as dt

import sqlalchemy as sa
from sqlalchemy.orm import Session

from catalog import nodes
from catalog.models import DepotNode, RunOwner

LEASE = dt.timedelta(seconds=10)
T0 = dt.datetime(2026, 11, 23, tzinfo=dt.UTC)


def _beat(session: Session, node: str) -> None:
    nodes.heartbeat(session, node, f"{node}.internal:51235", "test", T0)
    session.flush()


def _age(session: Session, node: str, by: dt.timedelta) -> None:
    """As if `node` last heart-beat `by` ago."""
    row = session.get(DepotNode, node)
    assert row is not None
    row.heartbeat_at = nodes.db_now(session) - by
    session.flush()


def test_first_claim_wins_and_others_learn_the_owner(session: Session) -> None:
    _beat(session, "a")
    _beat(session, "b")
    first = nodes.claim(session, "run-1", "a", LEASE)
    assert first.mine and first.epoch == 1 and first.taken_from is None
    second = nodes.claim(session, "run-1", "b", LEASE)
    assert not second.mine
    assert (second.node_id, second.peer_addr, second.epoch) == ("a", "a.internal:51235", 1)
    again = nodes.claim(session, "run-1", "a", LEASE)
    assert again.mine and again.epoch == 1  # the owner asking again changes nothing


def test_a_silent_owner_loses_the_run_and_cannot_seal_it(session: Session) -> None:
    _beat(session, "a")
    _beat(session, "b")
    assert nodes.claim(session, "run-1", "a", LEASE).mine
    _age(session, "a", LEASE + dt.timedelta(seconds=1))
    taken = nodes.claim(session, "run-1", "b", LEASE)
    assert taken.mine and taken.epoch == 2 and taken.taken_from == "a"
    assert not nodes.holds(session, "run-1", "a", 1)  # its sealing commit would be refused
    assert nodes.holds(session, "run-1", "b", 2)
    assert not nodes.release(session, "run-1", "a", 1)
    assert nodes.leases_of(session, "b") == {"run-1": 2}
    assert nodes.leases_of(session, "a") == {}


def test_an_owner_the_catalog_never_saw_is_taken_over(session: Session) -> None:
    _beat(session, "b")
    session.add(RunOwner(run_id="run-9", node_id="gone", epoch=4, since=T0))
    session.flush()
    taken = nodes.claim(session, "run-9", "b", LEASE)
    assert taken.mine and taken.epoch == 5 and taken.taken_from == "gone"


def test_release_gives_the_run_up_once(session: Session) -> None:
    _beat(session, "a")
    assert nodes.claim(session, "run-1", "a", LEASE).mine
    assert nodes.release(session, "run-1", "a", 1)
    assert not nodes.release(session, "run-1", "a", 1)
    assert nodes.owner_of(session, ["run-1"]) == {}
    assert nodes.claim(session, "run-1", "a", LEASE).epoch == 1  # a fresh claim starts over


def test_an_idle_release_spares_a_run_claimed_within_the_lease(session: Session) -> None:
    _beat(session, "a")
    assert nodes.claim(session, "run-1", "a", LEASE).mine
    assert not nodes.release(session, "run-1", "a", 1, idle_for=LEASE)  # just claimed: kept
    session.execute(sa.update(RunOwner).values(since=nodes.db_now(session) - 2 * LEASE))
    assert nodes.release(session, "run-1", "a", 1, idle_for=LEASE)


def test_nodes_lists_who_is_alive_and_what_each_owns(session: Session) -> None:
    _beat(session, "a")
    _beat(session, "b")
    nodes.claim(session, "run-1", "a", LEASE)
    nodes.claim(session, "run-2", "a", LEASE)
    _age(session, "b", 2 * LEASE)
    listed = {n.id: n for n in nodes.nodes(session, LEASE)}
    assert listed["a"].alive and listed["a"].runs_owned == 2
    assert not listed["b"].alive and listed["b"].runs_owned == 0
    assert nodes.node_alive(session, "a", LEASE) and not nodes.node_alive(session, "b", LEASE)
    assert not nodes.node_alive(session, "nobody", LEASE)
