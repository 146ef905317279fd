"""RrdDecoder / iter_events on real recordings written by rerun-sdk 0.41."""

from __future__ import annotations

import dataclasses
import io
import struct

import pytest
import xxhash
from hypothesis import given, settings
from hypothesis import strategies as st

from services.rrd import (
    ArrowMessage,
    BlueprintActivationMessage,
    EndMessage,
    RerunVersion,
    RrdDecoder,
    StoreInfoMessage,
    StoreKind,
    StreamFooter,
    StreamStart,
    errors,
    iter_events,
)
from services.rrd.messages import Event
from tests.services.rrd.recordings import CLI_FILES, Recording, walk_frames

pytestmark = pytest.mark.sdk

LOCATED = (StoreInfoMessage, ArrowMessage, BlueprintActivationMessage, EndMessage)


def decode(data: bytes, piece: int | None = None) -> list[Event]:
    """Feed `data` in pieces of `piece` bytes (all at once when None), then finish()."""
    decoder = RrdDecoder()
    step = piece or max(len(data), 1)
    events: list[Event] = []
    for i in range(0, len(data), step):
        events += decoder.feed(data[i : i + step])
    events += decoder.finish()
    return events


def decode_until_error(data: bytes, piece: int | None = None) -> tuple[list[Event], errors.RrdError | None]:
    decoder = RrdDecoder()
    step = piece or max(len(data), 1)
    events: list[Event] = []
    try:
        for i in range(0, len(data), step):
            events += decoder.feed(data[i : i + step])
        events += decoder.finish()
    except errors.RrdError as exc:
        return events, exc
    return events, None


def shifted(events: list[Event], base: int, index: int) -> list[Event]:
    """`events` of a stream decoded alone, as they appear when that stream starts at `base`."""
    out: list[Event] = []
    for e in events:
        if isinstance(e, StreamStart | StreamFooter):
            out.append(dataclasses.replace(e, offset=e.offset + base, stream_index=index))
        else:
            out.append(dataclasses.replace(e, offset=e.offset + base, stream_offset=base, stream_index=index))
    return out


def stores_of(events: list[Event]) -> list[StoreInfoMessage]:
    return [e for e in events if isinstance(e, StoreInfoMessage)]


# --- message sequence ------------------------------------------------------------------------


def test_message_sequence(whole: Recording):
    events = decode(whole.data)
    start = events[0]
    assert isinstance(start, StreamStart)
    assert (start.offset, start.stream_index) == (0, 0)
    assert start.version == RerunVersion(0, 41, 0)
    assert (start.header.compression, start.header.serializer) == (1, 2)
    assert not any(isinstance(e, StreamStart) for e in events[1:])

    if whole.truth["footer"]:
        assert isinstance(events[-2], EndMessage)
        assert isinstance(events[-1], StreamFooter)
        body = events[1:-2]
    else:
        body = events[1:]
    assert body
    assert all(isinstance(e, StoreInfoMessage | ArrowMessage | BlueprintActivationMessage) for e in body)

    # Every store is announced (twice by the SDK, once after `rerun rrd merge`) before its first chunk.
    infos_per_store = 1 if whole.name in CLI_FILES else 2
    store_ids = {e.store_id for e in stores_of(body)}
    for store_id in store_ids:
        positions = [i for i, e in enumerate(body) if isinstance(e, StoreInfoMessage) and e.store_id == store_id]
        assert len(positions) == infos_per_store, store_id
        first_chunk = next(i for i, e in enumerate(body) if isinstance(e, ArrowMessage) and e.store_id == store_id)
        assert positions[-1] < first_chunk
    for e in body:
        if isinstance(e, ArrowMessage):
            assert e.store_id in store_ids
    for info in stores_of(body):
        assert info.sdk_version == RerunVersion(0, 41, 0)
        assert info.source.startswith("python_sdk (python 3.")

    recordings = {(s.application_id, s.recording_id) for s in store_ids if s.kind == StoreKind.RECORDING}
    assert recordings == {(r["application_id"], r["recording_id"]) for r in whole.recordings}
    blueprints = [s for s in store_ids if s.kind == StoreKind.BLUEPRINT]
    assert len(blueprints) == sum(r["blueprint"] for r in whole.recordings)

    # At least one chunk per logged entity, in the right store.
    for rec in whole.recordings:
        chunks = [e for e in body if isinstance(e, ArrowMessage) and e.store_id.recording_id == rec["recording_id"]]
        assert len(chunks) >= len(rec["entities"])


def test_end_and_stream_footer(footer_file: Recording):
    data = footer_file.data
    events = decode(data)
    end, trailer = events[-2], events[-1]
    assert isinstance(end, EndMessage) and isinstance(trailer, StreamFooter)
    chunk_stores = {e.store_id for e in events if isinstance(e, ArrowMessage)}
    assert end.footer is not None
    assert len(end.footer.manifests) == len(chunk_stores)
    assert {(m.store_id.kind, m.store_id.application_id.id, m.store_id.recording_id) for m in end.footer.manifests} == {
        (int(s.kind), s.application_id, s.recording_id) for s in chunk_stores
    }

    assert trailer.offset == end.offset + 16 + len(end.raw)
    assert trailer.offset + 32 == len(data)
    assert trailer.stream_index == 0
    assert trailer.footer_start == end.stream_payload_offset == end.offset + 16
    assert trailer.footer_length == len(end.raw)
    assert trailer.crc == xxhash.xxh32_intdigest(end.raw, seed=7850921)
    assert struct.unpack_from("<QQI", data, trailer.offset) == (
        trailer.footer_start,
        trailer.footer_length,
        trailer.crc,
    )
    assert data[-12:] == b"RRF2FOOT" + struct.pack("<I", 1)


def test_offsets_point_at_headers(whole: Recording):
    data = whole.data
    events = decode(data)
    frames, trailer = walk_frames(data)
    messages = [e for e in events if isinstance(e, LOCATED)]
    assert [(m.offset, int(m.kind), len(m.raw)) for m in messages] == [(f.offset, f.kind, f.length) for f in frames]
    for m in messages:
        assert struct.unpack_from("<QQ", data, m.offset) == (m.kind, len(m.raw))
        assert data[m.payload_offset : m.payload_offset + len(m.raw)] == m.raw
        assert (m.stream_offset, m.stream_index) == (0, 0)
        assert m.stream_payload_offset == m.offset + 16
    footers = [e for e in events if isinstance(e, StreamFooter)]
    assert [f.offset for f in footers] == ([] if trailer is None else [trailer])
    # The messages tile the file: nothing skipped, nothing read twice.
    assert messages[0].offset == 12
    end = messages[-1].offset + 16 + len(messages[-1].raw)
    assert end == (len(data) if trailer is None else trailer)


@pytest.mark.parametrize("piece", [1, 7, 4096])
def test_piece_size_does_not_matter(whole: Recording, piece: int):
    expected = decode(whole.data)
    assert decode(whole.data, piece) == expected
    assert list(iter_events(whole.path, read_size=piece)) == expected
    assert list(iter_events(io.BytesIO(whole.data), read_size=piece)) == expected


def test_start_offset_shifts_every_offset(recordings: dict[str, Recording]):
    """A decoder that resumes at byte N of an input reports absolute offsets; stream-relative ones stay."""
    data = recordings["blueprint"].data
    decoder = RrdDecoder(start_offset=1000)
    events = decoder.feed(data) + decoder.finish()
    assert events == shifted(decode(data), 1000, 0)
    assert decoder.offset == 1000 + len(data)
    assert [e.stream_payload_offset for e in events if isinstance(e, ArrowMessage)] == [
        e.stream_payload_offset for e in decode(data) if isinstance(e, ArrowMessage)
    ]


def test_iter_events_path_and_file_object(whole: Recording):
    expected = decode(whole.data)
    assert list(iter_events(whole.path)) == expected
    assert list(iter_events(str(whole.path))) == expected
    with open(whole.path, "rb") as fh:
        assert list(iter_events(fh)) == expected


# --- several stores --------------------------------------------------------------------------


def test_blueprint_and_recording_stores(recordings: dict[str, Recording]):
    rec = recordings["blueprint"]
    events = decode(rec.data)
    store_ids = {e.store_id for e in stores_of(events)}
    assert len(store_ids) == 2
    blueprint = next(s for s in store_ids if s.kind == StoreKind.BLUEPRINT)
    recording = next(s for s in store_ids if s.kind == StoreKind.RECORDING)
    assert blueprint.application_id == recording.application_id == "fleet_bp"
    assert recording.recording_id == "rec-blueprint"
    assert blueprint.is_blueprint and not recording.is_blueprint

    activations = [e for e in events if isinstance(e, BlueprintActivationMessage)]
    assert len(activations) == 1
    assert activations[0].blueprint_id == blueprint
    assert activations[0].make_default is True
    assert activations[0].make_active is False

    chunks = [e for e in events if isinstance(e, ArrowMessage)]
    assert {c.store_id for c in chunks} == {blueprint, recording}
    # The activation follows the blueprint's chunks.
    last_blueprint_chunk = max(
        i for i, e in enumerate(events) if isinstance(e, ArrowMessage) and e.store_id == blueprint
    )
    assert events.index(activations[0]) > last_blueprint_chunk


def test_merged_file_holds_two_recordings(recordings: dict[str, Recording]):
    events = decode(recordings["merged"].data)
    chunk_stores = {e.store_id for e in events if isinstance(e, ArrowMessage)}
    assert {(s.kind, s.application_id, s.recording_id) for s in chunk_stores} == {
        (StoreKind.RECORDING, "fleet_merge", "rec-merge-a"),
        (StoreKind.RECORDING, "fleet_merge", "rec-merge-b"),
    }
    end = next(e for e in events if isinstance(e, EndMessage))
    assert end.footer is not None and len(end.footer.manifests) == 2


# --- files without footer, cut files ---------------------------------------------------------


def test_no_footer_file(recordings: dict[str, Recording]):
    rec = recordings["no_footer"]
    decoder = RrdDecoder()
    events = decoder.feed(rec.data)
    assert decoder.finish() == []
    assert not any(isinstance(e, EndMessage | StreamFooter) for e in events)
    assert isinstance(events[-1], ArrowMessage)
    assert events[-1].offset + 16 + len(events[-1].raw) == len(rec.data)
    assert decoder.offset == len(rec.data)
    assert decoder.streams == 1


@pytest.mark.parametrize("piece", [None, 1, 7, 4096])
def test_cut_file(recordings: dict[str, Recording], piece: int | None):
    rec = recordings["cut"]
    torn_at = rec.truth["cut_message_offset"]
    full = decode(recordings["points"].data)
    expected = [e for e in full if e.offset < torn_at]
    assert any(isinstance(e, ArrowMessage) for e in expected)

    events, error = decode_until_error(rec.data, piece)
    assert events == expected
    assert isinstance(error, errors.TruncatedError)
    assert error.offset == torn_at
    assert f"at byte {torn_at}" in str(error)


def test_cut_file_iter_events(recordings: dict[str, Recording]):
    rec = recordings["cut"]
    torn_at = rec.truth["cut_message_offset"]
    expected = [e for e in decode(recordings["points"].data) if e.offset < torn_at]
    got: list[Event] = []
    with pytest.raises(errors.TruncatedError) as info:
        for event in iter_events(rec.path, read_size=1000):
            got.append(event)
    assert got == expected
    assert info.value.offset == torn_at


def _units(data: bytes) -> list[tuple[int, int]]:
    """(start, end) of each unit the decoder reads whole: stream header, messages, footer parts."""
    frames, trailer = walk_frames(data)
    units = [(0, 12)] + [(f.offset, f.end) for f in frames]
    if trailer is not None:
        units.append((trailer, trailer + 32))  # reported once whole; a cut anywhere in it is truncation
    return units


def _expect_cut(full: list[Event], units: list[tuple[int, int]], at: int) -> tuple[list[Event], int | None]:
    for start, end in units:
        if start < at < end:
            return [e for e in full if e.offset < start], start
    return [e for e in full if e.offset < at], None


def _check_cut(data: bytes, full: list[Event], units: list[tuple[int, int]], at: int, piece: int | None) -> None:
    expected, error_at = _expect_cut(full, units, at)
    events, error = decode_until_error(data[:at], piece)
    assert events == expected, at
    if error_at is None:
        assert error is None, (at, error)
    else:
        assert isinstance(error, errors.TruncatedError), (at, error)
        assert error.offset == error_at, at


SMALL_PIECES_UP_TO = 256 << 10


def test_cut_at_every_unit_edge(whole: Recording):
    """Cut at and just around every unit boundary: a cut on a boundary is a clean (footer-less) end,
    a cut inside a unit is TruncatedError at the unit's first byte, with everything before returned."""
    data = whole.data
    full = decode(data)
    units = _units(data)
    positions = {
        p for start, end in units for p in (start, start + 1, start + 8, start + 15, start + 16, start + 17, end - 1)
    }
    for at in sorted(p for p in positions if 0 < p < len(data)):
        _check_cut(data, full, units, at, None)
        # fed in pieces too: 7 bytes at a time for the first units, 4 KiB past them (7-byte pieces
        # of a large recording's every cut would take minutes and find nothing new)
        _check_cut(data, full, units, at, 7 if at <= SMALL_PIECES_UP_TO else 4096)


@settings(max_examples=60, deadline=None)
@given(
    fraction=st.floats(0, 1, exclude_max=True),
    piece=st.sampled_from([None, 1, 3, 16, 100, 4096]),
    name=st.sampled_from(["points", "blueprint", "no_footer", "merged"]),
)
def test_cut_anywhere(recordings: dict[str, Recording], fraction: float, piece: int | None, name: str):
    data = recordings[name].data
    at = 1 + int(fraction * (len(data) - 1))
    _check_cut(data, decode(data), _units(data), at, piece)


def test_empty_input_is_not_rrd():
    with pytest.raises(errors.NotAnRrdError) as info:
        decode(b"")
    assert info.value.offset == 0


# --- concatenated streams --------------------------------------------------------------------

CONCATENATIONS = [
    ("points", "scalars"),
    ("no_footer", "points"),  # the first stream has no End at all
    ("no_footer", "no_footer", "blueprint"),
    ("blueprint", "merged", "no_footer"),
]


@pytest.mark.parametrize("names", CONCATENATIONS, ids="+".join)
@pytest.mark.parametrize("piece", [None, 1, 7, 4096])
def test_concatenated_streams(recordings: dict[str, Recording], names: tuple[str, ...], piece: int | None):
    parts = [recordings[n].data for n in names]
    expected: list[Event] = []
    base = 0
    for index, part in enumerate(parts):
        expected += shifted(decode(part), base, index)
        base += len(part)
    data = b"".join(parts)
    decoder = RrdDecoder()
    step = piece or len(data)
    events: list[Event] = []
    for i in range(0, len(data), step):
        events += decoder.feed(data[i : i + step])
    events += decoder.finish()
    assert events == expected
    starts = [e for e in events if isinstance(e, StreamStart)]
    assert [(s.offset, s.stream_index) for s in starts] == [
        (sum(len(p) for p in parts[:i]), i) for i in range(len(parts))
    ]
    assert decoder.streams == len(parts)
    assert decoder.offset == len(data)


def test_concatenated_stream_offsets_match_sdk_manifests(recordings: dict[str, Recording]):
    """Offsets relative to each stream are what the SDK's footer of that stream records."""
    from services.rrd.manifest import read_manifest

    first, second = recordings["points"].data, recordings["blueprint"].data
    events = decode(first + second)
    manifests = [e.footer for e in events if isinstance(e, EndMessage)]
    assert len(manifests) == 2
    byte_offsets: dict[tuple[int, bytes], int] = {}
    for stream_index, footer in enumerate(manifests):
        assert footer is not None
        for manifest in footer.manifests:
            table = read_manifest(manifest)
            for chunk_id, offset in zip(
                table.column("chunk_id").to_pylist(), table.column("chunk_byte_offset").to_pylist(), strict=True
            ):
                byte_offsets[(stream_index, chunk_id)] = offset
    chunks = [e for e in events if isinstance(e, ArrowMessage)]
    assert len(chunks) == len(byte_offsets)
    for chunk in chunks:
        assert chunk.stream_offset == (0 if chunk.stream_index == 0 else len(first))
        assert chunk.chunk_id is not None
        assert chunk.stream_payload_offset == byte_offsets[(chunk.stream_index, chunk.chunk_id)]


# --- corrupted real files --------------------------------------------------------------------

# iter_events raises "at the end (after yielding everything before it)", and summarize /
# `fleet rrd inspect` count everything before a fault, whatever the read size.
READ_SIZES = [1, 7, pytest.param(None, id="one-read")]


def iter_until_error(data: bytes, read_size: int | None) -> tuple[list[Event], errors.RrdError | None]:
    events: list[Event] = []
    try:
        for event in iter_events(io.BytesIO(data), read_size=read_size or len(data)):
            events.append(event)
    except errors.RrdError as exc:
        return events, exc
    return events, None


@pytest.mark.parametrize("read_size", READ_SIZES)
def test_bad_footer_crc(recordings: dict[str, Recording], read_size: int | None):
    data = bytearray(recordings["points"].data)
    _, trailer = walk_frames(bytes(data))
    assert trailer is not None
    data[trailer + 16] ^= 0xFF  # the CRC
    events, error = iter_until_error(bytes(data), read_size)
    assert isinstance(error, errors.FooterError)
    assert error.offset == trailer
    assert events == [e for e in decode(recordings["points"].data) if e.offset < trailer]


@pytest.mark.parametrize("read_size", READ_SIZES)
def test_unknown_message_kind(recordings: dict[str, Recording], read_size: int | None):
    data = bytearray(recordings["scalars"].data)
    frames, _ = walk_frames(bytes(data))
    bad = frames[3]
    struct.pack_into("<Q", data, bad.offset, 9)
    events, error = iter_until_error(bytes(data), read_size)
    assert isinstance(error, errors.UnknownMessageKindError)
    assert error.offset == bad.offset
    assert [e.offset for e in events] == [0] + [f.offset for f in frames[:3]]


@pytest.mark.parametrize("read_size", READ_SIZES)
def test_message_too_large(recordings: dict[str, Recording], read_size: int | None):
    data = recordings["image"].data
    frames, _ = walk_frames(data)
    limit = max(f.length for f in frames) - 1
    first_too_large = next(f for f in frames if f.length > limit)
    events: list[Event] = []
    with pytest.raises(errors.MessageTooLargeError) as info:
        for event in iter_events(io.BytesIO(data), max_message_size=limit, read_size=read_size or len(data)):
            events.append(event)
    assert info.value.offset == first_too_large.offset
    assert [e.offset for e in events] == [0] + [f.offset for f in frames if f.offset < first_too_large.offset]


def test_message_size_limit_is_inclusive(recordings: dict[str, Recording]):
    data = recordings["image"].data
    frames, _ = walk_frames(data)
    limit = max(f.length for f in frames)
    assert list(iter_events(io.BytesIO(data), max_message_size=limit)) == decode(data)
