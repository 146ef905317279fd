"""Where a secret could be kept without showing in a plain grep: a file's bytes are searched, and
also the LZ4-compressed chunks of its .rrd streams, its compressed Parquet columns, and the rows of
a DuckDB catalog (whose storage compresses strings)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import duckdb

from services.rrd.chunk import decompress_payload
from services.rrd.decoder import iter_events
from services.rrd.messages import ArrowMessage


def places_holding(files: list[Path], secrets: list[str], *, open_catalogs: bool) -> list[str]:
    """Each file, and each view of it, that holds one of `secrets`. DuckDB files are opened only
    with `open_catalogs` (when their server is stopped: it holds them locked)."""
    wanted = [s.encode() for s in secrets]
    return [
        f"{path} ({view})"
        for path in files
        for view, content in _views(path, open_catalogs)
        if any(w in content for w in wanted)
    ]


def _views(path: Path, open_catalogs: bool) -> Iterator[tuple[str, bytes]]:
    yield "bytes", path.read_bytes()
    if path.suffix == ".rrd":
        yield "decompressed chunks", b"".join(_payloads(path))
    elif path.suffix == ".parquet":
        yield "rows", _parquet_rows(path)
    elif path.suffix == ".duckdb" and open_catalogs:
        yield "rows", _duckdb_rows(path)


def _payloads(path: Path) -> Iterator[bytes]:
    for event in iter_events(path):
        if isinstance(event, ArrowMessage):
            yield decompress_payload(event)


def _parquet_rows(path: Path) -> bytes:
    with duckdb.connect() as db:
        return repr(db.execute("SELECT * FROM read_parquet(?)", [str(path)]).fetchall()).encode()


def _duckdb_rows(path: Path) -> bytes:
    with duckdb.connect(str(path), read_only=True) as db:
        tables = db.execute("SELECT table_schema, table_name FROM information_schema.tables").fetchall()
        return b"".join(repr(db.execute(f'SELECT * FROM "{s}"."{t}"').fetchall()).encode() for s, t in tables)
