"""The robot's own tier: every message the SDK streams to the agent, or writes to a watched file,
filed into one `.rrd` per run under `SPOOL/runs/RUN/run.rrd`, each chunk once.

It is the depot's hot tier run on the robot (`HotStore` with its chunk index, fsync setting and
crash recovery) fed by the depot's own ingest rules (`IngestService` without a catalog): runs by
recording id, blueprints beside their recording, properties' secret fields never written.
"""

from __future__ import annotations

import datetime as dt
import logging
import shutil
from collections.abc import Sequence
from pathlib import Path

from core.errors import ConflictError
from core.states import RunStatus
from services.agent.settings import AgentSettings
from services.facts.identity import SecretFields
from services.hot.read import HotRecording
from services.hot.store import HotStore
from services.ingest.replay import ReplayHub
from services.ingest.service import IngestService
from services.ingest.source import Source
from services.ingest.view import HotRunView
from services.rrd import errors as rrd_errors
from services.rrd.decoder import iter_events
from services.rrd.messages import Event, StoreInfoMessage
from services.rules.observe import ChunkObserver

log = logging.getLogger("fleet.agent")

RUNS_DIR = "runs"
REPLAY_BYTES = 16 << 20  # recent live data for a viewer on the robot (`rerun --connect .../proxy`)
MAX_STREAMS = 64


class Spool:
    def __init__(self, settings: AgentSettings, observer: ChunkObserver | None = None) -> None:
        """`observer`: what sees each spooled chunk (the robot's trigger rules)."""
        self.root = settings.agent_spool
        self.hot = HotStore(
            self.root / RUNS_DIR,
            durability=settings.agent_durability,
            interval_ms=settings.group_commit_ms,
            min_free_bytes=settings.agent_min_free_bytes,
        )
        self.ingest = IngestService(
            self.hot,
            None,
            default_robot=settings.default_robot,
            max_streams=MAX_STREAMS,
            close_after=dt.timedelta(seconds=settings.close_after_s),
            replay=ReplayHub(REPLAY_BYTES),
            secret_fields=SecretFields(settings.secret_fields),
            observer=observer,
        )
        self._file_sources: dict[str, Source] = {}

    def recover(self) -> list[str]:
        recovered = self.ingest.recover()
        self.hot.start()
        return recovered

    def close(self) -> None:
        for source in self._file_sources.values():
            self.ingest.close_source(source)
        self._file_sources.clear()
        self.ingest.close()

    # --- runs ---------------------------------------------------------------------------------

    def runs(self) -> list[HotRunView]:
        return self.ingest.hot_runs()

    def run(self, run_id: str) -> HotRunView | None:
        return self.ingest.hot_run(run_id)

    def recording(self, run_id: str) -> HotRecording | None:
        return self.ingest.hot_recording(run_id)

    @staticmethod
    def is_open(run: HotRunView) -> bool:
        """More may come: a stream or a watched file still feeds it."""
        return run.status == RunStatus.LIVE or run.sources > 0

    def size(self) -> int:
        return sum(run.size for run in self.runs())

    def remove(self, run_id: str) -> bool:
        """Delete a run's spool copy (retention); False if it is not here or something still feeds it."""
        run = self.ingest.hot_run(run_id)
        if run is None or self.is_open(run):
            return False
        try:
            left = self.ingest.hand_over(run, doing="being removed", then="kept")
        except ConflictError:  # fed again since: kept
            return False
        shutil.rmtree(left.folder, ignore_errors=True)
        return True

    # --- watched files --------------------------------------------------------------------------

    def reading(self, path: Path) -> bool:
        """Whether messages of this file were filed since the agent started."""
        return str(path) in self._file_sources

    def file_events(
        self, path: Path, events: Sequence[Event], store_infos: Sequence[StoreInfoMessage] | None = None
    ) -> list[str]:
        """File messages read from a watched file: one source per file while it is read, so its
        SetStoreInfo, read once, names the store of the chunks that follow in later reads (a file
        resumed mid-way after a restart comes with its `store_infos`, read again from its start)."""
        key = str(path)
        source = self._file_sources.get(key)
        if source is None:
            source = self._file_sources[key] = self.ingest.open_source(live=False)
            for info in store_infos or ():
                self.ingest.accept(source, info)
        for event in events:
            self.ingest.accept(source, event)
        return list(source.report.runs)

    def file_done(self, path: Path) -> None:
        """The file is complete (or gone): its runs no longer count it among their sources."""
        source = self._file_sources.pop(str(path), None)
        if source is not None:
            self.ingest.close_source(source)


def store_infos(path: Path) -> list[StoreInfoMessage]:
    """The SetStoreInfo messages of a file (what names the stores of the chunks read after them)."""
    found: list[StoreInfoMessage] = []
    try:
        for event in iter_events(path):
            if isinstance(event, StoreInfoMessage):
                found.append(event)
    except (rrd_errors.RrdError, OSError) as exc:  # a torn tail: the infos before it are what counts
        log.debug("reading the store infos of %s stopped: %s", path, exc)
    return found
