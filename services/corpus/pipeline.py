"""The corpus's moving parts on one node, built by the server: the live rules (ingest's chunk
observer), the sealing that gives sealed runs their final values (retention's `on_sealed`), and the
rules backfill (a job of the one schedule, and `fleet rules backfill`)."""

from __future__ import annotations

from dataclasses import dataclass

from services.corpus.backfill import RulesBackfill
from services.corpus.live import QUEUE_CHUNKS, LiveRules
from services.corpus.sealing import Sealing
from services.hot.read import HotRuns
from services.node import Node

BACKFILL_JOB = "rules-backfill"


@dataclass(frozen=True)
class CorpusPipeline:
    live: LiveRules
    sealing: Sealing
    backfill: RulesBackfill

    def attach(self, hot: HotRuns) -> None:
        """The node's ingest, once built (it takes `live` as its observer): where hot runs are read."""
        self.live.hot_runs = self.sealing.hot_runs = self.backfill.hot_runs = hot

    def start(self) -> None:
        self.live.start()
        self.sealing.start()

    def stop(self) -> None:
        self.sealing.stop()
        self.live.stop()


def corpus_pipeline(node: Node, *, queue_chunks: int = QUEUE_CHUNKS) -> CorpusPipeline:
    settings = node.settings
    live = LiveRules(
        node, max_events=settings.max_events_per_run, flush_s=settings.catalog_flush_s, queue_chunks=queue_chunks
    )
    return CorpusPipeline(
        live,
        Sealing(node, live, None, max_events=settings.max_events_per_run),
        RulesBackfill(node, None, settings.max_events_per_run, settings.rules_backfill_bytes_s),
    )
