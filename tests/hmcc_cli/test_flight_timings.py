"""``hmcc flight``'s timeline and its guess of a file's pair count (no children run here)."""

from __future__ import annotations

import orjson

from hmcc_cli.flight import Timeline, pair_estimate
from hmcc_schema.flight_file import encode_flight


def _pairs(n: int) -> list[dict[str, object]]:
    return [{"id": f"p{i}", "image1": "a", "image2": "b", "matches": [[0, 1]]} for i in range(n)]


def test_the_pair_estimate_counts_pairs_in_both_formats_without_parsing() -> None:
    images = {"a": {"camera": {}, "pose": {}}, "b": {"camera": {}, "pose": {}}}
    assert pair_estimate(orjson.dumps({"images": images, "pairs": _pairs(7)})) == 7
    assert pair_estimate(encode_flight(images, _pairs(5))) == 5


def test_a_timeline_keeps_each_steps_first_mark_in_order() -> None:
    timeline = Timeline()
    timeline.mark("read")
    timeline.mark("parsed")
    timeline.mark("read")
    marks = timeline.marks()
    assert list(marks) == ["read", "parsed"]
    assert 0 <= marks["read"] <= marks["parsed"]
    assert timeline.line().startswith("timeline (s from the process's start): read ")
