"""Recordings as SDKs before 0.25 sent them, made from a current SDK's file.

Before 0.25 a StoreId carried no application id: SetStoreInfo named it in StoreInfo's (now
deprecated) `application_id`, and ArrowMsg / BlueprintActivationCommand store ids lacked it.
Chunk payloads are kept; only those protobuf fields are rewritten.
"""

from __future__ import annotations

from pathlib import Path

from services.rrd import iter_events
from services.rrd.frames import MessageKind, StreamHeader, encode_message_header
from services.rrd.messages import ArrowMessage, BlueprintActivationMessage, StoreInfoMessage, StreamStart
from services.rrd.pb import log_msg_pb2


def legacy_messages(path: Path, *, drop_chunk_ids: bool = False) -> list[tuple[MessageKind, bytes]]:
    """(kind, protobuf bytes) of every message of `path`, rewritten as 0.23/0.24 wrote them;
    `drop_chunk_ids` also leaves out ArrowMsg.chunk_id and is_static (as 0.23 did)."""
    out: list[tuple[MessageKind, bytes]] = []
    for event in iter_events(path):
        if isinstance(event, StoreInfoMessage):
            info = log_msg_pb2.SetStoreInfo.FromString(bytes(event.raw))
            info.info.application_id.id = info.info.store_id.application_id.id
            info.info.store_id.ClearField("application_id")
            out.append((MessageKind.SET_STORE_INFO, info.SerializeToString()))
        elif isinstance(event, ArrowMessage):
            arrow = log_msg_pb2.ArrowMsg.FromString(bytes(event.raw))
            arrow.store_id.ClearField("application_id")
            if drop_chunk_ids:
                arrow.ClearField("chunk_id")
                arrow.ClearField("is_static")
            out.append((MessageKind.ARROW_MSG, arrow.SerializeToString()))
        elif isinstance(event, BlueprintActivationMessage):
            activation = log_msg_pb2.BlueprintActivationCommand.FromString(bytes(event.raw))
            activation.blueprint_id.ClearField("application_id")
            out.append((MessageKind.BLUEPRINT_ACTIVATION, activation.SerializeToString()))
    return out


def legacy_file(path: Path, out: Path, *, drop_chunk_ids: bool = False) -> Path:
    """`path` rewritten as a pre-0.25 SDK's file (no footer, as their FileSink wrote none)."""
    version = next(e.version for e in iter_events(path) if isinstance(e, StreamStart))
    with open(out, "wb") as fh:
        fh.write(StreamHeader(version).encode())
        for kind, raw in legacy_messages(path, drop_chunk_ids=drop_chunk_ids):
            fh.write(encode_message_header(kind, len(raw)) + raw)
        fh.write(encode_message_header(MessageKind.END, 0))
    return out
