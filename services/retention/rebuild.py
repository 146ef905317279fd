"""Disaster recovery: an empty catalog rebuilt from the stores' `run.json` and objects.

Every sealed run left its catalog record beside its recording; the tier is read from where the
recording is now (warm, an archive storage class, or the cold store), not from the record.
Runs already in the catalog are left alone, so a rebuild can be repeated or resumed.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import logging
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

from sqlalchemy.orm import Session, sessionmaker

from catalog import queries
from catalog.db import session_scope
from catalog.models import RunLifecycle
from core.clock import aware
from core.states import ARCHIVED_IN_STORE, Tier
from services.sealed.tiers import RunJson, Tiers, parse_run_json
from services.sealed.write import INDEX, RECORDING, RUN_JSON
from services.storage.objectstore import ObjectInfo, ObjectNotFoundError

log = logging.getLogger(__name__)

ARCHIVE_CLASSES = frozenset({"GLACIER", "DEEP_ARCHIVE", "GLACIER_IR", "STANDARD_IA", "ONEZONE_IA"})


@dataclass(frozen=True)
class RebuildStep:
    run_id: str
    outcome: str  # added | present | skipped
    detail: str

    def to_dict(self) -> dict[str, str]:
        return {"run": self.run_id, "outcome": self.outcome, "detail": self.detail}


def run_files(tiers: Tiers) -> Iterator[str]:
    """Keys of every run.json in the warm store (ROBOT/DATE/RUN/run.json)."""
    for info in tiers.warm.list():
        parts = info.key.split("/")
        if len(parts) == 4 and parts[3] == RUN_JSON:
            yield info.key


def rebuild(
    catalog: sessionmaker[Session],
    tiers: Tiers,
    now: dt.datetime,
    progress: Callable[[RebuildStep], None] | None = None,
) -> list[RebuildStep]:
    steps = []
    for key in run_files(tiers):
        step = _rebuild_one(catalog, tiers, key, now)
        steps.append(step)
        if progress is not None:
            progress(step)
    return steps


def rebuild_streamed(
    catalog: sessionmaker[Session],
    tiers: Tiers,
    clock: Callable[[], dt.datetime],
    emit: Callable[[dict[str, Any]], None],
) -> None:
    """`POST /v1/catalog/rebuild`: rebuild, saying so as it goes (one line per run found, then the counts)."""
    steps = rebuild(catalog, tiers, clock(), lambda step: emit({"event": "run", **step.to_dict()}))
    counts = {k: sum(s.outcome == k for s in steps) for k in ("added", "present", "skipped")}
    emit({"event": "end", **counts})


def _rebuild_one(catalog: sessionmaker[Session], tiers: Tiers, key: str, now: dt.datetime) -> RebuildStep:
    run_id = key.split("/")[2]
    try:
        found = parse_run_json(tiers.warm.get_range(key))
    except (ValueError, KeyError, TypeError) as exc:
        return RebuildStep(run_id, "skipped", f"{key} is not a run record ({exc})")
    with session_scope(catalog) as session:
        if queries.get_run(session, found.record.id) is not None:
            return RebuildStep(run_id, "present", "already in the catalog")
    where = _recording(tiers, found.prefix)
    if where is None:
        return RebuildStep(run_id, "skipped", f"{found.prefix}/{RECORDING} is in neither store")
    try:
        tiers.warm.head(f"{found.prefix}/{INDEX}")
    except ObjectNotFoundError:
        return RebuildStep(run_id, "skipped", f"{found.prefix}/{INDEX} is missing")
    tier, mode, info = where
    _insert(catalog, found, tier, mode, info, now)
    return RebuildStep(run_id, "added", f"{tier}, {found.record.chunks} chunks, {found.record.bytes} bytes")


def _recording(tiers: Tiers, prefix: str) -> tuple[Tier, str | None, ObjectInfo] | None:
    key = f"{prefix}/{RECORDING}"
    try:
        info = tiers.warm.head(key)
        if info.storage_class in ARCHIVE_CLASSES:
            return Tier.COLD, info.storage_class, info
        return Tier.WARM, None, info
    except ObjectNotFoundError:
        pass
    try:
        return Tier.COLD, ARCHIVED_IN_STORE, tiers.cold.head(key)
    except ObjectNotFoundError:
        return None


def _restore_dataset(session: Session, name: str, now: dt.datetime, entry_id: str | None) -> None:
    """The dataset of application `name` with the entry id its run.json kept. A run.json from before
    datasets keeps none, and the dataset is given a new one; a later run.json's kept id replaces it
    if this same rebuild (`now`) made it, whatever order the store lists them in."""
    dataset = queries.ensure_dataset(session, name, now, entry_id)
    if entry_id and dataset.entry_id != entry_id and aware(dataset.created_at) == now:
        dataset.entry_id = entry_id


def _insert(
    catalog: sessionmaker[Session], found: RunJson, tier: Tier, mode: str | None, info: ObjectInfo, now: dt.datetime
) -> None:
    record = dataclasses.replace(found.record, tier=tier)
    objects = [dataclasses.replace(o, tier=tier) if o.name == RECORDING else o for o in found.objects]
    with session_scope(catalog, write=True) as session:
        if record.application_id:  # the entry id Rerun's clients know it by, kept in run.json
            _restore_dataset(session, record.application_id, now, found.dataset_id)
        queries.save_run(session, record, now)
        run = queries.get_run(session, record.id)
        assert run is not None
        run.pinned, run.pinned_by = found.pinned, found.pinned_by if found.pinned else None
        session.add(
            RunLifecycle(
                run_id=record.id,
                prefix=found.prefix,
                promoted_at=found.sealed_at,
                archived_at=info.last_modified if tier == Tier.COLD else None,
                archive_mode=mode,
            )
        )
        queries.replace_objects(session, record.id, objects)
        queries.add_event(session, record.id, "rebuild", now, "catalog rebuild", None, f"from {found.prefix}/")
