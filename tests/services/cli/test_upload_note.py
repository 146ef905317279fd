"""What `fleet upload` says a refused upload left on the depot: the true outcome, as the depot
reports it (a run refused part-way is dropped whole; its chunks are not "kept")."""

from __future__ import annotations

from services.cli.upload import kept_note


def test_a_dropped_run_is_said_to_be_dropped_not_kept():
    note = kept_note({"runs": [], "dropped": ["rec-1"], "chunks_new": 0, "chunks_duplicate": 0})
    assert note == " (run rec-1 dropped whole: nothing of it is kept)"
    assert "is kept: " not in note


def test_runs_kept_before_a_fault_are_named_with_their_chunks():
    note = kept_note({"runs": ["rec-2"], "dropped": ["rec-1"], "chunks_new": 3, "chunks_duplicate": 1})
    assert note == (
        " (run rec-1 dropped whole: nothing of it is kept;"
        " what came before it is kept: 3 new chunks in rec-2, 1 already held)"
    )


def test_a_fault_part_way_keeps_what_came_before():
    note = kept_note({"runs": ["rec-2"], "chunks_new": 2, "chunks_duplicate": 0})
    assert note == " (what came before it is kept: 2 new chunks in rec-2, 0 already held)"
    assert kept_note({}) == ""
