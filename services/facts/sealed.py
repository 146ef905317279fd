"""What is known of a run that left the hot tier: `SealedInfo`, given by the sealed tiers
(`sealed.tiers.sealed_lookup`) to ingest, which files data that comes for it later."""

from __future__ import annotations

import datetime as dt
from collections.abc import Callable
from dataclasses import dataclass

from core.states import Tier


@dataclass(frozen=True)
class SealedInfo:
    """What the catalog knows of a run that left the hot tier (given by the retention side)."""

    tier: Tier  # warm, cold or deleted
    prefix: str  # ROBOT/YYYY-MM-DD/RUN
    robot_id: str
    date: dt.date
    chunk_ids: frozenset[bytes]


# Asked (off the event loop) whether a run id not hot here was sealed before, and where.
SealedLookup = Callable[[str], SealedInfo | None]
