"""An episode's samples read back from chunks the real SDK wrote: scalar vectors, raw images of each
colour model, JPEG and PNG decoded, rows in time order whatever the chunks' order, and latest-at."""

from __future__ import annotations

import io
from pathlib import Path

import av
import numpy as np
import pytest
import rerun as rr

from services.datasets.samples import SampleError, Series, read_series
from services.rrd.chunk import ChunkMeta, chunk_meta
from services.rrd.decoder import iter_events
from services.rrd.messages import ArrowMessage

S = 1_000_000_000


def chunks(path: Path) -> list[tuple[ArrowMessage, ChunkMeta]]:
    return [(e, chunk_meta(e)) for e in iter_events(path) if isinstance(e, ArrowMessage)]


def encoded(rgb: np.ndarray, codec: str) -> bytes:
    out = io.BytesIO()
    with av.open(out, "w", format="image2pipe" if codec == "png" else "mjpeg") as container:
        stream = container.add_stream(codec, rate=1)
        assert isinstance(stream, av.VideoStream)
        stream.width, stream.height = rgb.shape[1], rgb.shape[0]
        stream.pix_fmt = "rgb24" if codec == "png" else "yuvj444p"
        frame = av.VideoFrame.from_ndarray(rgb, format="rgb24")
        for packet in stream.encode(frame):
            container.mux(packet)
        for packet in stream.encode(None):
            container.mux(packet)
    return out.getvalue()


@pytest.fixture
def recording(tmp_path: Path) -> Path:
    path = tmp_path / "samples.rrd"
    rec = rr.RecordingStream("samples", recording_id="run-samples")
    rec.save(str(path))
    picture = np.zeros((8, 10, 3), dtype=np.uint8)
    picture[:, :, 0], picture[:, :, 1], picture[:, :, 2] = 200, 100, 50
    for t in (3, 1, 2):  # out of order: read back in time order
        rec.set_time("t", timestamp=np.datetime64(t * S, "ns"))
        rec.log("/joints", rr.Scalars([t, t * 10.0, t * 100.0]))
        rec.flush()
    rec.set_time("t", timestamp=np.datetime64(1 * S, "ns"))
    rec.log("/cam/rgb", rr.Image(picture))
    rec.log("/cam/bgr", rr.Image(picture[:, :, ::-1], color_model="BGR"))
    rec.log("/cam/grey", rr.Image(picture[:, :, :1]))
    rec.log("/cam/png", rr.EncodedImage(contents=encoded(picture, "png"), media_type="image/png"))
    rec.log("/cam/jpeg", rr.EncodedImage(contents=encoded(picture, "mjpeg"), media_type="image/jpeg"))
    rec.log("/cam/float", rr.Image(picture.astype(np.float32)))
    rec.flush()
    rec.disconnect()
    return path


def test_scalars_in_time_order_and_latest_at(recording: Path):
    series = read_series(chunks(recording), "t", {"/joints"})["/joints"]
    assert series.times.tolist() == [1 * S, 2 * S, 3 * S]
    assert [v.tolist() for v in series.values] == [[1, 10, 100], [2, 20, 200], [3, 30, 300]]
    grid = np.array([0, 1 * S, 1.5 * S, 3 * S, 9 * S], dtype=np.int64)
    assert series.at(grid).tolist() == [-1, 0, 0, 2, 2]


def test_images_of_each_kind(recording: Path):
    found = read_series(chunks(recording), "t", {"/cam/rgb", "/cam/bgr", "/cam/grey", "/cam/png", "/cam/jpeg"})
    expected = np.array([200, 100, 50])
    for entity in ("/cam/rgb", "/cam/bgr", "/cam/png"):
        (image,) = found[entity].values
        assert np.array_equal(image.rgb()[0, 0], expected), entity
    (grey,) = found["/cam/grey"].values
    assert grey.rgb().shape == (8, 10, 3) and grey.rgb()[0, 0].tolist() == [200, 200, 200]
    (jpeg,) = found["/cam/jpeg"].values
    assert np.abs(jpeg.rgb()[4, 5].astype(int) - expected).max() < 8  # within JPEG's error


def test_an_image_it_cannot_take_says_so(recording: Path):
    (image,) = read_series(chunks(recording), "t", {"/cam/float"})["/cam/float"].values
    with pytest.raises(SampleError, match="8-bit"):
        image.rgb()


def test_an_empty_series_has_nothing_at_any_time():
    assert Series().at(np.array([5], dtype=np.int64)).tolist() == [-1]
