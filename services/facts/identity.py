"""Run identity (DESIGN.md section 4): ids safe for object keys, the robot, the date, and
recording properties with their secrets removed.

Property chunks (`/__properties/...`) are the only chunks whose data columns are read: they are
small, static, and hold what identifies a run (`rr.send_property("fleet", rr.AnyValues(robot_id=...))`).
"""

from __future__ import annotations

import datetime as dt
import re
from dataclasses import dataclass, field
from typing import Any

import pyarrow as pa

from core.errors import PermissionDeniedError
from services.rrd.chunk import ChunkMeta, chunk_meta, with_batch
from services.rrd.fieldmeta import component_name, rerun_key
from services.rrd.manifest import PROPERTIES_ENTITY, is_property_entity
from services.rrd.messages import ArrowMessage
from services.rrd.validate import validated_batch
from services.settings import DEFAULT_SECRET_FIELDS

IDENTITY_PROPERTY = "fleet"
ROBOT_FIELD = "robot_id"
TOKEN_FIELD = "token"  # of the fleet property: how an unmodified SDK stream proves itself (a depot token)
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
    name = property_name(meta.entity_path)
    secret = [
        i
        for i, f in enumerate(batch.schema)
        if _is_data(f) and (_is_secret(f, secret_fields) or (name == IDENTITY_PROPERTY and _is_token(f)))
    ]
    values: dict[str, Any] = {}
    for i, fld in enumerate(batch.schema):
        if i in secret or not _is_data(fld):
            continue
        value = _newest(batch.column(i))
        if value is not None:
            values[_component(fld)] = _plain(value)
    if not secret:
        return PropertyChunk(msg, meta, name, values)
    stripped = with_batch(msg, batch.select([i for i in range(batch.num_columns) if i not in secret]))
    return PropertyChunk(stripped, chunk_meta(stripped), name, values)


def check_robot(bound: str | None, run_id: str, robot: str) -> None:
    """A robot's token (`bound`: its robot, None for a token of no robot) writes its own runs only."""
    if bound is not None and robot != bound:
        raise PermissionDeniedError(
            f"run {run_id!r} is robot {robot!r}'s, and this token writes for robot {bound!r} only: "
            "send it with that robot's token"
        )


@dataclass(frozen=True)
class FleetClaim:
    """What a `fleet` property chunk says of who sent it: a token, and the robot it names, if any."""

    token: str = field(repr=False)
    robot: str | None


def fleet_claim(msg: ArrowMessage, meta: ChunkMeta) -> FleetClaim | None:
    """The `token` (and `robot_id`) of a `fleet` property chunk (`rr.send_property("fleet",
    rr.AnyValues(robot_id=..., token=...))`); None if `msg` is no such chunk or has no token. Read
    to authenticate a stream, and kept nowhere: the chunk is filed by `read_property_chunk`, which
    strips that field whatever FLEET_SECRET_FIELDS says."""
    if not is_property_entity(meta.entity_path) or property_name(meta.entity_path) != IDENTITY_PROPERTY:
        return None
    batch = validated_batch(msg, meta)
    token = robot = None
    for i, fld in enumerate(batch.schema):
        if _is_data(fld) and _is_token(fld):
            token = _newest(batch.column(i))
        elif _is_data(fld) and _component(fld) == ROBOT_FIELD:
            robot = _newest(batch.column(i))
    if token is None:
        return None
    return FleetClaim(str(_plain(token)), None if robot is None else str(_plain(robot)))


def _newest(column: pa.Array | pa.ChunkedArray) -> Any:
    """The newest non-null value of a property column, as Python; None if it has none."""
    for row in range(len(column) - 1, -1, -1):
        if column[row].is_valid:
            return column[row].as_py()
    return None


def _is_token(fld: pa.Field) -> bool:
    return _component(fld).rpartition(":")[2] == TOKEN_FIELD


def _is_data(fld: pa.Field) -> bool:
    return rerun_key(fld, "kind") in (b"data", b"component")


def _is_secret(fld: pa.Field, secret_fields: SecretFields) -> bool:
    return _component(fld) in secret_fields or fld.name in secret_fields


def _component(fld: pa.Field) -> str:
    return component_name(fld)


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
