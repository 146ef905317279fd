"""An MCAP upload, from a received file to a filed run: checked, identified by its content digest,
converted by the Rerun CLI within limits, and filed through the same path as an RRD upload.

Identity: conversion makes fresh chunk ids each time, so the file's digest says whether the depot
holds it (`mcap_digests`, one row per file): the same bag again is "already held". A bag whose data
section begins with the whole data section of one held (the same recording, written further) adds
the messages after it, converted alone, to that import's run. A bag whose first bytes are those of
a longer one held may be an earlier copy of it: that cannot be checked exactly (the depot keeps no
bag), so it is refused unless its run is named apart. A failed import's original goes to quarantine
and its digest is released, so a retry (after a rerun-sdk upgrade) or a new upload may try again.
"""

from __future__ import annotations

import json
import logging
import shutil
from dataclasses import dataclass
from pathlib import Path

from catalog import imports as rows
from catalog.db import session_scope
from catalog.models import Import
from core.errors import ConflictError, InvalidArgumentError
from core.ids import check_id
from services.imports import convert
from services.imports.mcap_file import RUN_KEYS, McapFacts, check_chunks, digests_at, inspect
from services.imports.mcap_tail import write_tail
from services.imports.records import Ledger, run_ids_of
from services.settings import Settings

log = logging.getLogger(__name__)

MIN_OUTPUT_BYTES = 256 << 20
SLOWEST_BYTES_PER_S = 2e6
DEFAULT_APPLICATION = "mcap"


@dataclass(frozen=True)
class Converter:
    """How this depot converts: its CLI, its limits, where it stages files."""

    cli: str | None
    timeout_s: float
    memory_bytes: int
    output_ratio: float
    staging: Path

    @classmethod
    def of(cls, settings: Settings) -> Converter:
        return cls(
            settings.rerun_cli,
            settings.mcap_timeout_s,
            settings.mcap_memory_mb << 20,
            settings.mcap_max_output_ratio,
            settings.data_dir / "imports",
        )

    def limits(self, size: int) -> convert.Limits:
        """A file's limits: its output at most `output_ratio` times its size, its time at most
        FLEET_MCAP_TIMEOUT_S and no more than a minute plus 2 MB/s (the CLI converts hundreds of MB/s;
        some corrupt files make it spin without end)."""
        output = max(MIN_OUTPUT_BYTES, int(size * self.output_ratio))
        timeout = min(self.timeout_s, 60.0 + size / SLOWEST_BYTES_PER_S)
        return convert.Limits(timeout, self.memory_bytes, output)

    def folder(self, import_id: str) -> Path:
        folder = self.staging / import_id
        folder.mkdir(parents=True, exist_ok=True)
        return folder


@dataclass(frozen=True)
class Asked:
    """What the uploader asked: a run id, an application id, the robot (its token's or named)."""

    run_id: str | None
    application: str | None
    robot: str | None


@dataclass(frozen=True)
class Held:
    """The file is held already, by this import, in this run."""

    import_id: str
    run_id: str


@dataclass(frozen=True)
class Converted:
    """The file claimed and converted: the recording to file, and into which run."""

    run_id: str
    application: str
    robot: str | None
    recording: Path
    digest: str
    extends: str | None  # the import whose recording this one continues


def prepare(
    ledger: Ledger, converter: Converter, import_id: str, original: Path, digest: str, asked: Asked
) -> Held | Converted:
    """Check, identify, claim and convert one MCAP file (blocking: call from a worker thread)."""
    facts = inspect(original)
    held = _held(ledger, digest)
    if held is not None:
        return held
    check_chunks(original, converter.memory_bytes // 2)
    extends, data_digest = _extends(ledger, original, facts)
    run_id, application = _names(asked, facts, digest, extends)
    if extends is None:
        _refuse_earlier_copy(ledger, facts, asked, run_id)
    robot = asked.robot or facts.named({"fleet": "robot_id", "foxglove": "deviceName"})
    holder = rows.claim(ledger.catalog, digest, import_id, run_id)
    if holder is not None:
        raise ConflictError(f"the same file is being filed by import {holder}: send it again once that is done")
    cli = convert.cli_path(converter.cli)
    ledger.update(
        import_id,
        state=rows.CONVERTING,
        digest=digest,
        head_digest=facts.head_digest,
        data_end=facts.data_end,
        data_digest=data_digest,
        run_ids=json.dumps([run_id]),
        application_id=application,
        robot_id=robot,
        converter=convert.cli_version(cli),
        reason=f"extends import {extends.id}" if extends is not None else None,
    )
    folder = converter.folder(import_id)
    source, messages = original, facts.messages
    if extends is not None:
        source = folder / "tail.mcap"
        messages = write_tail(original, extends.data_end or 0, facts.data_end, source)
        log.info("import %s extends %s: %d new messages of %d", import_id, extends.id, messages, facts.messages)
    recording = folder / "converted.rrd"
    convert.convert(
        cli,
        source,
        recording,
        recording_id=run_id,
        application_id=application,
        limits=converter.limits(source.stat().st_size),
        messages=messages,
    )
    return Converted(run_id, application, robot, recording, digest, extends.id if extends else None)


def _held(ledger: Ledger, digest: str) -> Held | None:
    with session_scope(ledger.catalog) as session:
        found = rows.holder(session, digest)
        if found is None:
            return None
        holder = rows.get(session, found.import_id)
        if holder is not None and holder.state == rows.FILED:
            return Held(found.import_id, found.run_id)
    raise ConflictError(f"the same file is being filed by import {found.import_id}: send it again once that is done")


def _extends(ledger: Ledger, original: Path, facts: McapFacts) -> tuple[Import | None, str]:
    """The held import this file continues (its data section is this file's first bytes), if any,
    and the digest of this file's own data section."""
    candidates: list[Import] = []
    if facts.head_digest is not None:
        with session_scope(ledger.catalog) as session:
            candidates = rows.extension_candidates(session, facts.head_digest, facts.data_end)
            for row in candidates:
                session.expunge(row)
    offsets = (*tuple(int(c.data_end or 0) for c in candidates), facts.data_end)
    with open(original, "rb") as f:
        found = digests_at(f, offsets)
    for candidate in candidates:  # longest first
        if found.get(int(candidate.data_end or 0)) == candidate.data_digest:
            return candidate, found[facts.data_end]
    return None, found[facts.data_end]


def _names(asked: Asked, facts: McapFacts, digest: str, extends: Import | None) -> tuple[str, str]:
    """The run id and application id the recording is filed under."""
    if extends is not None:
        held_run = _first_run(extends)
        if asked.run_id is not None and asked.run_id != held_run:
            raise InvalidArgumentError(
                f"this file continues the recording of import {extends.id}, filed as run {held_run}: "
                f"it adds to that run, not to {asked.run_id!r} (upload it without a run id)"
            )
        return held_run, extends.application_id or DEFAULT_APPLICATION
    run_id = asked.run_id or facts.named(RUN_KEYS) or f"mcap-{digest[:24]}"
    check_id("run id", run_id)
    application = asked.application or DEFAULT_APPLICATION
    return run_id, application


def _refuse_earlier_copy(ledger: Ledger, facts: McapFacts, asked: Asked, run_id: str) -> None:
    if facts.head_digest is None:
        return
    with session_scope(ledger.catalog) as session:
        twins = [(t.id, _first_run(t)) for t in rows.longer_twins(session, facts.head_digest, facts.data_end)]
    for twin_id, twin_run in twins:
        if asked.run_id is None or asked.run_id == twin_run:
            raise ConflictError(
                f"this file begins as import {twin_id} (run {twin_run}) does, which is longer: it looks like an "
                "earlier copy of that recording, whose messages the depot holds. It was not filed, so nothing is "
                "held twice; if it is another recording, upload it with a run id of its own"
            )


def _first_run(row: Import) -> str:
    runs = run_ids_of(row)
    return runs[0] if runs else ""


def cleanup(converter: Converter, import_id: str) -> None:
    shutil.rmtree(converter.staging / import_id, ignore_errors=True)
