"""A binary flight file with its pairs as columns: the same flight as its rows, read in place,
and bad columns refused naming the column (or, for a pair, as the rows' parse names it)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest
from pydantic import ValidationError

from hmcc import InputError
from hmcc_schema import validation_issues
from hmcc_schema.columns import PairColumns, pairs_are_columns
from hmcc_schema.flight_columns import (
    column_rows,
    encode_flight_columns,
    read_flight_columns,
    write_flight_columns,
)
from hmcc_schema.flight_file import MappedFlightFile, read_flight_file, write_flight_file
from tests.support.flights import small_flight


def _doc(n: int) -> dict[str, Any]:
    doc = small_flight(n)
    doc.pop("truth")
    return doc


def _mapped(path: Path) -> MappedFlightFile:
    mapped = MappedFlightFile.open(path)
    assert mapped is not None
    return mapped


def _columns_file(tmp_path: Path, doc: dict[str, Any], name: str = "columns") -> Path:
    doc = dict(doc)
    path = tmp_path / f"{name}.msgpack"
    write_flight_columns(path, doc.pop("images"), doc.pop("pairs"), **doc)
    return path


def test_columns_give_the_flight_of_the_rows_and_the_same_results(tmp_path: Path) -> None:
    doc = _doc(4)
    rows = tmp_path / "rows.msgpack"
    write_flight_file(rows, doc["images"], doc["pairs"], plane=doc["plane"])
    path = _columns_file(tmp_path, doc)
    mapped = _mapped(path)
    assert pairs_are_columns(mapped.data) and not pairs_are_columns(_mapped(rows).data)
    assert mapped.pair_count() == _mapped(rows).pair_count() == 4
    flight, whole = read_flight_columns(mapped), read_flight_file(rows)
    assert isinstance(flight.pairs, PairColumns) and len(flight.pairs) == 4
    assert (flight.method, flight.plane_z, flight.options) == (
        whole.method,
        whole.plane_z,
        whole.options,
    )
    assert flight.images.keys() == whole.images.keys()
    for i, (p, q) in enumerate(zip(flight.pairs, whole.pairs, strict=True)):
        assert (p.id, p.image1, p.image2) == (q.id, q.image1, q.image2)
        assert p.matches.dtype == np.int64
        np.testing.assert_array_equal(p.matches, q.matches)
        np.testing.assert_array_equal(flight.verify(i).inliers, whole.verify(i).inliers)


def test_the_columns_stay_in_the_file(tmp_path: Path) -> None:
    """Nothing of the matches is copied: their column is a view of the mapping, as are the
    images' keypoints."""
    path = _columns_file(tmp_path, _doc(3))
    mapped = _mapped(path)
    flight = read_flight_columns(mapped)
    assert isinstance(flight.pairs, PairColumns)
    assert mapped.offset(flight.pairs.matches) is not None
    keypoints = flight.images["a0"].keypoints
    assert keypoints is not None and mapped.offset(keypoints) is not None


def test_a_selection_of_pairs_is_columns_too(tmp_path: Path) -> None:
    flight = read_flight_columns(_mapped(_columns_file(tmp_path, _doc(5))))
    pairs = flight.pairs
    assert isinstance(pairs, PairColumns)
    part = pairs.take([4, 1, 2])
    assert isinstance(part, PairColumns) and part.matches is pairs.matches
    assert [p.id for p in part] == ["p4", "p1", "p2"]
    assert [p.id for p in part.take([2, 0])] == ["p2", "p4"]
    assert part[-1].id == "p2" and [p.id for p in pairs[1:3]] == ["p1", "p2"]
    with pytest.raises(IndexError):
        part[3]


def test_pairs_without_ids_have_none(tmp_path: Path) -> None:
    doc = _doc(2)
    for pair in doc["pairs"]:
        del pair["id"]
    flight = read_flight_columns(_mapped(_columns_file(tmp_path, doc)))
    assert [p.id for p in flight.pairs] == [None, None]
    assert "id" not in msgpack.unpackb(_columns_file(tmp_path, doc).read_bytes())["pairs"]


def test_a_pair_that_is_not_matches_only_has_no_columns() -> None:
    doc = _doc(2)
    doc["pairs"][1]["keypoints1"] = np.zeros((3, 2))
    with pytest.raises(ValueError, match=r"pairs\[1\] has \['keypoints1', 'matches'\]"):
        encode_flight_columns(doc["images"], doc["pairs"])
    doc["pairs"][1] = {"image1": "a1", "image2": "b1", "match": True}
    with pytest.raises(ValueError, match=r"pairs\[1\]"):
        encode_flight_columns(doc["images"], doc["pairs"])


def _rewritten(tmp_path: Path, change: Callable[[dict[str, Any]], None]) -> MappedFlightFile:
    """The columns file of a three-pair flight with ``change`` made to its document."""
    doc = msgpack.unpackb(_columns_file(tmp_path, _doc(3)).read_bytes())
    change(doc)
    path = tmp_path / "changed.msgpack"
    path.write_bytes(msgpack.packb(doc))
    return _mapped(path)


def _counts(doc: dict[str, Any], counts: list[int]) -> None:
    doc["pairs"]["counts"]["data"] = np.asarray(counts, "<i8").tobytes()


def _first_count_moved(doc: dict[str, Any]) -> None:
    """Pair 0 one match fewer, pair 1 one more: the counts still add up."""
    counts = np.frombuffer(doc["pairs"]["counts"]["data"], "<i8").copy()
    counts[0] -= 1
    counts[1] += 1
    doc["pairs"]["counts"]["data"] = counts.tobytes()


def _set(doc: dict[str, Any], pair: int, row: int, column: int, value: int) -> None:
    """Match ``row`` of pair ``pair``: its index in ``column`` made ``value``."""
    m = doc["pairs"]["matches"]
    matches = np.frombuffer(m["data"], m["dtype"]).reshape(m["shape"]).copy()
    start = int(np.frombuffer(doc["pairs"]["counts"]["data"], "<i8")[:pair].sum())
    matches[start + row, column] = value
    m["data"] = matches.tobytes()


@pytest.mark.parametrize(
    ("change", "field", "reason"),
    [
        (lambda d: d["pairs"].update(extra=[1, 2, 3]), "pairs.extra", "not a column"),
        (lambda d: d["pairs"].pop("counts"), "pairs.counts", "missing"),
        (lambda d: d["pairs"]["image2"].pop(), "pairs.image2", "2 values; one a pair: 3"),
        (lambda d: d["pairs"].update(id=["x"]), "pairs.id", "1 values; one a pair: 3"),
        (lambda d: d["pairs"].update(image1="a0"), "pairs.image1", "a column is an array"),
        (lambda d: _counts(d, [1, 2, 3]), "pairs.matches", "the counts add up to 6"),
        (lambda d: _counts(d, [0, 2, 3]), "pairs.counts[0]", "0 matches; a pair has 1 to"),
        (lambda d: d["pairs"]["counts"].update(dtype="<f8"), "pairs.counts", "dtype '<f8'"),
        (lambda d: d["pairs"].update(matches=[[0, 1]]), "pairs.matches", "a buffer"),
        (
            lambda d: d["pairs"]["matches"].update(shape=[-1, 4]),
            "pairs.matches",
            "shape",
        ),
    ],
)
def test_a_column_that_is_not_one_is_refused_naming_it(
    tmp_path: Path, change: Callable[[dict[str, Any]], None], field: str, reason: str
) -> None:
    mapped = _rewritten(tmp_path, change)
    with pytest.raises(InputError) as refused:
        read_flight_columns(mapped)
    assert refused.value.field == field and reason in refused.value.reason, refused.value


@pytest.mark.parametrize(
    ("change", "field", "reason"),
    [
        (lambda d: d["pairs"]["image2"].__setitem__(1, "nowhere"), "pairs[1].image2", "no image"),
        (
            lambda d: _set(d, 1, 7, 1, 150_000),
            "pairs[1].matches",
            "matches[7][1] = 150000 is out of range",
        ),
        (lambda d: _set(d, 2, 5, 0, -1), "pairs[2].matches[5][0]", "greater than or equal"),
        (lambda d: d["pairs"]["id"].__setitem__(2, 7), "pairs[2].id", ""),
        (lambda d: d["images"]["b2"]["pose"].pop("position"), "images.b2.pose.position", ""),
        (lambda d: d["images"]["b1"].pop("pose"), "images.b1.pose", "uses the rough poses"),
    ],
)
def test_a_bad_pair_is_refused_as_the_rows_parse_refuses_it(
    tmp_path: Path, change: Callable[[dict[str, Any]], None], field: str, reason: str
) -> None:
    """Past the columns, a pair is checked as a row would be: the same field and reason."""
    mapped = _rewritten(tmp_path, change)
    with pytest.raises((InputError, ValidationError)) as refused:
        read_flight_columns(mapped)
    issues = [(issue.field, issue.reason) for issue in validation_issues(refused.value)]
    assert any(f == field and reason in r for f, r in issues), issues


def test_counts_that_move_matches_between_pairs_give_those_pairs(tmp_path: Path) -> None:
    """The columns say where each pair's matches start: pairs of other lengths read as such
    (the counts decide, as a writer wrote them)."""
    flight = read_flight_columns(_rewritten(tmp_path, _first_count_moved))
    whole = read_flight_columns(_mapped(_columns_file(tmp_path, _doc(3), "whole")))
    assert len(flight.pairs[0].matches) == len(whole.pairs[0].matches) - 1
    np.testing.assert_array_equal(flight.pairs[0].matches, whole.pairs[0].matches[:-1])


def test_more_pairs_than_allowed_are_refused(tmp_path: Path) -> None:
    with pytest.raises(InputError) as refused:
        read_flight_columns(_mapped(_columns_file(tmp_path, _doc(3))), max_pairs=2)
    assert refused.value.field == "pairs"


def test_columns_read_as_rows_for_a_client(tmp_path: Path) -> None:
    doc = _doc(3)
    unpacked = msgpack.unpackb(_columns_file(tmp_path, doc).read_bytes())
    rows = column_rows(unpacked["pairs"])
    assert [(r["id"], r["image1"], r["image2"]) for r in rows] == [
        (p["id"], p["image1"], p["image2"]) for p in doc["pairs"]
    ]
    for row, pair in zip(rows, doc["pairs"], strict=True):
        np.testing.assert_array_equal(row["matches"], pair["matches"])


def test_a_file_that_is_not_columns_is_not_counted_as_such(tmp_path: Path) -> None:
    path = tmp_path / "odd.msgpack"
    path.write_bytes(msgpack.packb({"pairs": {"counts": 3}}))  # columns, but no image1
    assert pairs_are_columns(_mapped(path).data) and _mapped(path).pair_count() == 0
    path.write_bytes(msgpack.packb({"images": {}}) + b"\xc1")
    assert not pairs_are_columns(_mapped(path).data) and _mapped(path).pair_count() == 0


def test_a_file_of_columns_cut_short_is_refused_as_such(tmp_path: Path) -> None:
    path = _columns_file(tmp_path, _doc(2))
    path.write_bytes(path.read_bytes()[:-100])
    with pytest.raises(InputError) as refused:
        read_flight_columns(_mapped(path))
    assert refused.value.field == "body" and "cut short" in refused.value.reason
