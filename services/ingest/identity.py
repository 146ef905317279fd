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

from services.rrd.chunk import ChunkMeta, chunk_meta, with_batch
from services.rrd.manifest import PROPERTIES_ENTITY
from services.rrd.messages import ArrowMessage
from services.rrd.validate import validated_batch
from services.settings import DEFAULT_SECRET_FIELDS

IDENTITY_PROPERTY = "fleet"
ROBOT_FIELD = "robot_id"
START_TIME_COMPONENT = "RecordingInfo:start_time"


_WORD = re.compile(r"[A-Z]+(?=[A-Z][a-z])|[A-Z]?[a-z]+|[A-Z]+|[0-9]+")


def words(name: str) -> tuple[str, ...]:
    """`DB_PASSWORD` -> (db, password); `apiKey` -> (api, key); `AnyValues:ingest-token` ->
    (any, values, ingest, token): snake_case, kebab-case, dots, colons and camelCase split."""
    return tuple(w.lower() for w in _WORD.findall(name))


class SecretFields:
    """Secret-like field names: a field is secret if the words of a configured name appear, in a
    row, among the words of its name (`ingest_token`, `DB_PASSWORD`, `apiKey` are; `tokens_used`
    is not). Case-insensitive; the component name after the last ':' is covered (':' splits words)."""

    def __init__(self, names: tuple[str, ...] | list[str] = DEFAULT_SECRET_FIELDS) -> None:
        self.names = tuple(names)
        self._patterns = [w for w in (words(n) for n in names) if w]

    def __contains__(self, name: str) -> bool:
        got = words(name)
        return any(got[i : i + len(p)] == p for p in self._patterns for i in range(len(got) - len(p) + 1))


DEFAULT_SECRETS = SecretFields()


def property_name(entity_path: str) -> str:
    """`/__properties/fleet` -> `fleet`; `/__properties` (RecordingInfo) -> ``."""
    return entity_path[len(PROPERTIES_ENTITY) :].strip("/")


@dataclass
class PropertyChunk:
    """A property chunk as filed: its message (secrets removed) and the values it carries."""

    message: ArrowMessage
    meta: ChunkMeta  # of `message` (a secret field is no component of it: not in the catalog either)
    name: str
    values: dict[str, Any]  # field (component) -> last value logged, secrets removed


def read_property_chunk(
    msg: ArrowMessage, meta: ChunkMeta, secret_fields: SecretFields = DEFAULT_SECRETS
) -> PropertyChunk:
    """Decode a property chunk (fully validated first: its values are read); if it holds a secret
    field, return a re-encoded message without it (same chunk id, so the chunk is still stored
    exactly once)."""
    batch = validated_batch(msg, meta)
    secret = [i for i, f in enumerate(batch.schema) if _is_data(f) and _is_secret(f, secret_fields)]
    values: dict[str, Any] = {}
    for i, fld in enumerate(batch.schema):
        if i in secret or not _is_data(fld):
            continue
        column = batch.column(i)
        for row in range(len(column) - 1, -1, -1):  # the newest non-null value wins
            if column[row].is_valid:
                values[_component(fld)] = _plain(column[row].as_py())
                break
    name = property_name(meta.entity_path)
    if not secret:
        return PropertyChunk(msg, meta, name, values)
    stripped = with_batch(msg, batch.select([i for i in range(batch.num_columns) if i not in secret]))
    return PropertyChunk(stripped, chunk_meta(stripped), name, values)


def _is_data(fld: pa.Field) -> bool:
    return (fld.metadata or {}).get(b"rerun:kind") in (b"data", b"component")


def _is_secret(fld: pa.Field, secret_fields: SecretFields) -> bool:
    return _component(fld) in secret_fields or fld.name in secret_fields


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
