"""Tables on the catalog protocol's wire: an IPC stream written into a buffer of its exact size is
the stream Arrow's own writer makes, for tables of one batch, several and none."""

from __future__ import annotations

import pyarrow as pa
import pytest

from services.redap.dataframe import dataframe_part, ipc_stream, read_dataframe_part


def growing_buffer_stream(table: pa.Table | pa.RecordBatch) -> bytes:
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, table.schema) as writer:
        writer.write(table)
    return bytes(sink.getvalue().to_pybytes())


TABLES = {
    "batch": pa.record_batch({"n": list(range(1000)), "path": [f"/robot/{n % 7}" for n in range(1000)]}),
    "several batches": pa.Table.from_batches(
        [pa.record_batch({"n": [1, 2]}), pa.record_batch({"n": [3]}), pa.record_batch({"n": [4, 5, 6]})]
    ),
    "empty": pa.table({"n": pa.array([], pa.int64()), "key": pa.array([], pa.binary())}),
}


@pytest.mark.parametrize("name", TABLES)
def test_the_stream_is_arrow_s_own_byte_for_byte(name: str):
    table = TABLES[name]
    written = ipc_stream(table)
    assert written.to_pybytes() == growing_buffer_stream(table)
    assert read_dataframe_part(dataframe_part(table)).equals(
        pa.Table.from_batches([table]) if isinstance(table, pa.RecordBatch) else table
    )
