"""Reading one `rerun` metadata key of an Arrow field (or schema) in either spelling.

SDK 0.23 and older write `rerun.kind`, `rerun.component`, ... (a dot); SDK 0.24 on write
`rerun:kind`, `rerun:component`, ... (a colon). Stored chunks keep the spelling their SDK wrote (the
depot never rewrites a chunk's bytes to migrate it), so every reader of raw chunk metadata goes
through here: a reader of the colon spelling only would not see, for example, a 0.23 `fleet`
property's `token` field, and would serve it.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import overload

import pyarrow as pa

_PREFIXES = (b"rerun:", b"rerun.")  # current first: a chunk with both is read as Rerun reads it


@overload
def rerun_key(source: pa.Field | Mapping[bytes, bytes] | None, key: str) -> bytes | None: ...
@overload
def rerun_key(source: pa.Field | Mapping[bytes, bytes] | None, key: str, default: bytes) -> bytes: ...
def rerun_key(source: pa.Field | Mapping[bytes, bytes] | None, key: str, default: bytes | None = None) -> bytes | None:
    """`rerun:KEY` (else `rerun.KEY`) of a field's metadata, or of a metadata mapping; `default` if neither."""
    md = source.metadata if isinstance(source, pa.Field) else source
    if not md:
        return default
    for prefix in _PREFIXES:
        value = md.get(prefix + key.encode())
        if value is not None:
            return value
    return default


def component_name(fld: pa.Field) -> str:
    """The field's component (`rerun:component` in either spelling), else its column name."""
    return rerun_key(fld, "component", fld.name.encode()).decode()
