"""What a chunk's record batch header says, worked out once per distinct header.

A stream's one-row chunks of one entity carry byte-identical record batch headers (the same row
count, null counts, and buffer offsets and sizes; only the body's values differ), so everything
the header tells (row count, whether the chunk can be read without pyarrow, where each index
column's first and last values sit, which Scalars offsets to check, a null where Rerun forbids one)
is worked out once and kept on the layout, keyed by the header's bytes. A chunk then costs a dict
lookup and a few reads of its values. A header seen for the first time is read by hand
(`layout.read_batch_header`) as before.

Positions in a plan are relative to the start of the record batch message, so a plan holds for any
chunk whose header has those bytes, wherever its schema message ended.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from services.rrd.layout import BatchHeader, ChunkLayout, read_batch_header
from services.rrd.lz4_prefix import PrefixTooShort
from services.rrd.value_checks import OffsetsCheck, value_checks

_MAX_PLANS = 256  # per layout: large chunks rarely share a header; cleared when full
_I32 = struct.Struct("<i")
_MISSING = object()


@dataclass(frozen=True, slots=True)
class IndexRead:
    name: str  # the timeline
    first: int  # where its first value sits
    count: int  # its values (the rows)
    is_sorted: bool  # sorted: the first and last values are its range


@dataclass(frozen=True, slots=True)
class BatchPlan:
    length: int  # bytes from the record batch message's start to its body's end
    rows: int
    reads: tuple[IndexRead, ...]  # none when the chunk has no rows
    # What full validation checks in the body of each chunk with this header (`value_checks`); None:
    # the header alone shows a problem, or holds types not walked there: pyarrow decides.
    checks: tuple[OffsetsCheck, ...] | None
    null_counts: tuple[int, ...]  # of the columns declared non-nullable
    reach: int  # bytes from the record batch message's start that the reads of a chunk need
    # A one-row chunk's index values, all read by one unpack from `reads[0].first` (None: read one
    # by one); they are each timeline's min and max.
    one_row: struct.Struct | None = None


def batch_plan(data: bytes, pos: int, layout: ChunkLayout, total: int) -> BatchPlan | None:
    """The plan of the record batch at `pos` (None: it is read with pyarrow). `data` may be the
    first bytes of a payload of `total` bytes (PrefixTooShort when its header is not within them)."""
    if pos + 8 > len(data):
        if pos + 8 > total:
            return None
        raise PrefixTooShort(pos + 8)
    end = pos + 8 + _I32.unpack_from(data, pos + 4)[0]
    if end > len(data):
        if end > total or end <= pos + 8:
            return None
        raise PrefixTooShort(end)
    key = data[pos:end]
    plans = layout.batch_plans
    plan = plans.get(key, _MISSING)
    if plan is _MISSING:
        header = read_batch_header(data, pos, layout, total)
        plan = _plan(data, pos, layout, header) if header is not None else None
        if len(plans) >= _MAX_PLANS:
            plans.clear()
        plans[key] = plan
    assert plan is None or isinstance(plan, BatchPlan)
    if plan is not None and pos + plan.length > total:
        return None  # this payload is too short for its header's body: pyarrow says why
    return plan


def _plan(data: bytes, pos: int, layout: ChunkLayout, header: BatchHeader) -> BatchPlan | None:
    """None when the header asks for pyarrow: a column shorter than the batch, or a null that matters
    (in an index column, or a data column whose per-component ranges would then differ)."""
    rows, nodes = header.length, header.nodes
    if layout.pick_top_lengths(nodes).count(rows) != len(layout.top_nodes) or any(layout.pick_null_counts(nodes)):
        return None
    body = header.body - pos
    reads = []
    if rows:
        index_buffers = layout.pick_index_buffers(header.buffers)
        for i, ix in enumerate(layout.indexes):
            offset, size = index_buffers[2 * i], index_buffers[2 * i + 1]
            if size < 8 * rows:
                return None
            reads.append(IndexRead(ix.name, body + offset, rows, ix.is_sorted))
    checks = value_checks(layout.schema, rows, nodes, header.buffers, body)
    reach = max([header.body - pos] + [r.first + 8 * r.count for r in reads])
    required = tuple(nodes[2 * layout.top_nodes[i] + 1] for i in layout.required)
    return BatchPlan(header.end - pos, rows, tuple(reads), checks, required, reach, _one_row(reads))


def _one_row(reads: list[IndexRead]) -> struct.Struct | None:
    """One struct for a one-row chunk's index values, when they come in the reads' order."""
    if not reads or any(r.count != 1 for r in reads):
        return None
    fmt, at = "<", reads[0].first
    for read in reads:
        if read.first < at:
            return None
        fmt += f"{read.first - at}xq"
        at = read.first + 8
    return struct.Struct(fmt)
