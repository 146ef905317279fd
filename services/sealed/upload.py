"""A run sealed straight into the store: the sealing writes `recording.rrd` into a bounded pipe on a
thread of its own while the store's upload reads it (S3: multipart, parts sent as they fill). No
local copy of the sealed recording is made, so sealing a 50 GB run needs no 50 GB of free disk, and
the sealing and the upload run at once.

The store's `put` is all or nothing (S3 completes a multipart upload only at the end, a folder
renames into place), so a sealing that fails leaves the object as it was, and the upload of one
that is abandoned is aborted.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import BinaryIO, cast

from services.facts.identity import DEFAULT_SECRETS, SecretFields
from services.rrd.chunk import ChunkMeta
from services.rrd.messages import ArrowMessage, Event
from services.sealed.write import SealedRun, seal
from services.storage.objectstore import ObjectStore
from services.storage.pipe import Pipe

PIPE_BYTES = 16 * 1024 * 1024  # sealed, waiting for the upload to take it (which holds its parts)


def seal_to_store(
    store: ObjectStore,
    key: str,
    recordings: Iterable[Iterator[Event]],
    run_id: str,
    now: dt.datetime,
    on_chunk: Callable[[ArrowMessage, ChunkMeta], None] | None = None,
    secret_fields: SecretFields = DEFAULT_SECRETS,
    pipe_bytes: int = PIPE_BYTES,
) -> SealedRun:
    """`seal` written into `key` of `store` as it is made (at most `pipe_bytes` waiting for the
    upload). What the store holds is checked by the caller, with the run's other objects."""
    pipe = Pipe(pipe_bytes)

    def make() -> SealedRun:
        try:
            sealed = seal(recordings, cast(BinaryIO, pipe), run_id, now, on_chunk, secret_fields)
        except BaseException as exc:
            pipe.fail(exc)  # the upload stops with the sealing's own error
            raise
        pipe.close()
        return sealed

    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="seal") as sealing:
        made = sealing.submit(make)
        try:
            store.put(key, cast(BinaryIO, pipe))
        except BaseException:
            pipe.abandon()  # the sealing's next write raises: it stops
            made.exception()  # (waited for; the upload's error is the one raised)
            raise
        return made.result()
