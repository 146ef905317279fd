"""An episode's samples, read from its chunks: per entity, its rows on the snapshot's timeline, in
time order, and the latest of them at each time of the export's grid.

Scalars (`Scalars:scalars`) give a vector per row (every instance: a joint array logged as one
Scalars is one vector). Images give RGB frames: a raw `Image` (8-bit L, RGB, RGBA, BGR or BGRA)
from its buffer and format, an `EncodedImage` (JPEG, PNG) decoded with PyAV. Image rows are decoded
only when a frame of the grid takes them, so memory holds the rows' bytes, not their pixels.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import av
import numpy as np
import pyarrow as pa

from services.rrd.chunk import ChunkMeta
from services.rrd.errors import InvalidChunkError
from services.rrd.messages import ArrowMessage
from services.rrd.validate import validated_batch
from services.rrd.values import data_columns, index_columns

SCALARS = "Scalars:scalars"
IMAGE_BUFFER, IMAGE_FORMAT = "Image:buffer", "Image:format"
ENCODED_BLOB, MEDIA_TYPE = "EncodedImage:blob", "EncodedImage:media_type"
# Rerun's ColorModel values -> channels, and their order as RGB; ChannelDatatype U8
COLOR_MODELS = {1: (1, None), 2: (3, None), 3: (4, None), 4: (3, [2, 1, 0]), 5: (4, [2, 1, 0])}
U8 = 6
DECODERS = {"image/jpeg": "mjpeg", "image/png": "png"}


class SampleError(ValueError):
    """A row the export cannot read (an image format it does not take): said with the entity."""


@dataclass(frozen=True)
class RawImage:
    buffer: bytes
    width: int
    height: int
    color_model: int | None
    datatype: int | None
    pixel_format: int | None

    def rgb(self) -> np.ndarray:
        if self.pixel_format is not None or self.datatype != U8 or self.color_model not in COLOR_MODELS:
            raise SampleError(
                f"an Image of pixel format {self.pixel_format}, color model {self.color_model}, channel type "
                f"{self.datatype}: the export takes 8-bit L, RGB, RGBA, BGR or BGRA images (or JPEG and PNG)"
            )
        channels, order = COLOR_MODELS[self.color_model]
        pixels = np.frombuffer(self.buffer, dtype=np.uint8)
        if pixels.size != self.width * self.height * channels:
            raise SampleError(f"an Image of {pixels.size} bytes for {self.width}x{self.height}x{channels}")
        pixels = pixels.reshape(self.height, self.width, channels)
        if channels == 1:
            return np.repeat(pixels, 3, axis=2)
        if order is not None:
            pixels = pixels[:, :, order + ([3] if channels == 4 else [])]
        return np.ascontiguousarray(pixels[:, :, :3])


@dataclass(frozen=True)
class EncodedImage:
    blob: bytes
    media_type: str | None

    def rgb(self) -> np.ndarray:
        codec = DECODERS.get(self.media_type or "")
        if codec is None:
            raise SampleError(f"an EncodedImage of media type {self.media_type!r}: the export takes JPEG and PNG")
        context = av.VideoCodecContext.create(codec, "r")
        assert isinstance(context, av.VideoCodecContext)
        try:
            frames = [*context.decode(av.Packet(self.blob)), *context.decode(None)]
        except av.FFmpegError as exc:
            raise SampleError(f"an EncodedImage ({self.media_type}) that does not decode: {exc}") from exc
        if not frames:
            raise SampleError(f"an EncodedImage ({self.media_type}) that does not decode")
        frame = frames[0]
        assert isinstance(frame, av.VideoFrame)
        return frame.to_ndarray(format="rgb24")


Image = RawImage | EncodedImage


@dataclass
class Series:
    """One entity's rows on the timeline: their times, sorted, and their values."""

    times: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    values: list[Any] = field(default_factory=list)

    def at(self, grid: np.ndarray) -> np.ndarray:
        """For each time of the grid, the index of the latest row at or before it (-1: none yet)."""
        return np.searchsorted(self.times, grid, side="right") - 1


Observe = Callable[[str, np.ndarray, list[Any]], None]


def read_series(
    chunks: Iterable[tuple[ArrowMessage, ChunkMeta]], timeline: str, wanted: set[str], observe: Observe | None = None
) -> dict[str, Series]:
    """The rows of the `wanted` entities on `timeline` (rows off it and static rows skipped), each
    entity's in time order whatever the order of its chunks. `observe` sees each chunk's rows as
    they were logged (entity, times, values), before they are sorted."""
    pieces: dict[str, list[tuple[np.ndarray, list[Any]]]] = {}
    for msg, meta in chunks:
        if meta.is_static or meta.entity_path not in wanted:
            continue
        try:
            batch = validated_batch(msg, meta)
        except InvalidChunkError as exc:
            raise SampleError(f"{meta.entity_path}: {exc}") from exc
        index = index_columns(batch, meta).get(timeline)
        if index is None:
            continue
        _, times, has_time = index
        values = _row_values(data_columns(batch, meta))
        if values is None:
            continue
        keep = [i for i in range(len(times)) if has_time[i] and values[i] is not None]
        kept = (times[keep], [values[i] for i in keep])
        if observe is not None:
            observe(meta.entity_path, *kept)
        pieces.setdefault(meta.entity_path, []).append(kept)
    out: dict[str, Series] = {}
    for entity, parts in pieces.items():
        times = np.concatenate([t for t, _ in parts]) if parts else np.zeros(0, dtype=np.int64)
        values = [v for _, vs in parts for v in vs]
        order = np.argsort(times, kind="stable")
        out[entity] = Series(times[order], [values[i] for i in order])
    return out


def _row_values(columns: dict[str, pa.Array]) -> list[Any] | None:
    if SCALARS in columns:
        return [
            None if row is None or not row else np.asarray(row, dtype=np.float64) for row in _rows(columns[SCALARS])
        ]
    if IMAGE_BUFFER in columns and IMAGE_FORMAT in columns:
        out: list[Any] = []
        for buffer, fmt in zip(_rows(columns[IMAGE_BUFFER]), _rows(columns[IMAGE_FORMAT]), strict=True):
            if not buffer or not fmt:
                out.append(None)
                continue
            f = fmt[0]
            out.append(
                RawImage(
                    bytes(buffer[0]), f["width"], f["height"], f.get("color_model"), f.get("channel_datatype"),
                    f.get("pixel_format"),
                )
            )  # fmt: skip
        return out
    if ENCODED_BLOB in columns:
        media = _rows(columns[MEDIA_TYPE]) if MEDIA_TYPE in columns else None
        blobs = _rows(columns[ENCODED_BLOB])
        return [
            EncodedImage(bytes(blob[0]), (media[i] or [None])[0] if media is not None else None) if blob else None
            for i, blob in enumerate(blobs)
        ]
    return None


def _rows(column: pa.Array) -> list[Any]:
    rows: list[Any] = column.to_pylist()
    return rows
