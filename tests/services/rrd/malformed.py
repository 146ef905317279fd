"""Malformed chunks built from a real recording, for the validation, ingest and fuzz tests.

A small recording is written by the real rerun-sdk (in a subprocess): a property (with secret-like
fields), Scalars, TextLog and Transform3D. Its chunks are then rebuilt with pyarrow and re-wrapped
(LZ4 block, `uncompressed_size` fixed) so that each variant is damaged in exactly one way. Variants
that pyarrow refuses to build (bad offsets, a column longer than the batch) are made by patching
the IPC bytes of a valid chunk.
"""

from __future__ import annotations

import io
import struct
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import lz4.block
import numpy as np
import pyarrow as pa

from services.rrd.chunk import read_chunk
from services.rrd.decoder import iter_events
from services.rrd.encoder import RrdEncoder
from services.rrd.frames import DEFAULT_VERSION, MessageKind
from services.rrd.layout import LayoutCache, _parse_batch_header, split_ipc
from services.rrd.messages import ArrowMessage, BlueprintActivationMessage, Event, StoreInfoMessage
from services.rrd.pb import log_msg_pb2, sdk_comms_pb2

SEED_SCRIPT = """
import sys
import rerun as rr

rec = rr.RecordingStream("malformed", recording_id=sys.argv[2])
rec.save(sys.argv[1])
rec.send_property("fleet", rr.AnyValues(robot_id="robot-seven-of-nine", ingest_token="t0p", apiKey="k3y",
                                      tokens_used=12, tags=["a", "bb", "ccc", "arm", "base", "lidar", "cam0", "cam1"]))
rec.send_property("db", rr.AnyValues(DB_PASSWORD="hunter2", host="db.local"))
for frame in range(4):
    rec.set_time("frame", sequence=frame)
    rec.log("robot/speed", rr.Scalars([frame * 0.5, frame]))
    rec.log("log", rr.TextLog(f"step {frame}", level="INFO"))
    rec.log("tf", rr.Transform3D(translation=[frame, 0, 0], quaternion=[0, 0, 0, 1]))
    rec.log("points", rr.Points3D([[frame, 0, 0], [0, frame, 0], [0, 0, frame]], colors=[0xFF0000FF]))
rec.flush()
"""

SCALARS, TEXT, LEVEL = "Scalars:scalars", "TextLog:text", "TextLog:level"
TRANSLATION, QUATERNION = "Transform3D:translation", "Transform3D:quaternion"
POSITIONS, COLORS = "Points3D:positions", "Points3D:colors"  # components the depot never reads


def record_seed(path: Path, recording_id: str = "seed") -> Path:
    done = subprocess.run(
        [sys.executable, "-c", SEED_SCRIPT, str(path), recording_id], capture_output=True, timeout=120, check=False
    )
    assert done.returncode == 0, done.stderr.decode(errors="replace")
    return path


@dataclass
class Seed:
    events: list[Event]

    @classmethod
    def read(cls, path: Path) -> Seed:
        return cls(list(iter_events(path)))

    def chunk(self, entity: str) -> ArrowMessage:
        for event in self.events:
            if isinstance(event, ArrowMessage) and entity_of(event) == entity:
                return event
        raise KeyError(entity)

    def stream(self, replace: dict[int, bytes] | None = None, recording_id: str | None = None) -> bytes:
        """The recording as an .rrd stream (no footer), with the Arrow messages at `replace`'s
        offsets replaced by its raw ArrowMsg bytes, and the recording id changed if given."""
        out = io.BytesIO()
        encoder = RrdEncoder(out, DEFAULT_VERSION, write_footer=False)
        for kind, raw in self.messages(replace, recording_id):
            encoder.write_raw(kind, raw)
        encoder.finish()
        return out.getvalue()

    def messages(
        self, replace: dict[int, bytes] | None = None, recording_id: str | None = None
    ) -> list[tuple[MessageKind, bytes]]:
        out: list[tuple[MessageKind, bytes]] = []
        for event in self.events:
            if isinstance(event, StoreInfoMessage):
                out.append((MessageKind.SET_STORE_INFO, renamed_store_info(bytes(event.raw), recording_id)))
            elif isinstance(event, ArrowMessage):
                raw = (replace or {}).get(event.offset, bytes(event.raw))
                out.append((MessageKind.ARROW_MSG, renamed_arrow(raw, recording_id)))
            elif isinstance(event, BlueprintActivationMessage):
                out.append((MessageKind.BLUEPRINT_ACTIVATION, bytes(event.raw)))
        return out

    def grpc_requests(self, replace: dict[int, bytes] | None = None, recording_id: str | None = None) -> list[bytes]:
        """The same messages as serialized WriteMessagesRequests (what the SDK's gRPC sink sends)."""
        fields: dict[MessageKind, tuple[str, Any]] = {
            MessageKind.SET_STORE_INFO: ("set_store_info", log_msg_pb2.SetStoreInfo),
            MessageKind.ARROW_MSG: ("arrow_msg", log_msg_pb2.ArrowMsg),
            MessageKind.BLUEPRINT_ACTIVATION: ("blueprint_activation_command", log_msg_pb2.BlueprintActivationCommand),
        }
        requests = []
        for kind, raw in self.messages(replace, recording_id):
            name, cls = fields[kind]
            log_msg = log_msg_pb2.LogMsg(**{name: cls.FromString(raw)})
            requests.append(sdk_comms_pb2.WriteMessagesRequest(log_msg=log_msg).SerializeToString())
        return requests


def renamed_store_info(raw: bytes, recording_id: str | None) -> bytes:
    if recording_id is None:
        return raw
    pb = log_msg_pb2.SetStoreInfo.FromString(raw)
    if pb.info.store_id.kind == 1:  # recording
        pb.info.store_id.recording_id = recording_id
    return pb.SerializeToString()


def renamed_arrow(raw: bytes, recording_id: str | None) -> bytes:
    if recording_id is None:
        return raw
    pb = log_msg_pb2.ArrowMsg.FromString(raw)
    if pb.store_id.kind == 1:
        pb.store_id.recording_id = recording_id
    return pb.SerializeToString()


def entity_of(msg: ArrowMessage) -> str:
    return str(read_chunk(msg).schema.metadata[b"rerun:entity_path"].decode())


def ipc_of(batch: pa.RecordBatch) -> bytes:
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, batch.schema) as writer:
        writer.write_batch(batch)
    return bytes(sink.getvalue().to_pybytes())


def wrap(msg: ArrowMessage, ipc: bytes) -> bytes:
    """`msg`'s ArrowMsg holding `ipc` instead (LZ4 block, uncompressed_size fixed)."""
    pb = log_msg_pb2.ArrowMsg.FromString(bytes(msg.raw))
    pb.compression = 2  # type: ignore[assignment]  # LZ4
    pb.payload = lz4.block.compress(ipc, store_size=False)
    pb.uncompressed_size = len(ipc)
    return bytes(pb.SerializeToString())


def with_column(batch: pa.RecordBatch, name: str, array: pa.Array) -> pa.RecordBatch:
    i = batch.schema.get_field_index(name)
    old = batch.schema.field(i)
    fields, columns = list(batch.schema), list(batch.columns)
    fields[i], columns[i] = pa.field(old.name, array.type, old.nullable, old.metadata), array
    return pa.RecordBatch.from_arrays(columns, schema=pa.schema(fields, metadata=batch.schema.metadata))


def i32(*values: int) -> bytes:
    return np.array(values, dtype=np.int32).tobytes()


def patched(batch: pa.RecordBatch, old: bytes, new: bytes) -> bytes:
    ipc = ipc_of(batch)
    assert ipc.count(old) == 1, f"{old!r} occurs {ipc.count(old)} times"
    return ipc.replace(old, new)


def node_length_patched(batch: pa.RecordBatch, node: int, length: int) -> bytes:
    """The IPC of `batch` with the length of its `node`-th field node (depth-first) changed."""
    ipc = bytearray(ipc_of(batch))
    found = split_ipc(bytes(ipc))
    assert found is not None
    schema_message, pos = found
    parsed = _parse_batch_header(bytes(ipc), pos, LayoutCache().get(schema_message, b"", 0))
    assert parsed is not None and parsed[1] is not None
    at = pos + 8 + parsed[1].at_nodes + 16 * node
    ipc[at : at + 8] = struct.pack("<q", length)
    return bytes(ipc)


def _without_metadata(batch: pa.RecordBatch, key: bytes) -> pa.RecordBatch:
    return batch.replace_schema_metadata({k: v for k, v in batch.schema.metadata.items() if k != key})


def _nested(values: list[list[float]], item: pa.DataType) -> pa.Array:
    return pa.array([[v] for v in values], pa.list_(item))


Builder = Callable[[pa.RecordBatch], bytes]

# (variant, entity) -> the IPC bytes of the damaged chunk. Each is refused by `rerun rrd verify` 0.41.
MALFORMED: dict[str, tuple[str, Builder]] = {
    "scalars_float32": (
        "/robot/speed",
        lambda b: ipc_of(with_column(b, SCALARS, b.column(SCALARS).cast(pa.list_(pa.float32())))),
    ),
    "scalars_int32": (
        "/robot/speed",
        lambda b: ipc_of(with_column(b, SCALARS, b.column(SCALARS).cast(pa.list_(pa.int32()), safe=False))),
    ),
    "scalars_large_list": (
        "/robot/speed",
        lambda b: ipc_of(with_column(b, SCALARS, b.column(SCALARS).cast(pa.large_list(pa.float64())))),
    ),
    "scalars_fixed_size_list": (
        "/robot/speed",
        lambda b: ipc_of(with_column(b, SCALARS, pa.FixedSizeListArray.from_arrays(b.column(SCALARS).values, 2))),
    ),
    "scalars_offsets_decreasing": ("/robot/speed", lambda b: patched(b, i32(0, 2, 4, 6, 8), i32(0, 2, 7, 6, 8))),
    "scalars_offsets_past_values": ("/robot/speed", lambda b: patched(b, i32(0, 2, 4, 6, 8), i32(0, 2, 4, 6, 1 << 20))),
    "scalars_offsets_negative": ("/robot/speed", lambda b: patched(b, i32(0, 2, 4, 6, 8), i32(-4, 2, 4, 6, 8))),
    "scalars_column_shorter_than_batch": ("/robot/speed", lambda b: node_length_patched(b, 3, 3)),
    "index_column_shorter_than_batch": ("/robot/speed", lambda b: node_length_patched(b, 1, 3)),
    "row_id_null": (
        "/robot/speed",
        lambda b: ipc_of(
            with_column(b, "rerun.controls.RowId", pa.array([None, *b.column(0).to_pylist()[1:]], pa.binary(16)))
        ),
    ),
    "row_id_missing": ("/robot/speed", lambda b: ipc_of(b.drop_columns(["rerun.controls.RowId"]))),
    "row_id_binary": (
        "/robot/speed",
        lambda b: ipc_of(with_column(b, "rerun.controls.RowId", pa.array(b.column(0).to_pylist(), pa.binary()))),
    ),
    "no_chunk_id_metadata": ("/robot/speed", lambda b: ipc_of(_without_metadata(b, b"rerun:id"))),
    "index_int32": ("/robot/speed", lambda b: ipc_of(with_column(b, "frame", pa.array(range(4), pa.int32())))),
    "text_binary": ("/log", lambda b: ipc_of(with_column(b, TEXT, b.column(TEXT).cast(pa.list_(pa.binary()))))),
    "text_not_utf8": ("/log", lambda b: patched(b, b"step 2", b"step \xff")),
    "level_int32": ("/log", lambda b: ipc_of(with_column(b, LEVEL, pa.array([[1]] * 4, pa.list_(pa.int32()))))),
    "translation_width_2": (
        "/tf",
        lambda b: ipc_of(with_column(b, TRANSLATION, _nested([[1.0, 2.0]] * 4, pa.list_(pa.float32(), 2)))),
    ),
    "translation_float64": (
        "/tf",
        lambda b: ipc_of(with_column(b, TRANSLATION, _nested([[1.0, 2.0, 3.0]] * 4, pa.list_(pa.float64(), 3)))),
    ),
    "quaternion_width_3": (
        "/tf",
        lambda b: ipc_of(with_column(b, QUATERNION, _nested([[1.0, 2.0, 3.0]] * 4, pa.list_(pa.float32(), 3)))),
    ),
    # Components the depot never reads: only full validation and Rerun's own component types see them
    # (round two's finding: 24 of 24 such chunks with broken offsets were filed and served).
    "points_offsets_past_values": ("/points", lambda b: patched(b, i32(0, 3, 6, 9, 12), i32(0, 1 << 30, 6, 9, 12))),
    "points_offsets_decreasing": ("/points", lambda b: patched(b, i32(0, 3, 6, 9, 12), i32(0, 7, 6, 9, 12))),
    "points_positions_float64": (
        "/points",
        lambda b: ipc_of(with_column(b, POSITIONS, b.column(POSITIONS).cast(pa.list_(pa.list_(pa.float64(), 3))))),
    ),
    "points_positions_large_list": (
        "/points",
        lambda b: ipc_of(
            with_column(b, POSITIONS, b.column(POSITIONS).cast(pa.large_list(b.column(POSITIONS).type.value_type)))
        ),
    ),
    "points_colors_int32": (
        "/points",
        lambda b: ipc_of(with_column(b, COLORS, b.column(COLORS).cast(pa.list_(pa.int32()), safe=False))),
    ),
    # Finding 2: a small property chunk whose list offsets point far outside its values.
    "property_offsets_past_values": ("/__properties/fleet", lambda b: _property_offsets(b)),
    "property_not_utf8": (
        "/__properties/fleet",
        lambda b: patched(b, b"robot-seven-of-nine", b"robot\xffseven-of-nine"),
    ),
}


def _property_offsets(batch: pa.RecordBatch) -> bytes:
    """The `tags` column's string offsets (0, 1, 3, 6) made (0, 1 << 30, 3, 6): first and last are
    plausible, so pyarrow's cheap `validate()` passes it, and reading the first tag reads 1 GiB
    past the buffer (what aborted `fleet serve`)."""
    return patched(batch, i32(0, 1, 3, 6), i32(0, 1 << 30, 3, 6))  # the first 4 of the tags' 9 offsets


def malformed_chunk(seed: Seed, variant: str) -> tuple[ArrowMessage, bytes]:
    """(the seed's chunk, the raw ArrowMsg of its `variant`)."""
    entity, build = MALFORMED[variant]
    msg = seed.chunk(entity)
    return msg, wrap(msg, build(read_chunk(msg)))


def rerun_verify(rerun_bin: str, path: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [rerun_bin, "rrd", "verify", "--check-footers", "false", str(path)],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
