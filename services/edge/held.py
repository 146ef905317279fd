"""`POST /v1/runs/RUN/held`: which of a robot's chunks of a run the depot holds, and how safely.

Each chunk id asked about is in one of three places: `missing` (the depot holds it nowhere),
`unsealed` (only in this node's hot tier: on one disk, not yet durable in the warm tier), or sealed
(in the warm tier's recording, as the `chunks.parquet` the catalog committed lists it; counted).
A robot's agent sends what is missing and keeps what is not sealed yet.

A cold or deleted run takes no data: nothing is missing or unsealed (`accepts_data` false), and
`sealed` counts what its sealed index lists (none for a deleted run, whose index is gone).

The hot run is looked at before the catalog: a chunk moves from hot to sealed (promotion commits
the catalog before the hot run is forgotten), never back, so a promotion meanwhile can make an
answer say unsealed for a chunk just sealed, but never missing for a chunk held.
"""

from __future__ import annotations

import hashlib
import logging
import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from catalog import queries
from catalog.db import session_scope
from core.errors import BadParameterError
from core.ids import check_id
from core.states import Tier
from services.auth.scopes import Principal, Scope
from services.edge.context import Edge, acting_robot, check_robot
from services.ingest.view import HotRunView
from services.sealed.index import chunk_ids_of
from services.sealed.write import INDEX
from services.storage.objectstore import ObjectNotFoundError

log = logging.getLogger(__name__)

MAX_CHUNK_IDS = 100_000
CHUNK_ID = re.compile(r"[0-9a-f]{32}")
TAKES_NO_DATA = (Tier.COLD, Tier.DELETED)


def parse_chunk_ids(given: Sequence[object]) -> list[str]:
    """The chunk ids asked about, each once, in the order given; one clear error naming the first
    that is not 32 lowercase hex digits, or a list empty or too long."""
    if not given:
        raise BadParameterError("chunk_ids", f"no chunk ids: ask about 1 to {MAX_CHUNK_IDS}")
    if len(given) > MAX_CHUNK_IDS:
        raise BadParameterError(
            "chunk_ids", f"{len(given)} chunk ids: at most {MAX_CHUNK_IDS} per request; ask in batches"
        )
    for i, item in enumerate(given):
        if not isinstance(item, str) or not CHUNK_ID.fullmatch(item):
            raise BadParameterError(
                "chunk_ids",
                f"item {i} ({str(item)[:40]!r}) is not a chunk id: 32 lowercase hex digits, the chunk's "
                "16-byte id (time_ns then inc, big-endian) as chunks.parquet writes it",
            )
    return list(dict.fromkeys(str(item) for item in given))


@dataclass(frozen=True)
class _Hot:
    """What this node's hot tier holds of the run, looked at first."""

    robot: str
    status: str
    held: frozenset[str]  # asked ids in its hot file
    sealed_before: frozenset[str]  # asked ids of the sealed copy it adds to (late data)


@dataclass(frozen=True)
class _Catalogued:
    robot: str
    tier: str
    status: str
    prefix: str | None  # of a sealed run
    index_sha256: str | None  # of the chunks.parquet the catalog committed


def held_answer(edge: Edge, principal: Principal, run_id: str, chunk_ids: Sequence[object]) -> dict[str, Any]:
    """The answer of `POST /v1/runs/RUN/held` (read scope, or a robot's ingest token for its own
    robot's runs and runs the depot does not know)."""
    check_id("run id", run_id)
    asked = {c: bytes.fromhex(c) for c in parse_chunk_ids(chunk_ids)}  # hex -> the id's bytes
    bound = acting_robot(principal, Scope.READ)
    hot = _hot_view(edge, run_id, asked)
    found = _catalog_view(edge, run_id)
    robot = hot.robot if hot is not None else found.robot if found is not None else None
    if robot is not None:
        check_robot(bound, f"run {run_id!r}", robot)
    tier = found.tier if found is not None else Tier.HOT if hot is not None else None
    status = hot.status if hot is not None else found.status if found is not None else None
    sealed_ids = _sealed_ids(edge, run_id, found)
    sealed = {c for c, raw in asked.items() if raw in sealed_ids}
    if hot is not None:
        sealed |= hot.sealed_before
    if tier in TAKES_NO_DATA:
        missing, unsealed = [], []
    else:
        in_hot = hot.held if hot is not None else frozenset()
        unsealed = [c for c in asked if c not in sealed and c in in_hot]
        missing = [c for c in asked if c not in sealed and c not in in_hot]
    return {
        "run": run_id,
        "robot": robot,
        "tier": tier,
        "status": status,
        "accepts_data": tier not in TAKES_NO_DATA,
        "missing": missing,
        "unsealed": unsealed,
        "sealed": len(sealed),
        # the process holding the unsealed chunks: when it changes (another node took the run over,
        # or the depot restarted), chunks it was said to hold are asked about again
        "holder": edge.ingest.incarnation if hot is not None and edge.ingest is not None else None,
    }


def _hot_view(edge: Edge, run_id: str, asked: dict[str, bytes]) -> _Hot | None:
    run: HotRunView | None = edge.ingest.hot_run(run_id) if edge.ingest is not None else None
    if run is None or edge.ingest is None:
        return None
    # membership tests only (no copy of the run's chunk ids): ingest adds to them on the event loop meanwhile
    held = frozenset(c for c, raw in asked.items() if run.in_hot_file(raw))
    before = run.adds_to.chunk_ids if run.adds_to is not None else frozenset()
    sealed_before = frozenset(c for c, raw in asked.items() if raw in before)
    return _Hot(run.robot_id or edge.ingest.default_robot, str(run.status), held, sealed_before)


def _catalog_view(edge: Edge, run_id: str) -> _Catalogued | None:
    with session_scope(edge.catalog) as session:
        run = queries.get_run(session, run_id)
        if run is None:
            return None
        life = queries.lifecycle(session, run_id)
        index = queries.run_objects(session, run_id).get(INDEX) if life is not None else None
        return _Catalogued(
            run.robot_id,
            run.tier,
            run.status,
            life.prefix if life is not None else None,
            index.sha256 if index is not None else None,
        )


def _sealed_ids(edge: Edge, run_id: str, found: _Catalogued | None) -> frozenset[bytes]:
    """The chunk ids of the run's committed sealed index (none for a run not sealed, deleted, or
    on a node that cannot read the warm store)."""
    if found is None or found.tier not in (Tier.WARM, Tier.COLD) or edge.warm is None:
        return frozenset()
    prefix, committed = found.prefix, found.index_sha256
    if prefix is None or committed is None:
        return frozenset()
    warm = edge.warm

    def load() -> frozenset[bytes] | None:
        try:
            data = warm.get_range(f"{prefix}/{INDEX}")
        except ObjectNotFoundError:
            log.warning("run %s: %s/%s is missing from the warm store", run_id, prefix, INDEX)
            return None
        # A sealing of late data that stopped before its catalog switch leaves a newer index in the
        # store: only the index the catalog committed counts (as for ingest's sealed lookup).
        if hashlib.sha256(data).hexdigest() != committed:
            return None
        return chunk_ids_of(data)

    return edge.sealed_ids.get(run_id, committed, load)
