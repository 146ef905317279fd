"""Run identity (DESIGN.md section 4): ids safe for object keys, the robot, the date, and
recording properties with their secrets removed.

Property chunks (`/__properties/...`) are the only chunks whose data columns are read: they are
small, static, and hold what identifies a run (`rr.send_property("fleet", rr.AnyValues(robot_id=...))`).
"""

from __future__ import annotations

import datetime as dt
import re
from dataclasses import dataclass
from typing import Any

import pyarrow as pa

from services.errors import ErrorCode, FleetError
from services.rrd.chunk import ChunkMeta, read_chunk, with_batch
from services.rrd.manifest import PROPERTIES_ENTITY
from services.rrd.messages import ArrowMessage

SAFE_ID = re.compile(r"[A-Za-z0-9._-]{1,128}")
SECRET_FIELDS = frozenset({"token"})  # never written to disk nor served
IDENTITY_PROPERTY = "fleet"
ROBOT_FIELD = "robot_id"
START_TIME_COMPONENT = "RecordingInfo:start_time"


class UnsafeIdError(FleetError):
    code = ErrorCode.INVALID_ARGUMENT


def check_id(kind: str, value: str) -> str:
    """`value` if it can be part of an object key, else UnsafeIdError naming it and the rule."""
    if not SAFE_ID.fullmatch(value) or value in (".", ".."):
        raise UnsafeIdError(
            f"{kind} {value!r} cannot be used in object keys: use 1 to 128 characters from "
            "A-Z a-z 0-9 . _ - (for a recording id: rr.init(..., recording_id=...))"
        )
    return value


def is_property_entity(entity_path: str) -> bool:
    return entity_path == PROPERTIES_ENTITY or entity_path.startswith(PROPERTIES_ENTITY + "/")


def property_name(entity_path: str) -> str:
    """`/__properties/fleet` -> `fleet`; `/__properties` (RecordingInfo) -> ``."""
    return entity_path[len(PROPERTIES_ENTITY):].strip("/")


@dataclass
class PropertyChunk:
    """A property chunk as filed: its message (secrets removed) and the values it carries."""

    message: ArrowMessage
    name: str
    values: dict[str, Any]  # field (component) -> last value logged, secrets removed
    had_secret: bool


def read_property_chunk(msg: ArrowMessage, meta: ChunkMeta) -> PropertyChunk:
    """Decode a property chunk; if it holds a secret field, return a re-encoded message without it
    (same chunk id, so the chunk is still stored exactly once)."""
    batch = read_chunk(msg)
    secret = [i for i, f in enumerate(batch.schema) if _component(f) in SECRET_FIELDS]
    values: dict[str, Any] = {}
    for i, fld in enumerate(batch.schema):
        kind = (fld.metadata or {}).get(b"rerun:kind")
        if i in secret or kind != b"data":
            continue
        column = batch.column(i)
        for row in range(len(column) - 1, -1, -1):  # the newest non-null value wins
            if column[row].is_valid:
                values[_component(fld)] = _plain(column[row].as_py())
                break
    name = property_name(meta.entity_path)
    if not secret:
        return PropertyChunk(msg, name, values, had_secret=False)
    kept = batch.select([i for i in range(batch.num_columns) if i not in secret])
    return PropertyChunk(with_batch(msg, kept), name, values, had_secret=True)


def _component(fld: pa.Field) -> str:
    name: bytes = (fld.metadata or {}).get(b"rerun:component", fld.name.encode())
    return name.decode()


def _plain(value: Any) -> Any:
    """A property value as JSON can hold it: one-element lists unwrapped, bytes as hex."""
    if isinstance(value, list) and len(value) == 1:
        value = value[0]
    if isinstance(value, bytes):
        return value.hex()
    if isinstance(value, dt.datetime | dt.date):
        return value.isoformat()
    return value


def run_date(start_time_ns: int | None, first_log_time_ns: int | None, now: dt.datetime) -> dt.date:
    """UTC date of the run's start: RecordingInfo:start_time, else the first log_time, else now."""
    for ns in (start_time_ns, first_log_time_ns):
        if ns is not None and ns > 0:
            return dt.datetime.fromtimestamp(ns / 1e9, dt.UTC).date()
    return now.astimezone(dt.UTC).date()
