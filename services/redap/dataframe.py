"""Tables on the catalog protocol's wire: `DataframePart` (an Arrow IPC stream, uncompressed,
which every tested client accepts) and `Schema` (an IPC-serialized Arrow schema)."""

from __future__ import annotations

import pyarrow as pa

from core.errors import InvalidArgumentError
from services.rrd.pb import common_pb2


def dataframe_part(table: pa.Table | pa.RecordBatch) -> common_pb2.DataframePart:
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, table.schema) as writer:
        writer.write(table)
    payload = sink.getvalue().to_pybytes()
    return common_pb2.DataframePart(
        encoder_version=common_pb2.ENCODER_VERSION_V0,
        payload=payload,
        compression=common_pb2.COMPRESSION_NONE,
        uncompressed_size=len(payload),
    )


def read_dataframe_part(part: common_pb2.DataframePart) -> pa.Table:
    """A client's table (FetchChunks' chunk list); LZ4 parts too, as Rerun's own clients may send."""
    payload = part.payload
    if part.compression == common_pb2.COMPRESSION_LZ4:
        import lz4.block

        payload = lz4.block.decompress(payload, uncompressed_size=part.uncompressed_size)
    try:
        return pa.ipc.open_stream(payload).read_all()
    except pa.ArrowInvalid as exc:
        raise InvalidArgumentError(f"a dataframe part is not an Arrow IPC stream: {exc}") from exc


def schema_proto(schema: pa.Schema) -> common_pb2.Schema:
    return common_pb2.Schema(arrow_schema=schema.serialize().to_pybytes())
