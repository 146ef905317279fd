"""Warm -> cold, restores, and deletion. Each function is one run's step, safe to repeat.

Archive moves `recording.rrd` (the MB-scale object; archive classes bill a minimum size) either to
an S3 storage class in place, or to the cold store under the same key; `chunks.parquet` and
`run.json` stay warm, so a cold run can still be listed, planned and rebuilt. The catalog is
switched only once the cold copy is checked, and the warm copy removed only after that.
"""

from __future__ import annotations

import datetime as dt
import logging

from sqlalchemy.orm import Session, sessionmaker

from catalog import queries
from catalog.db import session_scope
from catalog.models import Run, RunLifecycle
from core.clock import aware
from core.errors import ConflictError
from core.states import ARCHIVED_IN_STORE, RestoreState, Tier
from services.analytics.extract import TABLES, partition_key
from services.sealed.tiers import Tiers, readable_when_cold, write_run_json
from services.sealed.write import RECORDING
from services.storage.objectstore import ArchiveStore, ObjectNotFoundError, StorageError, copy_object

log = logging.getLogger(__name__)


def _load(session: Session, run_id: str) -> tuple[Run, RunLifecycle]:
    run = queries.get_run(session, run_id)
    if run is None:
        raise queries.run_not_found(run_id)
    life = queries.lifecycle(session, run_id)
    if life is None:
        raise ConflictError(
            f"run {run_id!r} is {run.tier}, not sealed yet: it serves as it is, and "
            f"`fleet runs promote {run_id}` seals it now"
        )
    return run, life


def archive(run_id: str, tiers: Tiers, catalog: sessionmaker[Session], now: dt.datetime, policy: str) -> str:
    """Move a warm run's recording to the cold tier; returns what was done."""
    with session_scope(catalog) as session:
        run, life = _load(session, run_id)
        if run.tier != Tier.WARM:
            return f"already {run.tier}"
        key = f"{life.prefix}/{RECORDING}"
    if tiers.cold_storage_class:
        store = _archive_store(tiers)
        info = store.head(key)
        if (info.storage_class or "STANDARD") != tiers.cold_storage_class:  # else an attempt that died did it
            info = store.set_storage_class(key, tiers.cold_storage_class)
        if (info.storage_class or "STANDARD") != tiers.cold_storage_class:
            raise StorageError(
                f"{key} is in storage class {info.storage_class} after the move, not "
                f"{tiers.cold_storage_class}: the store refused the class; retried at the next run"
            )
        where = f"storage class {tiers.cold_storage_class}"
    else:
        copy_object(tiers.warm, tiers.cold, key)
        where = tiers.cold.url
    with session_scope(catalog, write=True) as session:
        run, life = _load(session, run_id)
        run.tier, run.updated_at = Tier.COLD, now
        life.archived_at, life.archive_mode = now, tiers.archive_mode()
        life.restore_state = life.restore_requested_at = life.restore_until = None
        objects = queries.run_objects(session, run_id)
        if RECORDING in objects:
            objects[RECORDING].tier = Tier.COLD
        queries.add_event(session, run_id, "archive", now, "retention", policy, f"recording to {where}")
        write_run_json(session, tiers.warm, run_id)  # says cold too (it stays warm, beside the index)
    if not tiers.cold_storage_class:
        tiers.warm.delete(key)  # only once the catalog points at the cold copy
    return f"archived to {where}"


def _archive_store(tiers: Tiers) -> ArchiveStore:
    return tiers.warm  # type: ignore[return-value]  # checked by open_tiers


def request_restore(
    run_id: str, tiers: Tiers, catalog: sessionmaker[Session], now: dt.datetime, actor: str, days: float
) -> RunLifecycle:
    """Start making a cold run readable for `days`: an S3 restore, or a copy back to warm (done by
    `advance_restore`, so a long copy runs in the background and survives a restart)."""
    with session_scope(catalog) as session:
        run, life = _load(session, run_id)
        if run.tier != Tier.COLD:
            raise ConflictError(f"run {run_id!r} is {run.tier}, not cold: it serves without a restore")
        if life.restore_state in (RestoreState.RESTORING, RestoreState.RESTORED) and (
            life.restore_until is None or aware(life.restore_until) > now
        ):
            session.expunge(life)  # read after the session closes: keep its loaded state
            return life  # already asked for: restoring twice changes nothing
        key = f"{life.prefix}/{RECORDING}"
        mode = life.archive_mode
    if readable_when_cold(mode):
        raise ConflictError(
            f"run {run_id!r} is kept in storage class {mode}, which reads without a restore: download it as it is"
        )
    if mode and mode != ARCHIVED_IN_STORE:
        _archive_store(tiers).restore(key, max(1, round(days)))
    with session_scope(catalog, write=True) as session:
        _, life = _load(session, run_id)
        life.restore_state, life.restore_requested_at = RestoreState.RESTORING, now
        life.restore_until = now + dt.timedelta(days=days)
        queries.add_event(session, run_id, "restore", now, actor, None, f"for {days:g} days")
        session.flush()
        session.expunge(life)
    return life


def advance_restore(run_id: str, tiers: Tiers, catalog: sessionmaker[Session], now: dt.datetime) -> str:
    """Move a restore on: finish the copy back (store mode) or notice S3 has restored the object;
    once `restore_until` has passed, drop the readable copy again."""
    with session_scope(catalog) as session:
        run, life = _load(session, run_id)
        tier, state, mode, key = run.tier, life.restore_state, life.archive_mode, f"{life.prefix}/{RECORDING}"
        until = aware(life.restore_until) if life.restore_until else None
    if tier != Tier.COLD or state is None:
        return "nothing to do"
    if until is not None and until <= now:
        if mode == ARCHIVED_IN_STORE:
            tiers.warm.delete(key)
        _set_restore(catalog, run_id, None, now, "restore ended")
        return "restore ended"
    if state == RestoreState.RESTORED:
        return "restored"
    if mode == ARCHIVED_IN_STORE:
        copy_object(tiers.cold, tiers.warm, key)
    elif tiers.warm.head(key).restore != "restored":
        return "restore under way"
    _set_restore(catalog, run_id, RestoreState.RESTORED, now, "restored")
    return "restored"


def _set_restore(
    catalog: sessionmaker[Session], run_id: str, state: RestoreState | None, now: dt.datetime, detail: str
) -> None:
    with session_scope(catalog, write=True) as session:
        _, life = _load(session, run_id)
        life.restore_state = state
        if state is None:
            life.restore_requested_at = life.restore_until = None
        queries.add_event(session, run_id, "restore", now, "retention", None, detail)


def delete(
    run_id: str, tiers: Tiers, catalog: sessionmaker[Session], now: dt.datetime, actor: str, policy: str | None
) -> str:
    """Delete a sealed run: its analytics rows leave the catalog first (SQL reads the files the catalog
    lists, so none of them may be missing), then every object under its prefix in both stores, then
    the run is marked deleted; the tombstone keeps who, when and which policy. Safe to repeat."""
    with session_scope(catalog, write=True) as session:
        run, life = _load(session, run_id)
        if run.tier == Tier.DELETED:
            return "already deleted"
        prefix = life.prefix
        analytics = queries.replace_analytics(session, run_id, [])
        # where they are, if an earlier attempt already took them out of the catalog
        analytics |= {partition_key(t, run.robot_id, run.date.isoformat(), run_id) for t in TABLES}
    removed = 0
    for store in (tiers.warm, tiers.cold) if tiers.cold is not tiers.warm else (tiers.warm,):
        for info in list(store.list(prefix + "/")):
            try:
                store.delete(info.key)
            except ObjectNotFoundError:
                continue
            removed += 1
    for key in sorted(analytics):  # the run's rows in the analytics tables (warm store, partitioned elsewhere)
        try:
            tiers.warm.head(key)
        except ObjectNotFoundError:
            continue
        tiers.warm.delete(key)
        removed += 1
    with session_scope(catalog, write=True) as session:
        run, life = _load(session, run_id)
        queries.mark_deleted(session, run_id, now)
        life.deleted_at, life.deleted_by, life.deleted_policy = now, actor, policy
        life.restore_state = life.restore_requested_at = life.restore_until = None
        queries.replace_objects(session, run_id, [])
        queries.add_event(session, run_id, "delete", now, actor, policy, f"{removed} objects removed")
    return f"deleted ({removed} objects)"
