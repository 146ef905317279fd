"""`/metrics` of a host running several workers (`fleet serve --workers N`): one exposition for the
whole host, whichever worker the scrape reaches. The worker asks its siblings for theirs over their
private Unix sockets (`?local=true`: their own only) and adds them up: counters, gauges and histogram
buckets summed per name and labels; the earliest `_created`; info metrics taken once."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Iterator
from pathlib import Path

import httpx
from prometheus_client import CollectorRegistry, generate_latest
from prometheus_client.metrics_core import Metric
from prometheus_client.parser import text_string_to_metric_families
from prometheus_client.registry import Collector

log = logging.getLogger(__name__)

SIBLING_TIMEOUT_S = 5.0


async def sibling_expositions(paths: list[Path], token: str | None) -> list[str]:
    """What each sibling worker answers for its own figures (one that does not answer is left out,
    and logged)."""

    async def one(path: Path) -> str | None:
        headers = {"authorization": f"Bearer {token}"} if token else {}
        transport = httpx.AsyncHTTPTransport(uds=str(path))
        try:
            async with httpx.AsyncClient(transport=transport, timeout=SIBLING_TIMEOUT_S) as client:
                answer = await client.get("http://worker/metrics", params={"local": "true"}, headers=headers)
                answer.raise_for_status()
                return answer.text
        except httpx.HTTPError as exc:
            log.warning("worker at %s left out of /metrics: %s", path, exc)
            return None

    found = await asyncio.gather(*(one(p) for p in paths))
    return [text for text in found if text is not None]


class _Merged(Collector):
    def __init__(self, families: list[Metric]) -> None:
        self.families = families

    def collect(self) -> Iterator[Metric]:
        yield from self.families


def merge_expositions(texts: list[str]) -> bytes:
    """One exposition adding up several processes' (see the module's docstring)."""
    families: dict[str, Metric] = {}
    values: dict[str, dict[tuple[str, tuple[tuple[str, str], ...]], float]] = {}
    for text in texts:
        for family in text_string_to_metric_families(text):
            families.setdefault(family.name, Metric(family.name, family.documentation, family.type))
            samples = values.setdefault(family.name, {})
            for sample in family.samples:
                key = (sample.name, tuple(sorted(sample.labels.items())))
                if key not in samples:
                    samples[key] = sample.value
                elif sample.name.endswith("_created"):
                    samples[key] = min(samples[key], sample.value)
                elif family.type != "info" and not sample.name.endswith("_info"):
                    samples[key] += sample.value
    out = []
    for name, family in families.items():
        for (sample_name, labels), value in values[name].items():
            family.add_sample(sample_name, dict(labels), value)
        out.append(family)
    registry = CollectorRegistry(auto_describe=False)
    registry.register(_Merged(out))
    return generate_latest(registry)
