"""What the catalog server served of chunks, by how: "depot" (FetchChunks answers, read through this
process) and "direct" (candidate rows handed out with a presigned URL: the client reads those
chunks from the bucket, `direct.py`). Read by `/metrics`."""

from __future__ import annotations

from collections import Counter

HOW = ("depot", "direct")

# (how, "chunks" | "bytes") -> total in this process
served: Counter[tuple[str, str]] = Counter()


def count_served(how: str, chunks: int, size: int) -> None:
    served[(how, "chunks")] += chunks
    served[(how, "bytes")] += size
