"""Dataset snapshots' catalog rows: versions numbered one after the other and kept as written,
episodes with their chunk ids, and which snapshots use a run."""

from __future__ import annotations

import datetime as dt

import pytest
import sqlalchemy as sa
from sqlalchemy.orm import Session, sessionmaker

from catalog import datasets, queries
from catalog.datasets import EpisodeRecord, VersionFacts
from catalog.db import session_scope
from catalog.models import DatasetVersion, RunLifecycle
from core.errors import BadParameterError
from core.states import Tier
from tests.catalog.records import run_record

NOW = dt.datetime(2026, 12, 1, 12, tzinfo=dt.UTC)


def _episode(
    run_id: str, ids: list[bytes], split: str | None = None, window: tuple[int, int] | None = None
) -> EpisodeRecord:
    start, end = window if window is not None else (None, None)
    return EpisodeRecord(run_id, "robot-7", split, "frame", start, end, None, tuple(ids), 10 * len(ids))


def _facts(selection: str = '{"robot":[]}', runs: int = 1) -> VersionFacts:
    return VersionFacts(selection, "alice", NOW, 3, runs, "[]")


def _add(catalog: sessionmaker[Session], name: str, episodes: list[EpisodeRecord], selection: str = "{}") -> int:
    with session_scope(catalog, write=True) as session:
        return datasets.add_version(
            session, name, _facts(selection, len({e.run_id for e in episodes})), episodes
        ).version


def test_versions_count_up_and_keep_what_each_was(catalog: sessionmaker[Session]) -> None:
    first = _add(catalog, "picks", [_episode("run-1", [b"b" * 16, b"a" * 16])], '{"a":1}')
    second = _add(catalog, "picks", [_episode("run-2", [b"c" * 16])], '{"a":2}')
    other = _add(catalog, "other", [])
    assert (first, second, other) == (1, 2, 1)
    with session_scope(catalog) as session:
        one = datasets.version(session, "picks", 1)
        assert one is not None and one.selection == '{"a":1}' and one.episodes == 1 and one.chunks == 2
        assert one.bytes == 20 and one.rules_version == 3 and one.created_by == "alice"
        (episode,) = datasets.episodes(session, "picks", 1, -1, 10)
        assert episode.run_id == "run-1" and datasets.chunk_ids_of(episode) == [b"a" * 16, b"b" * 16]  # sorted
        assert episode.range_start is None and episode.range_end is None
        assert [v.version for v in datasets.versions(session, "picks")] == [2, 1]
        listed = [(s.name, v.version if v else None) for s, v in datasets.snapshots(session)]
        assert listed == [("other", 1), ("picks", 2)]
        assert datasets.version(session, "picks", 3) is None


def test_episodes_page_in_order(catalog: sessionmaker[Session]) -> None:
    episodes = [_episode(f"run-{i}", [bytes([i]) * 16], "train" if i % 2 else "val", (i, i + 5)) for i in range(7)]
    _add(catalog, "paged", episodes)
    with session_scope(catalog) as session:
        first = datasets.episodes(session, "paged", 1, -1, 3)
        rest = datasets.episodes(session, "paged", 1, first[-1].episode, 10)
        counts = datasets.split_counts(session, "paged", 1)
        assert [e.episode for e in first] == [0, 1, 2] and [e.episode for e in rest] == [3, 4, 5, 6]
        assert (rest[0].range_start, rest[0].range_end) == (3, 8)
    assert counts == {"train": {"runs": 3, "episodes": 3, "chunks": 3}, "val": {"runs": 4, "episodes": 4, "chunks": 4}}


def test_which_snapshots_use_a_run(catalog: sessionmaker[Session]) -> None:
    _add(catalog, "a", [_episode("run-1", []), _episode("run-1", []), _episode("run-2", [])])
    _add(catalog, "a", [_episode("run-1", [])])
    _add(catalog, "b", [_episode("run-2", [])])
    with session_scope(catalog) as session:
        used = datasets.snapshots_using(session, ["run-1", "run-2", "run-3"])
    assert used == {"run-1": ["a@1", "a@2"], "run-2": ["a@1", "b@1"]}
    assert datasets.describe_use(used["run-1"]) == "datasets a@1, a@2"
    assert datasets.describe_use(["x@1"]) == "dataset x@1"
    assert datasets.describe_use([f"x@{i}" for i in range(1, 8)], most=2) == "datasets x@1, x@2 and 5 more"


def test_missing_runs_say_why(catalog: sessionmaker[Session]) -> None:
    with session_scope(catalog, write=True) as session:
        queries.save_run(session, run_record("kept", tier=Tier.WARM), NOW)
        queries.save_run(session, run_record("gone", tier=Tier.DELETED), NOW)
        session.add(RunLifecycle(run_id="gone", prefix="p", promoted_at=NOW, deleted_at=NOW, deleted_by="bob"))
    with session_scope(catalog) as session:
        missing = datasets.missing_runs(session, ["kept", "gone", "never"])
    assert sorted(missing) == ["gone", "never"]
    assert missing["gone"].why == "run deleted on 2026-12-01 12:00 UTC by bob"
    assert "no longer has" in missing["never"].why


@pytest.mark.parametrize("name", ["", "-a", ".a", "a b", "a@1", "x" * 65, "a/b", "é"])
def test_a_name_is_checked(name: str) -> None:
    with pytest.raises(BadParameterError, match="'name'"):
        datasets.check_name(name)


def test_a_good_name_passes() -> None:
    assert datasets.check_name("pick-place_v2.1") == "pick-place_v2.1"
    assert datasets.check_name("x" * 64) == "x" * 64


def test_the_same_version_twice_is_refused_by_the_key(catalog: sessionmaker[Session]) -> None:
    """Two writers that both read the same highest version: the second's insert fails (and the
    service tries again), never two versions with one number."""
    _add(catalog, "race", [])
    with pytest.raises(sa.exc.IntegrityError), session_scope(catalog, write=True) as session:
        session.add(
            DatasetVersion(
                name="race",
                version=1,
                selection="{}",
                created_by="x",
                created_at=NOW,
                rules_version=None,
                episodes=0,
                runs=0,
                chunks=0,
                bytes=0,
                skipped="[]",
            )
        )
        session.flush()
