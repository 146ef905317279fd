"""A robot's copy as the depot files it: its property chunks without their secret fields (the
`fleet` token), every other message as written. What a served run is compared with."""

from __future__ import annotations

from pathlib import Path

from services.facts.identity import read_property_chunk
from services.rrd import iter_events
from services.rrd.chunk import chunk_meta
from services.rrd.encoder import RrdEncoder
from services.rrd.frames import MessageKind
from services.rrd.manifest import is_property_entity
from services.rrd.messages import ArrowMessage, BlueprintActivationMessage, StoreInfoMessage, StreamStart


def stripped_copy(source: Path, target: Path) -> Path:
    """`source` with its property chunks' secret fields removed, written to `target` (one stream)."""
    events = list(iter_events(source))
    version = next(e.version for e in events if isinstance(e, StreamStart))
    with open(target, "wb") as out:
        encoder = RrdEncoder(out, version, write_footer=False)
        for event in events:
            if isinstance(event, StoreInfoMessage):
                encoder.write_raw(MessageKind.SET_STORE_INFO, event.raw)
            elif isinstance(event, BlueprintActivationMessage):
                encoder.write_raw(MessageKind.BLUEPRINT_ACTIVATION, event.raw)
            elif isinstance(event, ArrowMessage):
                meta = chunk_meta(event)
                msg = read_property_chunk(event, meta).message if is_property_entity(meta.entity_path) else event
                encoder.write_raw(MessageKind.ARROW_MSG, msg.raw)
        encoder.finish()
    return target
