"""The warm and cold stores, where a sealed run's objects live, and its `run.json`."""

from __future__ import annotations

import datetime as dt
import hashlib
import json
from dataclasses import asdict, dataclass
from typing import Any

from sqlalchemy.orm import Session, sessionmaker

from catalog import queries
from catalog.db import session_scope
from catalog.queries import EntityRecord, RunRecord, TimelineRecord
from core.clock import aware
from core.errors import InvalidArgumentError
from core.states import ARCHIVED_IN_STORE, Tier
from services.facts.sealed import SealedInfo, SealedLookup
from services.sealed.index import CHUNK, from_parquet
from services.sealed.write import INDEX, RUN_JSON
from services.settings import Settings
from services.storage.objectstore import ObjectStore, Uploads, open_store, supports_archive

RUN_JSON_FORMAT = 1
# Storage classes whose objects cannot be read until restored; the others (STANDARD_IA,
# ONEZONE_IA, GLACIER_IR, ...) are cheaper to keep but read like any object.
NEEDS_RESTORE = frozenset({"GLACIER", "DEEP_ARCHIVE"})


def readable_when_cold(archive_mode: str | None) -> bool:
    """Whether a cold run's recording can be read where it lies without a restore."""
    return archive_mode not in (None, ARCHIVED_IN_STORE) and archive_mode not in NEEDS_RESTORE


@dataclass
class Tiers:
    warm: ObjectStore
    cold: ObjectStore
    cold_storage_class: str = ""  # archive in place to this S3 class; "" = copy to the cold store

    def archive_mode(self) -> str:
        return self.cold_storage_class or ARCHIVED_IN_STORE


def open_tiers(settings: Settings) -> Tiers:
    uploads = Uploads(settings.s3_part_bytes, settings.s3_upload_concurrency)
    warm = open_store(
        settings.warm_url,
        endpoint_url=settings.s3_endpoint_url,
        region=settings.s3_region,
        uploads=uploads,
        presign_endpoint_url=settings.direct_reads_endpoint_url,
        loop_reads=settings.s3_loop_reads,
    )
    cold = open_store(
        settings.cold_url, endpoint_url=settings.s3_endpoint_url, region=settings.s3_region, uploads=uploads
    )
    if settings.cold_storage_class and not supports_archive(warm):
        raise InvalidArgumentError(
            f"FLEET_COLD_STORAGE_CLASS={settings.cold_storage_class} needs an s3:// warm store "
            f"({settings.warm_url} has no storage classes): unset it to archive by copying to FLEET_COLD_URL"
        )
    return Tiers(warm, cold, settings.cold_storage_class)


def run_prefix(robot_id: str, date: dt.date, run_id: str) -> str:
    return f"{robot_id}/{date.isoformat()}/{run_id}"


@dataclass(frozen=True)
class RunJson:
    """A sealed run's `run.json`: its catalog record kept beside its recording, so that the catalog
    can be rebuilt from the bucket. Written from the catalog rows (`write_run_json`), read back by
    the rebuild (`parse_run_json`)."""

    record: RunRecord
    prefix: str
    objects: list[queries.ObjectRecord]
    pinned: bool
    sealed_at: dt.datetime
    pinned_by: str | None = None
    dataset_id: str | None = None  # its application's entry id in Rerun's catalog protocol (a copy)

    @property
    def key(self) -> str:
        return f"{self.prefix}/{RUN_JSON}"

    def encode(self) -> bytes:
        body = {
            "format": RUN_JSON_FORMAT,
            "prefix": self.prefix,
            "sealed_at": self.sealed_at.isoformat(),
            "pinned": self.pinned,
            "pinned_by": self.pinned_by if self.pinned else None,
            "dataset_id": self.dataset_id,
            "run": asdict(self.record),
            "objects": [asdict(o) for o in self.objects],
        }
        return json.dumps(body, indent=1, sort_keys=True, default=_json_default).encode()


def _json_default(value: Any) -> str:
    if isinstance(value, dt.datetime | dt.date):
        return value.isoformat()
    raise TypeError(f"{type(value).__name__} is not JSON")


def parse_run_json(data: bytes) -> RunJson:
    body = json.loads(data)
    if body.get("format") != RUN_JSON_FORMAT:
        raise ValueError(f"run.json format {body.get('format')!r} is not {RUN_JSON_FORMAT}")
    run = body["run"]
    sealed_at = dt.datetime.fromisoformat(body["sealed_at"])

    def when(value: str | None) -> dt.datetime | None:
        return dt.datetime.fromisoformat(value) if value else None

    record = RunRecord(
        id=run["id"],
        robot_id=run["robot_id"],
        application_id=run["application_id"],
        date=dt.date.fromisoformat(run["date"]),
        status=run["status"],
        tier=run["tier"],
        started_at=when(run["started_at"]),
        ended_at=when(run["ended_at"]),
        last_data_at=when(run["last_data_at"]) or sealed_at,
        sdk_version=run["sdk_version"],
        chunks=run["chunks"],
        rows=run["rows"],
        bytes=run["bytes"],
        properties=run["properties"],
        entities=[EntityRecord(**e) for e in run["entities"]],
        timelines=[TimelineRecord(**t) for t in run["timelines"]],
    )
    objects = [queries.ObjectRecord(**o) for o in body["objects"]]
    return RunJson(
        record,
        body["prefix"],
        objects,
        bool(body.get("pinned")),
        sealed_at,
        body.get("pinned_by"),
        body.get("dataset_id"),  # absent from run.json written before datasets existed
    )


def catalog_run_json(session: Session, run_id: str) -> RunJson | None:
    """A sealed run's `run.json` as its catalog rows say it now (None: the run is not sealed)."""
    record = queries.run_record(session, run_id)
    life = queries.lifecycle(session, run_id)
    if record is None or life is None:
        return None
    pinned, pinned_by = queries.pin_state(session, run_id)
    # in the catalog's order, which a rebuild then keeps (GET /v1/runs/RUN lists them so)
    objects = [
        queries.ObjectRecord(o.name, o.key, o.tier, o.size, o.sha256)
        for o in queries.run_objects(session, run_id).values()
    ]
    dataset_id = queries.dataset_entry_id(session, record.application_id)
    return RunJson(record, life.prefix, objects, pinned, aware(life.promoted_at), pinned_by, dataset_id)


def write_run_json(session: Session, warm: ObjectStore, run_id: str) -> None:
    """Put a sealed run's `run.json`, built from its catalog rows as `session` sees them. Called in
    the transaction that changes what it holds (promotion, pin, archive), before that commits: the
    bucket's copy is never older than the catalog, and a put that fails rolls the change back."""
    found = catalog_run_json(session, run_id)
    if found is not None:
        warm.put(found.key, found.encode())


def sealed_lookup(catalog: sessionmaker[Session], tiers: Tiers) -> SealedLookup:
    """For ingest: whether a run id not hot on this node was sealed, and which chunks it holds."""

    def lookup(run_id: str) -> SealedInfo | None:
        with session_scope(catalog) as session:
            run = queries.get_run(session, run_id)
            life = queries.lifecycle(session, run_id)
            if run is None or life is None or run.tier == Tier.HOT:
                return None
            tier, prefix, robot_id, date = Tier(run.tier), life.prefix, run.robot_id, run.date
            index = queries.run_objects(session, run_id).get(INDEX)
            committed = index.sha256 if index is not None else None
        chunk_ids: frozenset[bytes] = frozenset()
        if tier == Tier.WARM:
            data = tiers.warm.get_range(f"{prefix}/{INDEX}")
            # Sealing late data that stopped before its catalog switch leaves a newer index in the
            # store: the catalog has not recorded those chunks as sealed, so a hot copy of them is
            # kept (recover) and sealed again. Only the index the catalog recorded counts.
            if hashlib.sha256(data).hexdigest() == committed:
                rows = from_parquet(data)
                chunk_ids = frozenset(r.chunk_id for r in rows if r.kind == CHUNK and r.chunk_id is not None)
        return SealedInfo(tier, prefix, robot_id, date, chunk_ids)

    return lookup
