"""The one door for Arrow IPC and LZ4 from clients (`services.rrd.untrusted`): hostile tables and
chunks are refused with a clear codec error, in a process of their own (a crash fails the test, not
pytest), and only the modules listed here with their reasons read Arrow IPC or LZ4 themselves."""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import lz4.block
import pytest

from services.rrd import errors, untrusted
from tests.services.rrd import hostile

REPO = Path(__file__).resolve().parents[3]

CASES_SCRIPT = """
import json
from services.redap.pb import cloud_pb2
from services.redap.chunks import requested_chunks
from services.rrd.chunk import chunk_meta
from services.rrd.decoder import decode_message
from services.rrd.validate import check_chunk
from services.rrd.errors import RrdError
from core.errors import FleetError
from tests.services.rrd import hostile

out = []
for part in hostile.hostile_dataframe_parts():
    try:
        requested_chunks(cloud_pb2.FetchChunksRequest(chunk_infos=[part]))
        out.append(("part", "accepted", ""))
    except FleetError as exc:
        out.append(("part", exc.code.name, str(exc)))
for payload in hostile.hostile_chunks():
    try:
        msg = decode_message(2, hostile.arrow_msg("r", payload))
        check_chunk(msg, chunk_meta(msg))
        out.append((payload.name, "accepted", ""))
    except RrdError as exc:
        out.append((payload.name, exc.code.name, str(exc)))
# VmHWM: this process's own peak (ru_maxrss keeps the forking parent's size across exec).
peak_kib = int(next(l.split()[1] for l in open("/proc/self/status") if l.startswith("VmHWM:")))
print(json.dumps({"cases": out, "max_rss_mib": peak_kib // 1024}))
"""


def test_hostile_tables_and_chunks_are_refused_in_a_process_that_survives() -> None:
    done = subprocess.run(
        [sys.executable, "-c", CASES_SCRIPT], capture_output=True, text=True, timeout=120, cwd=REPO, check=False
    )
    assert done.returncode == 0, f"the reading process died ({done.returncode}): {done.stderr[-2000:]}"
    answer = json.loads(done.stdout)
    cases = answer["cases"]
    assert len(cases) == len(hostile.hostile_dataframe_parts()) + len(hostile.hostile_chunks())
    for name, code, message in cases:
        assert code in ("INVALID_RRD", "MESSAGE_TOO_LARGE", "INVALID_ARGUMENT"), (name, code, message)
    # Nothing declared was allocated: 1 GiB declarations are refused before decompressing.
    assert answer["max_rss_mib"] < 600, answer["max_rss_mib"]


def test_a_declared_size_over_the_limit_is_refused_before_decompressing(monkeypatch: pytest.MonkeyPatch) -> None:
    def never(*args: object, **kwargs: object) -> bytes:
        raise AssertionError("decompressed")

    monkeypatch.setattr(lz4.block, "decompress", never)
    block = lz4.block.compress(bytes(4 << 20), store_size=False)
    with pytest.raises(errors.MessageTooLargeError, match="over the limit"):
        untrusted.decompress(block, hostile.GIB)
    with pytest.raises(errors.DecompressionError, match="cannot decompress to"):
        untrusted.decompress(block[:100], 100 * 255 + 65)


def test_ipc_body_compression_is_refused_before_it_is_read() -> None:
    with pytest.raises(errors.NotArrowError, match="IPC body compression"):
        untrusted.read_table(hostile.body_compressed(hostile.points()))


def test_a_valid_table_reads() -> None:
    table = untrusted.payload_table(
        True,
        lz4.block.compress(hostile.ipc_stream(hostile.points()), store_size=False),
        len(hostile.ipc_stream(hostile.points())),
    )
    assert table.num_rows == 3


# --- client bytes reach Arrow IPC and LZ4 readers only through the door -----------------------------

READERS = {
    ("pa", "ipc", "open_stream"),
    ("pa", "ipc", "open_file"),
    ("pa", "ipc", "read_message"),
    ("pa", "ipc", "read_record_batch"),
    ("pa", "ipc", "read_schema"),
    ("pa", "ipc", "read_tensor"),
    ("pa", "ipc", "RecordBatchStreamReader"),
    ("pa", "ipc", "RecordBatchFileReader"),
    ("pa", "ipc", "MessageReader"),
    ("lz4", "block", "decompress"),
    ("lz4", "frame", "decompress"),
    ("_lz4", "decompress"),
}
# Where the codec reads them, and why each is safe: client bytes only through `untrusted`.
ALLOWED = {
    "services/rrd/untrusted.py": "the door itself",
    "services/rrd/chunk.py": "chunks: decompression through untrusted.decompress; IPC read message by message, "
    "body compression refused first, fully validated before values are read (validate.check_chunk)",
    "services/rrd/layout.py": "a chunk's schema message, read by pyarrow's flatbuffers verifier (no values)",
    "services/rrd/manifest.py": "RRD footers the depot wrote itself (sealed runs)",
    "services/hot/index.py": "the depot's own hot chunk index (chunks.idx), written from validated chunks",
    "services/analytics/worker.py": "the catalog tables the depot sends its SQL worker",
    "services/rrd/known_components.py": "its own table of Rerun's component types, generated into the module",
}


def _calls(tree: ast.AST) -> set[tuple[str, ...]]:
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute):
            parts: list[str] = [node.attr]
            value: ast.expr = node.value
            while isinstance(value, ast.Attribute):
                parts.insert(0, value.attr)
                value = value.value
            if isinstance(value, ast.Name):
                parts.insert(0, value.id)
            found.add(tuple(parts))
    return found


def test_arrow_ipc_and_lz4_are_read_only_where_listed() -> None:
    """A module that reads Arrow IPC or LZ4 itself must be listed here with why it is safe; what
    clients send (and what the SQL sandbox answers) is read through services.rrd.untrusted."""
    readers: dict[str, set[tuple[str, ...]]] = {}
    for path in sorted((REPO / "services").rglob("*.py")):
        relative = path.relative_to(REPO).as_posix()
        if "/pb/" in relative:
            continue
        used = _calls(ast.parse(path.read_text())) & READERS
        if used:
            readers[relative] = used
    unexpected = {path: sorted(".".join(c) for c in used) for path, used in readers.items() if path not in ALLOWED}
    assert not unexpected, (
        f"these modules read Arrow IPC or LZ4 themselves: {unexpected}; read what clients send through "
        "services.rrd.untrusted (full validation, sizes checked first)"
    )
    assert set(readers) == set(ALLOWED), f"ALLOWED names modules that no longer read: {set(ALLOWED) - set(readers)}"
