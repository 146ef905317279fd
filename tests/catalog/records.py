"""A run's catalog record for tests, built in one place: each test names only the fields it is about.

`RunRecord` has fourteen fields without defaults; a test that wrote them all hid the two it meant
among twelve it did not, and every copy had to change when the record did.
"""

from __future__ import annotations

import datetime as dt
from typing import Any

from catalog.queries import RunRecord
from core.states import RunStatus, Tier

AT = dt.datetime(2026, 11, 21, 12, 0, tzinfo=dt.UTC)


def run_record(run_id: str = "run-1", at: dt.datetime = AT, **changes: Any) -> RunRecord:
    """A closed hot run of robot-7's `nav` application as ingest writes it: started, ended and last
    heard at `at` (its date that day), one chunk of one row, no properties, entities or timelines.
    `changes` set any field by name (`status="live"`, `entities=[...]`, even `id=...`)."""
    fields: dict[str, Any] = {
        "id": run_id,
        "robot_id": "robot-7",
        "application_id": "nav",
        "date": at.date(),
        "status": RunStatus.CLOSED,
        "tier": Tier.HOT,
        "started_at": at,
        "ended_at": at,
        "last_data_at": at,
        "sdk_version": "0.41.0",
        "chunks": 1,
        "rows": 1,
        "bytes": 10,
        "properties": {},
    }
    return RunRecord(**{**fields, **changes})
