"""hmcc_schema.columns: a batch body whose pairs are columns gives the flight its rows give,
wherever ``pairs`` lies in it; a body of rows, JSON or MessagePack, is parsed as rows; what is
wrong is named as for rows; a selection's helpers give what its pairs one at a time give."""

from __future__ import annotations

from typing import Any

import msgpack
import numpy as np
import orjson
import pytest
from pydantic import ValidationError

from hmcc import InputError
from hmcc_schema.columns import PairColumns, pairs_are_columns, parse_batch_body
from hmcc_schema.flight_columns import encode_flight_columns
from hmcc_schema.flight_file import encode_flight
from hmcc_schema.parse import JSON, MAX_DEPTH, MSGPACK
from tests.support.flights import small_flight


def _doc(n: int) -> dict[str, Any]:
    doc = small_flight(n)
    doc.pop("truth")
    return doc


def _bodies(doc: dict[str, Any]) -> tuple[bytes, bytes]:
    """The flight ``doc`` as a MessagePack body with its pairs as columns, and as rows."""
    extra = {"plane": doc["plane"], "params": {"result": "inliers"}}
    return (
        encode_flight_columns(doc["images"], doc["pairs"], **extra),
        encode_flight(doc["images"], doc["pairs"], **extra),
    )


def test_a_body_of_columns_gives_the_flight_of_its_rows() -> None:
    columns, rows = _bodies(_doc(5))
    got, want = parse_batch_body(columns, 100, MSGPACK), parse_batch_body(rows, 100, MSGPACK)
    assert isinstance(got.pairs, PairColumns) and isinstance(want.pairs, list)
    assert (got.method, got.options, got.plane_z) == (want.method, want.options, want.plane_z)
    assert got.images.keys() == want.images.keys()
    for p, q in zip(got.pairs, want.pairs, strict=True):
        assert (p.id, p.image1, p.image2) == (q.id, q.image1, q.image2)
        np.testing.assert_array_equal(p.matches, q.matches)
    # the matches are a view of the body, in the dtype it sent
    assert got.pairs.matches.base is not None and not got.pairs.matches.flags.owndata


@pytest.mark.parametrize("first", [True, False], ids=["pairs-first", "pairs-last"])
def test_the_pairs_may_lie_anywhere_in_the_body(first: bool) -> None:
    doc = msgpack.unpackb(_bodies(_doc(3))[0])
    pairs = doc.pop("pairs")
    body = msgpack.packb({"pairs": pairs, **doc} if first else {**doc, "pairs": pairs})
    assert pairs_are_columns(body)
    flight = parse_batch_body(body, 100, MSGPACK)
    assert [p.id for p in flight.pairs] == ["p0", "p1", "p2"]


def test_rows_are_parsed_as_rows_in_either_encoding() -> None:
    doc = _doc(3)
    rows = _bodies(doc)[1]
    assert not pairs_are_columns(rows)
    assert isinstance(parse_batch_body(rows, 100, MSGPACK).pairs, list)
    text = orjson.dumps(doc, option=orjson.OPT_SERIALIZE_NUMPY)
    assert isinstance(parse_batch_body(text, 100, JSON).pairs, list)
    for odd in (b"", b"\x00", b"\x81\xa5pairs", msgpack.packb([1, 2]), msgpack.packb({"a": 1})):
        assert not pairs_are_columns(odd)


def _changed(change: Any) -> bytes:
    doc = msgpack.unpackb(_bodies(_doc(3))[0])
    change(doc)
    return msgpack.packb(doc)


def test_what_is_wrong_is_named() -> None:
    def bad_image(doc: dict[str, Any]) -> None:
        doc["pairs"]["image2"][1] = "nowhere"

    with pytest.raises(InputError, match=r"pairs\[1\]\.image2: no image 'nowhere'"):
        parse_batch_body(_changed(bad_image), 100, MSGPACK)

    def bad_count(doc: dict[str, Any]) -> None:
        doc["pairs"]["counts"]["data"] = np.asarray([1, 1, 1], "<i8").tobytes()

    with pytest.raises(InputError, match=r"pairs\.matches: .* rows; the counts add up to 3"):
        parse_batch_body(_changed(bad_count), 100, MSGPACK)
    with pytest.raises(InputError, match=r"pairs: 3 pairs; at most 2 per batch"):
        parse_batch_body(_bodies(_doc(3))[0], 2, MSGPACK)

    def bad_method(doc: dict[str, Any]) -> None:
        doc["method"] = "nope"

    with pytest.raises(ValidationError, match="method"):
        parse_batch_body(_changed(bad_method), 100, MSGPACK)


def test_a_body_cut_short_or_nested_too_deep_is_refused_as_the_body() -> None:
    columns = _bodies(_doc(2))[0]
    with pytest.raises(InputError, match="body: not one MessagePack object"):
        parse_batch_body(columns + b"\x00", 100, MSGPACK)
    deep: Any = 1
    for _ in range(MAX_DEPTH + 5):
        deep = {"x": deep}
    body = msgpack.packb({"pairs": {"image1": ["a"]}, "extra": deep})
    with pytest.raises(InputError, match="nested more than"):
        parse_batch_body(body, 100, MSGPACK)


def test_a_selections_helpers_agree_with_its_pairs() -> None:
    flight = parse_batch_body(_bodies(_doc(5))[0], 100, MSGPACK)
    pairs = flight.pairs
    assert isinstance(pairs, PairColumns)
    for part in (pairs, pairs.take([3, 0, 4])):
        one_by_one = list(part)
        assert part.counts().tolist() == [len(p.matches) for p in one_by_one]
        assert part.pair_ids() == [p.id for p in one_by_one]
        assert part.image_names() == {p.image1 for p in one_by_one} | {p.image2 for p in one_by_one}
        sent = part.as_sent()
        assert [p.id for p in sent] == [p.id for p in one_by_one]
        for p, q in zip(sent, one_by_one, strict=True):
            assert p.matches.dtype == pairs.matches.dtype and q.matches.dtype == np.int64
            np.testing.assert_array_equal(p.matches, q.matches)
    joined = PairColumns.joined([pairs.take(range(0, 2)), pairs.take(range(2, 5))])
    assert joined is not None and [p.id for p in joined] == [p.id for p in pairs]
    other = parse_batch_body(_bodies(_doc(5))[0], 100, MSGPACK).pairs
    assert PairColumns.joined([pairs.take([0]), other]) is None
    assert PairColumns.joined([list(pairs)]) is None
