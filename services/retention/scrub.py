"""Secrets that slipped into runs before ingest stripped them everywhere (rerun-sdk 0.23's
`rerun.component` spelling hid a robot's `fleet` token; blueprint stores' properties were kept as
sent): found in the hot and warm tiers and sealed again without them (`fleet catalog scrub-secrets`,
`POST /v1/catalog/scrub-secrets`).

Each warm run is read whole from the warm store and every property chunk goes through ingest's own
strip (`read_property_chunk`: the same chunk id, the secret fields left out). A run none of whose
chunks changes is left alone, so the scrub can be run again and again. A changed run is sealed
again by the writer promotion uses; its recording and index go back under the same keys, and the
catalog's sizes, hashes (what readers' caches are keyed by) and properties (read again without
the secret fields), a `scrub` event naming who asked and run.json are written in one transaction.
It runs under the retention job's lock, so no archive moves a run while it is rewritten. Cold runs
are not read: restore them, then scrub.

This node's hot runs are read from their hot files. A closed one holding such fields is promoted
now, by promotion itself (`fleet runs promote`: under the run's lock, refused if data arrives), and
its warm copy scrubbed as above: the hot file is append-only, indexed by offset and may be followed
by readers, so it is not rewritten in place. A live one is left for a scrub after it closes; hot
runs of other nodes are named for a scrub there.
"""

from __future__ import annotations

import logging
import tempfile
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from catalog import queries
from catalog.db import session_scope
from catalog.models import Run, RunLifecycle
from core.errors import ConflictError
from core.states import RunStatus, Tier
from services.facts.identity import SecretFields, read_property_chunk
from services.hot.read import read_events
from services.ingest.view import HotRunView
from services.retention.locks import job_lock
from services.retention.promote import download_warm
from services.retention.service import Retention, catalog_engine, promote_now
from services.rrd.chunk import chunk_meta
from services.rrd.decoder import iter_events
from services.rrd.manifest import is_property_entity
from services.rrd.messages import ArrowMessage, Event
from services.sealed.tiers import write_run_json
from services.sealed.write import INDEX, RECORDING, seal

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ScrubStep:
    run_id: str
    outcome: str  # clean | found (a dry run) | scrubbed | skipped
    detail: str
    tier: str = Tier.WARM  # where the run was read (a hot run promoted by the scrub: hot)

    def to_dict(self) -> dict[str, str]:
        return {"run": self.run_id, "tier": self.tier, "outcome": self.outcome, "detail": self.detail}


def scrub(
    ctx: Retention,
    secret_fields: SecretFields,
    *,
    dry_run: bool,
    actor: str,
    progress: Callable[[ScrubStep], None] | None = None,
) -> list[ScrubStep]:
    """Every run checked (this node's hot ones and warm ones read, cold ones and other nodes' hot
    ones named), one step each; a hot run with a sealed part is read in both tiers."""
    steps: list[ScrubStep] = []

    def done(step: ScrubStep) -> None:
        steps.append(step)
        if progress is not None:
            progress(step)

    with job_lock(catalog_engine(ctx), "retention") as got:
        if not got:
            raise ConflictError("the retention job is running in another process: scrub when it is done")
        hot_here = ctx.ingest.hot_runs() if ctx.ingest is not None else []
        for hot in hot_here:
            done(_scrub_hot(ctx, secret_fields, hot, dry_run, actor))
        promoted = {s.run_id for s in steps if s.outcome == "scrubbed"}  # their warm copy was scrubbed too
        with session_scope(ctx.catalog) as session:
            sealed = queries.sealed_runs(session, (Tier.WARM, Tier.COLD))
            runs = [(run.id, run.tier, life.prefix) for run, life in sealed if run.id not in promoted]
            elsewhere = sorted(set(queries.run_ids_in_tier(session, Tier.HOT)) - {h.run_id for h in hot_here})
        for run_id in elsewhere:
            done(ScrubStep(run_id, "skipped", "hot on another node: scrub there, or here once promoted", Tier.HOT))
        for run_id, tier, prefix in runs:
            done(_scrub_one(ctx, secret_fields, run_id, tier, prefix, dry_run, actor))
        return steps


def scrub_streamed(
    ctx: Retention, secret_fields: SecretFields, dry_run: bool, actor: str, emit: Callable[[dict[str, Any]], None]
) -> None:
    """`POST /v1/catalog/scrub-secrets`: one line per sealed run, then the counts."""
    steps = scrub(
        ctx, secret_fields, dry_run=dry_run, actor=actor, progress=lambda s: emit({"event": "run", **s.to_dict()})
    )
    counts = {k: sum(s.outcome == k for s in steps) for k in ("clean", "found", "scrubbed", "skipped")}
    emit({"event": "end", "dry_run": dry_run, **counts})


def _scrub_one(
    ctx: Retention,
    secret_fields: SecretFields,
    run_id: str,
    tier: str,
    prefix: str,
    dry_run: bool,
    actor: str,
) -> ScrubStep:
    if tier != Tier.WARM:
        return ScrubStep(
            run_id, "skipped", f"{tier}: not read; restore it (fleet runs restore), then scrub again", tier
        )
    with tempfile.TemporaryDirectory(prefix="fleet-scrub-") as tmp:
        base = Path(tmp) / "base.rrd"
        download_warm(ctx.tiers, f"{prefix}/{RECORDING}", base)
        found = _secret_properties(iter_events(base), secret_fields)
        if not found:
            return ScrubStep(run_id, "clean", "no secret-like property field")
        what = f"secret-like fields in {len(found)} property chunks ({', '.join(sorted(set(found)))})"
        if dry_run:
            return ScrubStep(run_id, "found", what + ": run without --dry-run to seal it again without them")
        # Sealed to a local file first: the upload happens below, once the run is known to be warm still.
        with open(Path(tmp) / RECORDING, "wb") as out:
            sealed = seal([_stripped(base, secret_fields)], out, run_id, ctx.clock(), None, secret_fields)
        with session_scope(ctx.catalog, write=True) as session:
            run = session.get(Run, run_id)
            life = session.get(RunLifecycle, run_id)
            if run is None or run.tier != Tier.WARM or life is None or life.prefix != prefix:
                return ScrubStep(run_id, "skipped", "it changed tier while being read: scrub again")
            with open(Path(tmp) / RECORDING, "rb") as fh:
                ctx.tiers.warm.put(f"{prefix}/{RECORDING}", fh)
            ctx.tiers.warm.put(f"{prefix}/{INDEX}", sealed.index)
            objects = queries.run_objects(session, run_id)
            objects[RECORDING].size, objects[RECORDING].sha256 = sealed.recording_size, sealed.recording_sha256
            objects[INDEX].size, objects[INDEX].sha256 = len(sealed.index), sealed.index_sha256
            run.bytes = sealed.recording_size
            # read again through the strip: a field made secret after the run was filed leaves its row too
            queries.replace_properties(session, run, sealed.facts.properties)
            detail = f"{what} removed; {len(sealed.chunk_ids)} chunks sealed again"
            queries.add_event(session, run_id, "scrub", ctx.clock(), actor, None, detail)
            session.flush()
            write_run_json(session, ctx.tiers.warm, run_id)
    log.info("scrubbed run %s: %s", run_id, detail)
    return ScrubStep(run_id, "scrubbed", detail)


def _scrub_hot(ctx: Retention, secret_fields: SecretFields, run: HotRunView, dry_run: bool, actor: str) -> ScrubStep:
    """A hot run of this node read from its file up to its size now; holding secret-like fields and
    closed, it is promoted and its warm copy scrubbed."""
    found = _secret_properties(read_events(run.path, run.size), secret_fields)
    if not found:
        return ScrubStep(run.run_id, "clean", "no secret-like property field", Tier.HOT)
    what = f"secret-like fields in {len(found)} property chunks ({', '.join(sorted(set(found)))})"
    live = run.status == RunStatus.LIVE or run.live_sources > 0
    if dry_run:
        then = "live: scrub once its stream has closed" if live else "run without --dry-run to promote it without them"
        return ScrubStep(run.run_id, "found", f"{what}: {then}", Tier.HOT)
    if live:
        return ScrubStep(run.run_id, "skipped", what + ": live, scrub again once its stream has closed", Tier.HOT)
    try:
        promote_now(ctx, run.run_id, actor)
    except Exception as exc:  # data arrived meanwhile, another node owns it now, a full disk: the next runs go on
        why = f"{what}: not promoted ({type(exc).__name__}: {exc}); scrub again"
        return ScrubStep(run.run_id, "skipped", why, Tier.HOT)
    with session_scope(ctx.catalog) as session:
        life = queries.lifecycle(session, run.run_id)
        prefix = life.prefix if life is not None else None
    if prefix is None:
        return ScrubStep(run.run_id, "skipped", f"{what}: promoted, but the catalog has no warm copy: scrub again")
    step = _scrub_one(ctx, secret_fields, run.run_id, Tier.WARM, prefix, False, actor)
    return ScrubStep(run.run_id, step.outcome, f"promoted to warm; {step.detail}", Tier.HOT)


def _secret_properties(events: Iterable[Event], secret_fields: SecretFields) -> list[str]:
    """The names of the property chunks among `events` that hold a secret-like field (one per chunk)."""
    found = []
    for event in events:
        if isinstance(event, ArrowMessage):
            meta = chunk_meta(event)
            if is_property_entity(meta.entity_path):
                prop = read_property_chunk(event, meta, secret_fields)
                if prop.message is not event:
                    found.append(prop.name or "recording")
    return found


def _stripped(path: Path, secret_fields: SecretFields) -> Iterator[Event]:
    """The events of `path`, property chunks without their secret fields (same chunk ids)."""
    for event in iter_events(path):
        if isinstance(event, ArrowMessage):
            meta = chunk_meta(event)
            if is_property_entity(meta.entity_path):
                yield read_property_chunk(event, meta, secret_fields).message
                continue
        yield event
