"""Answers to an assistant stay bounded and say when they were cut."""

from __future__ import annotations

import json

from services.mcp_server.depot import bounded


def test_a_small_answer_is_whole() -> None:
    assert bounded({"runs": [1, 2, 3]}) == {"result": {"runs": [1, 2, 3]}, "truncated": False}


def test_long_lists_are_cut_and_say_so() -> None:
    answer = bounded({"runs": list(range(500)), "next_cursor": "c"}, max_items=100)
    assert answer["result"]["runs"] == list(range(100)) and answer["result"]["next_cursor"] == "c"
    assert answer["truncated"] is True and "500 items" in answer["note"]


def test_an_answer_too_large_is_shrunk_under_the_bound() -> None:
    rows = [{"text": "x" * 1000, "n": i} for i in range(90)]
    answer = bounded({"rows": rows}, max_bytes=20_000)
    assert len(json.dumps(answer["result"])) <= 20_000 and answer["truncated"] is True
    assert answer["result"]["rows"][0] == rows[0]  # what is kept is the first part, as it was
