"""Sealing writes each analytics table to its Parquet file as the rows come (`Extractor` with a
spill folder), a few thousand rows held at a time: the file holds exactly what the rows held in
memory would, including timelines that appear part-way through a run."""

from __future__ import annotations

from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from services.analytics import extract
from services.analytics.extract import Extractor


def scalar_rows(run: str, first: int, n: int, timelines: dict[str, pa.DataType]) -> pa.Table:
    columns: dict[str, pa.Array] = {
        "run_id": pa.array([run] * n),
        "entity": pa.array(["/battery"] * n),
        "value": pa.array([float(first + i) for i in range(n)], pa.float64()),
    }
    for name, kind in timelines.items():
        columns[name] = pa.array(range(first, first + n), pa.int64()).cast(kind)
    return pa.table(columns)


@pytest.mark.parametrize("spill_rows", [1, 4, 1000])
def test_spilled_files_hold_what_memory_holds(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, spill_rows: int):
    monkeypatch.setattr(extract, "SPILL_ROWS", spill_rows)
    pieces = [
        scalar_rows("r", 0, 3, {"frame": pa.int64()}),
        scalar_rows("r", 3, 2, {"frame": pa.int64()}),
        # a timeline that appears later in the run, then pieces without the first one
        scalar_rows("r", 5, 4, {"frame": pa.int64(), "log_time": pa.timestamp("ns")}),
        scalar_rows("r", 9, 2, {"log_time": pa.timestamp("ns")}),
        scalar_rows("r", 11, 5, {"frame": pa.int64()}),
    ]
    in_memory, spilled = Extractor("r"), Extractor("r", tmp_path)
    for piece in pieces:
        in_memory.append("scalars", piece)
        spilled.append("scalars", piece)

    files = spilled.files()

    assert set(files) == {"scalars"}
    expected = in_memory.tables()["scalars"]
    written = pq.read_table(files["scalars"])
    assert written.num_rows == 16
    assert sorted(written.column_names) == sorted(expected.column_names)
    assert written.select(expected.column_names).equals(expected)
    assert [p.name for p in tmp_path.iterdir()] == ["scalars.parquet"]  # the parts are gone


def test_a_table_without_rows_has_no_file(tmp_path: Path):
    extractor = Extractor("r", tmp_path)
    extractor.append("text_logs", scalar_rows("r", 0, 2, {"frame": pa.int64()}))
    assert set(extractor.files()) == {"text_logs"}
    assert Extractor("r", tmp_path / "none").files() == {}


def test_rows_are_copied_when_spilled_not_kept_as_slices_of_their_chunks(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    """Extracted columns are slices of the chunk's buffers; held as they are, each would keep its
    whole chunk alive until the run's end (about 25 KB per chunk of 100 scalars)."""
    monkeypatch.setattr(extract, "SPILL_ROWS", 100)
    extractor = Extractor("r", tmp_path)
    before = pa.total_allocated_bytes()
    for i in range(50):
        chunk = scalar_rows("r", i * 100, 100, {"frame": pa.int64()})
        big = pa.table({"padding": pa.array([b"x" * 10_000] * 100, pa.binary()), **chunk.to_pydict()})
        extractor.append("scalars", big.select(chunk.column_names).slice(0, 100))
    held = pa.total_allocated_bytes() - before
    assert held < 2 * 10_000 * 100, f"{held} bytes held after 50 chunks"
    assert pq.read_table(extractor.files()["scalars"]).num_rows == 5000
