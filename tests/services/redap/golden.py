"""The golden setup of the query tests: recordings written by the real SDK, a depot node holding
them sealed with its catalog server, Rerun's own `rerun server` on the same files, request
builders, and Rerun's own dataframe reader as the oracle of what a set of chunks is enough for."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pyarrow as pa
import pytest
from google.protobuf import empty_pb2

from catalog import queries
from catalog.db import session_scope
from services.redap.dataframe import read_dataframe_part
from services.redap.pb import cloud_pb2
from services.redap.tuid import Tuid
from services.rrd import ArrowMessage, StoreInfoMessage, iter_events
from services.rrd.encoder import RrdEncoder
from services.rrd.messages import StreamStart
from services.rrd.pb import common_pb2
from tests.services.redap.client import Redap, reference_serving
from tests.services.redap.serving import CatalogServerThread, DepotNode, build_node
from tests.services.rrd.recordings import Recording
from tests.services.runs.latest_at_scenes import log_scene

SCENES = ("points", "scalars", "static", "properties", "transforms", "merge_a", "merge_b")
# dataset (application id) -> its recordings; the latest-at scene logged twice, chunked two ways
DATASETS = {
    "fleet_points": ["points"],
    "fleet_scalars": ["scalars"],
    "fleet_static": ["static"],
    "fleet_props": ["properties"],
    "fleet_tf": ["transforms"],
    "fleet_merge": ["merge_a", "merge_b"],
    "fleet-latest-at": ["per_call", "batched"],
}
SECRET_COLUMN = "property:fleet:token"  # the depot never stores a secret property (DESIGN §4)
ALL = cloud_pb2.SegmentSelection(all=empty_pb2.Empty())
EVERYTHING = cloud_pb2.ContentSelection(all=empty_pb2.Empty())


def segments(*ids: str) -> cloud_pb2.SegmentSelection:
    return cloud_pb2.SegmentSelection(explicit=cloud_pb2.SegmentIds(ids=[common_pb2.SegmentId(id=i) for i in ids]))


def entities(*paths: str, components: list[str] | None = None) -> cloud_pb2.ContentSelection:
    chosen = [
        cloud_pb2.EntitySelection(entity_path=common_pb2.EntityPath(path=p), all=empty_pb2.Empty())
        if components is None
        else cloud_pb2.EntitySelection(
            entity_path=common_pb2.EntityPath(path=p), explicit=cloud_pb2.ComponentIds(ids=components)
        )
        for p in paths
    ]
    return cloud_pb2.ContentSelection(explicit=cloud_pb2.EntitySelections(entities=chosen))


def time_range(
    timeline: str,
    start: int | None = None,
    end: int | None = None,
    *,
    fill_mode: cloud_pb2.FillMode = cloud_pb2.FILL_MODE_NONE,
    segments: cloud_pb2.SegmentSelection = ALL,
) -> cloud_pb2.RangeSelection:
    found = cloud_pb2.RangeSelection(timeline=timeline, fill_mode=fill_mode, segments=segments)
    if start is not None:
        found.start_inclusive = start
    if end is not None:
        found.end_inclusive = end
    return found


def table(responses: list[Any]) -> pa.Table:
    parts = [read_dataframe_part(r.data) for r in responses]
    return pa.concat_tables(parts) if parts else pa.table({})


# --- the two servers ------------------------------------------------------------------------------


@dataclass
class Servers:
    ours: Redap
    reference: Redap
    our_ids: dict[str, str]  # dataset name -> entry id
    reference_ids: dict[str, str]
    files: dict[str, Path]  # recording name -> the file the SDK wrote
    node: DepotNode

    def both(self, rpc: str, dataset: str, request: Any) -> tuple[Any, Any]:
        return (
            self.reference.call(rpc, request, entry=self.reference_ids[dataset]),
            self.ours.call(rpc, request, entry=self.our_ids[dataset]),
        )


@pytest.fixture(scope="module", name="recordings")
def recordings_fixture(
    recordings: dict[str, Recording], tmp_path_factory: pytest.TempPathFactory, rerun_bin: str
) -> dict[str, Path]:
    """The session's scenes that the query tests read, and two chunkings of one more scene."""
    folder = tmp_path_factory.mktemp("query-recordings")
    files = {name: recordings[name].path for name in SCENES}
    for chunking in ("per_call", "batched"):
        files[chunking] = log_scene(chunking, folder / f"{chunking}.rrd", rerun_bin)
    return files


@pytest.fixture(scope="module", name="servers")
def servers_fixture(
    recordings: dict[str, Path], rerun_bin: str, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[Servers]:
    root = tmp_path_factory.mktemp("query-servers")
    with ExitStack() as stack:
        node = build_node(root / "node")
        stack.callback(node.close)
        for files in DATASETS.values():
            for name in files:
                node.upload(recordings[name])
        node.seal_all()
        ours = CatalogServerThread(node.depot).start()
        stack.callback(ours.stop)
        # the reference also serves each run of a multi-run dataset alone, for its per-run schema
        single = {f"one-{name}": [recordings[name]] for name in ("merge_a", "merge_b", "per_call", "batched")}
        datasets = {**{k: [recordings[n] for n in v] for k, v in DATASETS.items()}, **single}
        reference_client = stack.enter_context(reference_serving(rerun_bin, root, datasets))
        found = reference_client.call("FindEntries", cloud_pb2.FindEntriesRequest(filter=cloud_pb2.EntryFilter()))
        reference_ids = {e.name: str(Tuid.from_proto(e.id.id)) for e in found.entries}
        with session_scope(node.catalog) as session:
            our_ids = {d.name: d.entry_id for d in queries.datasets(session)}
        client = Redap(ours.port)
        stack.callback(client.close)
        yield Servers(client, reference_client, our_ids, reference_ids, recordings, node)


# --- the oracle ---------------------------------------------------------------------------------


def keep_chunks(path: Path, chunk_ids: set[bytes], out: Path) -> Path:
    """A copy of the recording with only the given chunks (and its store infos)."""
    with open(out, "wb") as sink:
        encoder: RrdEncoder | None = None
        for event in iter_events(path):
            if isinstance(event, StreamStart):
                encoder = encoder or RrdEncoder(sink, event.version)  # type: ignore[arg-type]
                continue
            kept = isinstance(event, StoreInfoMessage) or (
                isinstance(event, ArrowMessage) and event.chunk_id in chunk_ids
            )
            if kept and encoder is not None:
                encoder.write(event)  # type: ignore[arg-type]
        assert encoder is not None
        encoder.finish()
    return out


def reader_rows(
    path: Path,
    index: str = "frame",
    start: int | None = None,
    end: int | None = None,
    times: list[int] | None = None,
    columns: list[str] | None = None,
) -> list[str]:
    """The rows Rerun's own dataframe reader gives (latest-at filled), as comparable text."""
    import numpy as np
    import rerun as rr

    store = rr.chunk.RrdReader(path).stream().collect()
    kwargs: dict[str, Any] = {"fill_latest_at": True}
    if times is not None:
        kwargs["using_index_values"] = np.array(times, dtype=np.int64)
    found = store.reader(index, **kwargs).to_arrow_table()
    found = pa.table(
        {
            name: column.cast(pa.int64()) if pa.types.is_temporal(column.type) else column
            for name, column in zip(found.column_names, found.columns, strict=True)
        }
    )
    rows = found.select(columns or [c for c in found.column_names if c != "rerun.controls.RowId"]).to_pylist()
    instants = found.column(index).to_pylist()
    kept = [
        r for r, t in zip(rows, instants, strict=True) if (start is None or t >= start) and (end is None or t <= end)
    ]
    assert kept, "a check over no rows proves nothing"
    return sorted(repr(r) for r in kept)
