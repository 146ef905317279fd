"""What names may be: ids that become part of object keys, and names the catalog must hold.

Both are checked at ingest, before anything is written, so no run can make a key unsafe or make the
catalog refuse the writes and queries of every other run."""

from __future__ import annotations

import hashlib
import re
from collections.abc import Iterable

from core.errors import BadParameterError, InvalidArgumentError

ID_LENGTH = 128
SAFE_ID = re.compile(rf"[A-Za-z0-9._-]{{1,{ID_LENGTH}}}")
# Names the catalog indexes (application ids, timeline names) and entity paths: btree indexes hold
# values up to about 2,700 bytes, so these limits keep every index writable.
NAME_BYTES = 1024
PATH_BYTES = 2048


class UnsafeIdError(InvalidArgumentError):
    """Caught by ingest, which refuses the one stream and keeps the rest."""


def check_id(kind: str, value: str) -> str:
    """`value` if it can be part of an object key, else UnsafeIdError naming it and the rule."""
    if not SAFE_ID.fullmatch(value) or value in (".", ".."):
        raise UnsafeIdError(
            f"{kind} {value!r} cannot be used in object keys: use 1 to 128 characters from "
            "A-Z a-z 0-9 . _ - (for a recording id: rr.init(..., recording_id=...))"
        )
    return value


def is_id(value: str) -> bool:
    """Whether `value` can be a run's (or token's, pull's...) id. A string that cannot names nothing
    the depot holds: lookups answer "not found" for it without asking the catalog, which cannot
    compare a NUL and need not scan for 5,000 characters."""
    return SAFE_ID.fullmatch(value) is not None


def possible_ids(values: Iterable[str]) -> list[str]:
    """The `values` that can be ids (see is_id), in order: a filter by ids keeps only these."""
    return [value for value in values if is_id(value)]


def check_path_id(name: str, value: str) -> str:
    """`value` of the URL path parameter `name` (a run id, a token id, ...), if it can be an id of
    the depot; else a 422 naming the parameter. Every id a path names is of this form, so anything
    else (a NUL, which Postgres cannot even compare, a space, 200 characters) names nothing."""
    if not SAFE_ID.fullmatch(value):
        shown = value if len(value) <= 80 else value[:80] + "..."
        raise BadParameterError(
            name,
            f"{shown!r} is not an id of this depot: ids are 1 to {ID_LENGTH} characters from A-Z a-z 0-9 . _ - "
            "(check the URL)",
        )
    return value


def check_name(kind: str, value: str, limit: int = NAME_BYTES) -> str:
    """`value` if the catalog can hold it (no NUL character, at most `limit` UTF-8 bytes)."""
    if "\x00" in value:
        raise InvalidArgumentError(
            f"{kind} {value[:80]!r} contains a NUL character, which the catalog cannot "
            "store: remove it in the robot's logging code"
        )
    size = len(value.encode("utf-8", "surrogatepass"))
    if size > limit:
        raise InvalidArgumentError(
            f"{kind} {value[:80]!r}... is {size} bytes long, over the limit of {limit}: "
            "use a shorter one in the robot's logging code"
        )
    return value


def new_entry_id(name: str, time_ns: int) -> str:
    """A TUID for a catalog entry (Rerun's entry ids), as 32 hex digits: its creation time in
    nanoseconds, then 64 bits of its name's digest, so two nodes naming the same dataset at the
    same nanosecond still agree, and different names never collide in practice."""
    inc = int.from_bytes(hashlib.sha256(name.encode("utf-8", "surrogatepass")).digest()[:8], "big")
    return f"{time_ns & ((1 << 64) - 1):016X}{inc:016x}"
