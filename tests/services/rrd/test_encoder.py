"""RrdEncoder: re-write real recordings message by message; Rerun's own tools must accept the result
and the footer manifest must equal the one the SDK wrote."""

from __future__ import annotations

import io
import subprocess
from collections.abc import Callable, Iterable
from pathlib import Path

import lz4.block
import pyarrow as pa
import pytest

from services.rrd import (
    ArrowMessage,
    BlueprintActivationMessage,
    EndMessage,
    MessageKind,
    RerunVersion,
    RrdEncoder,
    StoreId,
    StoreInfoMessage,
    StreamFooter,
    StreamStart,
    chunk_meta,
    iter_events,
)
from services.rrd.manifest import read_manifest, read_sorbet_schema
from services.rrd.messages import Event, Message
from services.rrd.pb import log_msg_pb2
from tests.services.rrd.recordings import Recording, walk_frames

pytestmark = pytest.mark.sdk


def rewrite(
    events: Iterable[Event], out: Path, *, write_footer: bool = True, keep: Callable[[Message], bool] = lambda m: True
) -> None:
    """Write every message of `events` (not End / footers / stream headers) into one new stream."""
    encoder: RrdEncoder | None = None
    with open(out, "wb") as sink:
        for event in events:
            if isinstance(event, StreamStart):
                if encoder is None:
                    encoder = RrdEncoder(sink, event.version, write_footer=write_footer)
                continue
            if isinstance(event, EndMessage | StreamFooter) or not keep(event):
                continue
            assert encoder is not None
            encoder.write(event)
        assert encoder is not None
        encoder.finish()
        assert encoder.position == sink.tell()


def rerun(rerun_bin: str, *args: str | Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([rerun_bin, *map(str, args)], capture_output=True, text=True, timeout=120)


def assert_ok(result: subprocess.CompletedProcess[str]) -> None:
    assert result.returncode == 0, f"{result.args}: exit {result.returncode}\n{result.stderr[-3000:]}"


def footer_manifests(path: Path | bytes) -> dict[StoreId, log_msg_pb2.RrdManifest]:
    source = io.BytesIO(path) if isinstance(path, bytes) else path
    ends = [e for e in iter_events(source) if isinstance(e, EndMessage)]
    assert len(ends) == 1 and ends[0].footer is not None
    return {StoreId.from_proto(m.store_id): m for m in ends[0].footer.manifests}


# --- round trips through Rerun's tools ---------------------------------------------------------


def test_roundtrip_passes_rerun_verify_and_compare(rerun_bin: str, whole: Recording, tmp_path: Path):
    out = tmp_path / "out.rrd"
    rewrite(iter_events(whole.path), out)
    assert_ok(rerun(rerun_bin, "rrd", "verify", out))  # footers checked (the default)
    if len(whole.recordings) == 1:  # `rrd compare` refuses files with several recordings
        assert_ok(rerun(rerun_bin, "rrd", "compare", "--unordered", whole.path, out))


def test_roundtrip_copies_messages_byte_for_byte(whole: Recording, tmp_path: Path):
    out = tmp_path / "out.rrd"
    rewrite(iter_events(whole.path), out)
    original, written = whole.data, out.read_bytes()
    frames, _ = walk_frames(original)
    body_end = frames[-1].offset if frames[-1].kind == MessageKind.END else frames[-1].end
    assert written[:body_end] == original[:body_end]  # header and every message up to End

    events = list(iter_events(out))
    assert [type(e) for e in events[-2:]] == [EndMessage, StreamFooter]
    assert sum(isinstance(e, StreamStart) for e in events) == 1
    chunk_stores = {e.store_id for e in events if isinstance(e, ArrowMessage)}
    assert set(footer_manifests(out)) == chunk_stores


def test_merged_roundtrip_per_recording(rerun_bin: str, recordings: dict[str, Recording], tmp_path: Path):
    """The two-recording file: each recording cut out of our rewrite equals the SDK's original."""
    merged = tmp_path / "merged.rrd"
    rewrite(iter_events(recordings["merged"].path), merged)
    assert_ok(rerun(rerun_bin, "rrd", "verify", merged))
    for name in ("merge_a", "merge_b"):
        recording_id: str = recordings[name].recordings[0]["recording_id"]
        part = tmp_path / f"{name}.rrd"

        def keep(msg: Message, rid: str = recording_id) -> bool:
            return _store_of(msg).recording_id == rid

        rewrite(iter_events(merged), part, keep=keep)
        assert_ok(rerun(rerun_bin, "rrd", "verify", part))
        assert_ok(rerun(rerun_bin, "rrd", "compare", "--unordered", recordings[name].path, part))
        assert {s.recording_id for s in footer_manifests(part)} == {recording_id}


def _store_of(msg: Message) -> StoreId:
    if isinstance(msg, BlueprintActivationMessage):
        return msg.blueprint_id
    assert isinstance(msg, StoreInfoMessage | ArrowMessage)
    return msg.store_id


def test_no_footer_file_gets_a_footer(rerun_bin: str, recordings: dict[str, Recording], tmp_path: Path):
    source = recordings["no_footer"].path
    assert rerun(rerun_bin, "rrd", "verify", source).returncode != 0  # Rerun wants a footer
    out = tmp_path / "out.rrd"
    rewrite(iter_events(source), out)
    assert_ok(rerun(rerun_bin, "rrd", "verify", out))
    assert_ok(rerun(rerun_bin, "rrd", "compare", "--unordered", source, out))
    (manifest,) = footer_manifests(out).values()
    chunks = [e for e in iter_events(source) if isinstance(e, ArrowMessage)]
    table = read_manifest(manifest)
    assert table.column("chunk_id").to_pylist() == [c.chunk_id for c in chunks]
    assert table.column("chunk_byte_offset").to_pylist() == [c.stream_payload_offset for c in chunks]


def test_cut_file_prefix_is_a_valid_recording(rerun_bin: str, recordings: dict[str, Recording], tmp_path: Path):
    """What the decoder returns before a torn message re-encodes into a file Rerun accepts."""
    events: list[Event] = []
    with pytest.raises(Exception, match="truncated"):
        for event in iter_events(recordings["cut"].path):
            events.append(event)
    out = tmp_path / "repaired.rrd"
    rewrite(events, out)
    assert_ok(rerun(rerun_bin, "rrd", "verify", out))
    (manifest,) = footer_manifests(out).values()
    assert read_manifest(manifest).num_rows == sum(isinstance(e, ArrowMessage) for e in events)


def test_without_footer(rerun_bin: str, recordings: dict[str, Recording], tmp_path: Path):
    source = recordings["scalars"].path
    out = tmp_path / "out.rrd"
    rewrite(iter_events(source), out, write_footer=False)
    events = list(iter_events(out))
    assert isinstance(events[-1], EndMessage)
    assert events[-1].raw == b"" and events[-1].footer is None
    assert not any(isinstance(e, StreamFooter) for e in events)
    assert_ok(rerun(rerun_bin, "rrd", "verify", "--check-footers", "false", out))
    assert_ok(rerun(rerun_bin, "rrd", "compare", "--unordered", source, out))


def test_concatenation_rewritten_as_one_stream(rerun_bin: str, recordings: dict[str, Recording], tmp_path: Path):
    """`cat a.rrd b.rrd` breaks footer readers; re-encoding it gives one stream with both footers' stores."""
    data = recordings["points"].data + recordings["no_footer"].data + recordings["blueprint"].data
    out = tmp_path / "out.rrd"
    rewrite(iter_events(io.BytesIO(data)), out)
    assert_ok(rerun(rerun_bin, "rrd", "verify", out))
    events = list(iter_events(out))
    assert sum(isinstance(e, StreamStart) for e in events) == 1
    assert {s.recording_id for s in footer_manifests(out) if not s.is_blueprint} == {
        "rec-points",
        "rec-no-footer",
        "rec-blueprint",
    }


# --- the manifest equals the SDK's ------------------------------------------------------------


def test_manifest_equals_sdk_manifest(footer_file: Recording, tmp_path: Path):
    out = tmp_path / "out.rrd"
    rewrite(iter_events(footer_file.path), out)
    theirs, ours = footer_manifests(footer_file.path), footer_manifests(out)
    assert set(ours) == set(theirs)
    for store_id, sdk in theirs.items():
        mine = ours[store_id]
        assert mine.store_id == sdk.store_id
        assert mine.data.encoder_version == sdk.data.encoder_version
        sdk_table, our_table = read_manifest(sdk), read_manifest(mine)
        assert our_table.schema.names == sdk_table.schema.names, store_id
        for sdk_field in sdk_table.schema:
            our_field = our_table.schema.field(sdk_field.name)
            assert our_field.type == sdk_field.type, sdk_field.name
            assert our_field.nullable == sdk_field.nullable, sdk_field.name
            assert our_field.metadata == sdk_field.metadata, sdk_field.name
        sdk_rows, our_rows = sdk_table.sort_by("chunk_id"), our_table.sort_by("chunk_id")
        assert our_rows.num_rows == sdk_rows.num_rows
        for name in sdk_table.schema.names:  # chunk_byte_offset too: every message is copied as is
            assert our_rows.column(name).equals(sdk_rows.column(name)), (store_id, name)

        sdk_schema, our_schema = read_sorbet_schema(sdk), read_sorbet_schema(mine)
        assert set(our_schema.names) == set(sdk_schema.names), store_id
        for sdk_field in sdk_schema:
            our_field = our_schema.field(sdk_field.name)
            assert (our_field.type, our_field.nullable, our_field.metadata) == (
                sdk_field.type,
                sdk_field.nullable,
                sdk_field.metadata,
            ), sdk_field.name


def test_manifest_is_lz4_compressed_arrow(footer_file: Recording, tmp_path: Path):
    out = tmp_path / "out.rrd"
    rewrite(iter_events(footer_file.path), out)
    for manifest in footer_manifests(out).values():
        assert manifest.data.compression == 2
        ipc = lz4.block.decompress(manifest.data.payload, uncompressed_size=manifest.data.uncompressed_size)
        assert len(ipc) == manifest.data.uncompressed_size
        assert pa.ipc.open_stream(ipc).read_all().equals(read_manifest(manifest))
        assert len(manifest.sorbet_schema_sha256) == 32


# --- API -------------------------------------------------------------------------------------


def test_encoder_api(recordings: dict[str, Recording]):
    events = list(iter_events(recordings["properties"].path))
    messages = [e for e in events if isinstance(e, StoreInfoMessage | ArrowMessage)]

    plain, raw = io.BytesIO(), io.BytesIO()
    a = RrdEncoder(plain, RerunVersion(0, 41, 0))
    b = RrdEncoder(raw, RerunVersion(0, 41, 0))
    assert plain.getvalue() == recordings["properties"].data[:12]
    for msg in messages:
        a.write(msg)
        if isinstance(msg, ArrowMessage):
            with pytest.raises(ValueError, match="store id and chunk metadata"):
                b.write_raw(MessageKind.ARROW_MSG, msg.raw)
            b.write_raw(MessageKind.ARROW_MSG, msg.raw, store_id=msg.store_id, meta=chunk_meta(msg))
        else:
            b.write_raw(msg.kind, msg.raw)
        assert a.position == len(plain.getvalue())
    a.finish()
    b.finish()
    assert plain.getvalue() == raw.getvalue()
    assert a.position == len(plain.getvalue())

    written = plain.getvalue()
    a.finish()  # idempotent
    assert plain.getvalue() == written
    with pytest.raises(ValueError, match="finished"):
        a.write(messages[0])
    # Writing an End message is a no-op: finish() writes this stream's own.
    c_out = io.BytesIO()
    c = RrdEncoder(c_out, RerunVersion(0, 41, 0))
    for event in events:
        if isinstance(event, StoreInfoMessage | ArrowMessage | EndMessage):
            c.write(event)
    c.finish()
    assert c_out.getvalue() == written
