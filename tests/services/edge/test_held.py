"""`held`: which of a robot's chunks the depot holds, in which of missing, unsealed and sealed, for
runs it does not know, hot runs (live and closed), sealed runs, late data beside a sealed copy,
cold and deleted runs; who may ask; the chunk index read once per committed digest."""

from __future__ import annotations

import re
import secrets

import pytest

from core.errors import BadParameterError, PermissionDeniedError
from core.ids import UnsafeIdError
from services.edge.cache import SealedChunkIds
from services.edge.context import Edge
from services.edge.held import MAX_CHUNK_IDS, held_answer
from services.retention import archive
from services.retention.service import delete_run, promote_now
from services.rrd import iter_events
from services.sealed.index import IndexRow, to_parquet
from services.sealed.write import INDEX
from tests.services.edge.conftest import (
    ADMIN,
    OTHER_ROBOT,
    READER,
    ROBOT,
    RUN,
    WRITER,
    SdkRuns,
    add_run,
    chunk_ids,
    robot_token,
)
from tests.services.ingest import feeding
from tests.services.retention.conftest import Node

SDK = pytest.mark.sdk  # runs logged with the real SDK


def unknown_ids(count: int = 2) -> list[str]:
    return [secrets.token_hex(16) for _ in range(count)]


def ask(edge: Edge, ids: list[str], run_id: str = RUN, principal=READER) -> dict[str, object]:
    return held_answer(edge, principal, run_id, ids)


# --- what is asked --------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("ids", "says"),
    [
        ([], "no chunk ids: ask about 1 to 100000"),
        (["A" * 32], "item 0 ('AAAAAAAA"),  # upper case: not as chunks.parquet writes ids
        (["0" * 32, "0" * 31], "item 1 ('0000000000000000000000000000000')"),
        (["0" * 32, "g" * 32], "item 1"),
        ([12], "item 0 ('12') is not a chunk id: 32 lowercase hex digits"),
        (["0" * 32] * (MAX_CHUNK_IDS + 1), f"{MAX_CHUNK_IDS + 1} chunk ids: at most {MAX_CHUNK_IDS} per request"),
    ],
)
def test_chunk_ids_that_are_not_are_refused_by_name(edge: Edge, ids: list[object], says: str):
    with pytest.raises(BadParameterError) as info:
        held_answer(edge, READER, RUN, ids)
    assert info.value.parameter == "chunk_ids" and says in info.value.message
    assert info.value.http_status() == 422


def test_an_unsafe_run_id_is_refused(edge: Edge):
    with pytest.raises(UnsafeIdError, match=re.escape("run id '../x'")):
        held_answer(edge, READER, "../x", ["0" * 32])


def test_a_run_the_depot_does_not_know_has_every_chunk_missing(edge: Edge):
    ids = unknown_ids(3)
    for principal in (READER, WRITER, ADMIN, robot_token(), robot_token(OTHER_ROBOT)):
        answer = ask(edge, [*ids, ids[0]], "never-seen", principal)  # an id asked twice counts once
        assert answer == {
            "run": "never-seen",
            "robot": None,
            "tier": None,
            "status": None,
            "accepts_data": True,
            "missing": ids,
            "unsealed": [],
            "sealed": 0,
            "holder": None,  # no depot process holds any of it
        }


def test_a_robot_token_asks_about_its_own_robots_runs_only(edge: Edge, catalog):
    add_run(catalog, "theirs", robot=ROBOT)
    with pytest.raises(PermissionDeniedError) as info:
        ask(edge, unknown_ids(), "theirs", robot_token(OTHER_ROBOT))
    assert f"'{ROBOT}'" in info.value.message and f"'{OTHER_ROBOT}'" in info.value.message
    assert info.value.http_status() == 403
    assert ask(edge, unknown_ids(), "theirs", robot_token(ROBOT))["robot"] == ROBOT


# --- hot, sealed, late data, cold, deleted ----------------------------------------------------------


@SDK
def test_a_live_run_not_catalogued_yet_is_hot_and_unsealed(node: Node, node_edge: Edge, sdk_runs: SdkRuns):
    source = node.ingest.open_source(live=True)
    try:
        feeding.feed(node.ingest, source, iter_events(sdk_runs.first))
        ids, others = chunk_ids(sdk_runs.first), unknown_ids()
        answer = ask(node_edge, [*others, *ids])
        assert (answer["tier"], answer["status"], answer["robot"], answer["accepts_data"]) == (
            "hot",
            "live",
            ROBOT,
            True,
        )
        assert answer["unsealed"] == ids and answer["missing"] == others and answer["sealed"] == 0
        with pytest.raises(PermissionDeniedError, match=OTHER_ROBOT):
            ask(node_edge, ids, principal=robot_token(OTHER_ROBOT))  # hot here: its robot is known already
    finally:
        node.ingest.close_source(source)


@SDK
def test_a_run_is_unsealed_while_hot_then_sealed_once_promoted(node: Node, node_edge: Edge, sdk_runs: SdkRuns):
    node.upload(sdk_runs.first)
    ids, others = chunk_ids(sdk_runs.first), unknown_ids()
    hot = ask(node_edge, ids + others, principal=robot_token())
    assert (hot["tier"], hot["status"], hot["unsealed"], hot["missing"], hot["sealed"]) == (
        "hot",
        "closed",
        ids,
        others,
        0,
    )
    promote_now(node.retention, RUN)
    sealed = ask(node_edge, ids + others, principal=robot_token())
    assert (sealed["tier"], sealed["unsealed"], sealed["missing"], sealed["sealed"]) == ("warm", [], others, len(ids))
    assert sealed["accepts_data"] is True


@SDK
def test_late_data_beside_a_sealed_copy_is_unsealed_and_the_copy_sealed(node: Node, node_edge: Edge, sdk_runs: SdkRuns):
    node.upload(sdk_runs.first)
    promote_now(node.retention, RUN)
    node.upload(sdk_runs.later)  # the robot's file copy brings chunks the stream missed
    hot = node.ingest.hot_run(RUN)
    assert hot is not None and hot.adds_to is not None  # a hot run adding to the sealed one
    first, later, others = chunk_ids(sdk_runs.first), chunk_ids(sdk_runs.later), unknown_ids()
    answer = ask(node_edge, first + later + others)
    assert answer["tier"] == "warm" and answer["sealed"] == len(first)
    assert answer["unsealed"] == later and answer["missing"] == others
    promote_now(node.retention, RUN)  # sealed in with the rest: a new committed index
    again = ask(node_edge, first + later + others)
    assert (again["sealed"], again["unsealed"], again["missing"]) == (len(first) + len(later), [], others)


@SDK
def test_the_sealed_index_is_read_once_per_committed_digest(node: Node, sdk_runs: SdkRuns):
    edge = Edge(node.catalog, node.ingest, node.tiers.warm, node.clock, SealedChunkIds())
    node.upload(sdk_runs.first)
    promote_now(node.retention, RUN)
    ids = chunk_ids(sdk_runs.first)
    for _ in range(3):
        assert ask(edge, ids)["sealed"] == len(ids)
    assert edge.sealed_ids.loads == 1
    node.upload(sdk_runs.later)
    promote_now(node.retention, RUN)
    assert ask(edge, ids)["sealed"] == len(ids)
    assert edge.sealed_ids.loads == 2  # sealed again: another index, read afresh


@SDK
def test_an_index_the_catalog_did_not_commit_counts_for_nothing(node: Node, node_edge: Edge, sdk_runs: SdkRuns):
    """A sealing of late data that stopped before its catalog switch leaves a newer index in the
    store; until the catalog commits it, ingest takes those chunks again, and so held says."""
    node.upload(sdk_runs.first)
    promote_now(node.retention, RUN)
    ids = chunk_ids(sdk_runs.first)
    prefix = next(info.key for info in node.tiers.warm.list() if info.key.endswith(INDEX)).rsplit("/", 1)[0]
    node.tiers.warm.put(f"{prefix}/{INDEX}", to_parquet([IndexRow("chunk", "recording", 0, 1, bytes(16))]))
    answer = ask(node_edge, ids)
    assert answer["tier"] == "warm" and answer["sealed"] == 0 and answer["missing"] == ids
    assert node_edge.sealed_ids.loads == 1 and len(node_edge.sealed_ids) == 0  # not kept: asked again next time


@SDK
def test_a_cold_run_takes_no_data_and_counts_what_it_sealed(node: Node, node_edge: Edge, sdk_runs: SdkRuns):
    node.upload(sdk_runs.first)
    promote_now(node.retention, RUN)
    archive.archive(RUN, node.tiers, node.catalog, node.clock(), "test")
    ids, others = chunk_ids(sdk_runs.first), unknown_ids()
    answer = ask(node_edge, ids + others)
    assert (answer["tier"], answer["accepts_data"], answer["missing"], answer["unsealed"]) == ("cold", False, [], [])
    assert answer["sealed"] == len(ids)  # the others are neither: a cold run takes no data


@SDK
def test_a_deleted_run_takes_no_data_and_holds_nothing(node: Node, node_edge: Edge, sdk_runs: SdkRuns):
    node.upload(sdk_runs.first)
    promote_now(node.retention, RUN)
    delete_run(node.retention, RUN, "alice")
    answer = ask(node_edge, chunk_ids(sdk_runs.first))
    assert (answer["tier"], answer["accepts_data"], answer["missing"], answer["unsealed"], answer["sealed"]) == (
        "deleted",
        False,
        [],
        [],
        0,
    )
