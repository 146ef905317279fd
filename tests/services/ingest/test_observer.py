"""What ingest tells its chunk observer (the live rules): a run it starts, before any of its chunks,
then each new recording chunk the observer wants, once; never a property chunk or a duplicate."""

from __future__ import annotations

from pathlib import Path

from services.rrd import ArrowMessage, iter_events
from services.rrd.chunk import ChunkMeta, chunk_meta
from tests.services.ingest import feeding
from tests.services.ingest.factory import ingest_service
from tests.services.rrd.recordings import Recording


class Recorder:
    def __init__(self, wanted: str) -> None:
        self.wanted = wanted
        self.calls: list[tuple[str, str, bytes | None]] = []

    def wants(self, entity_path: str) -> bool:
        return entity_path == self.wanted

    def chunk(self, run_id: str, robot_id: str, msg: ArrowMessage, meta: ChunkMeta) -> None:
        self.calls.append(("chunk", run_id, meta.chunk_id))

    def started(self, run_id: str, robot_id: str) -> None:
        self.calls.append(("started", run_id, None))


def test_the_observer_hears_of_a_run_before_its_chunks_and_of_each_wanted_chunk_once(
    tmp_path: Path, recordings: dict[str, Recording]
):
    scene = recordings["properties"]
    events = list(iter_events(scene.path))
    data = [chunk_meta(e) for e in events if isinstance(e, ArrowMessage)]
    entity = next(m.entity_path for m in data if not m.entity_path.startswith("/__properties"))
    observer = Recorder(entity)
    service = ingest_service(tmp_path, None, observer=observer)
    for _ in range(2):  # the second time: every chunk is held already
        feeding.upload(service, events)
    wanted = [m.chunk_id for m in data if m.entity_path == entity]
    assert wanted and observer.calls == [
        ("started", "rec-properties", None),
        *[("chunk", "rec-properties", chunk_id) for chunk_id in wanted],
    ]
