"""hmcc_client.bodies: a flight's batch bodies stay under the size they are given, hold every
pair once in order, and are what the server's parser reads (the same arrays from MessagePack
buffers, pairs as rows or as columns, as from JSON)."""

from __future__ import annotations

from typing import Any

import msgpack
import numpy as np
import pytest
from pydantic import ValidationError

from hmcc_client import bodies
from hmcc_client.bodies import JSON, MSGPACK, flight_bodies
from hmcc_schema.columns import PairColumns, parse_batch_body
from tests.support.flights import small_flight


def _flight(dtype: type) -> dict[str, Any]:
    flight = small_flight(12, n_inliers=200)
    flight.pop("truth")
    for image in flight["images"].values():
        image["keypoints"] = np.asarray(image["keypoints"], dtype=dtype)
    return flight


@pytest.mark.parametrize("binary", [True, False], ids=["msgpack", "json"])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_bodies_stay_under_the_limit_and_keep_every_pair_in_order(
    binary: bool, dtype: type
) -> None:
    flight = _flight(dtype)
    max_bytes = 60_000
    bodies = list(
        flight_bodies(
            flight["images"],
            flight["pairs"],
            max_pairs=5,
            max_bytes=max_bytes,
            binary=binary,
            extra={"plane": flight["plane"]},
        )
    )
    assert len(bodies) > 12 / 5  # split by size, not only by count
    assert [i for b in bodies for i in b.indices] == list(range(12))
    assert all(len(b.content) <= max_bytes for b in bodies), [len(b.content) for b in bodies]
    assert {b.media_type for b in bodies} == {MSGPACK if binary else JSON}


@pytest.mark.parametrize("columns", [True, False], ids=["columns", "rows"])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_the_server_reads_the_same_arrays_from_msgpack_and_json(dtype: type, columns: bool) -> None:
    flight = _flight(dtype)
    parsed = [
        parse_batch_body(body.content, 100, body.media_type)
        for binary in (True, False)
        for body in flight_bodies(
            flight["images"],
            flight["pairs"],
            max_pairs=100,
            max_bytes=1 << 30,
            binary=binary,
            columns=columns,
            extra={"plane": flight["plane"]},
        )
    ]
    packed, text = parsed
    assert isinstance(packed.pairs, PairColumns) == columns
    assert (
        [p.id for p in packed.pairs] == [p.id for p in text.pairs] == [f"p{k}" for k in range(12)]
    )
    for a, b in zip(packed.pairs, text.pairs, strict=True):
        np.testing.assert_array_equal(a.matches, b.matches)
    for name, image in packed.images.items():
        assert image.keypoints is not None
        np.testing.assert_array_equal(image.keypoints, text.images[name].keypoints)
        np.testing.assert_array_equal(image.keypoints, flight["images"][name]["keypoints"])


def test_a_binary_body_is_packed_in_pieces_of_about_the_piece_size(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(bodies, "BODY_PIECE_BYTES", 4096)
    flight = _flight(np.float32)
    extra = {"plane": flight["plane"], "params": {"result": "inliers"}}
    (body,) = flight_bodies(
        flight["images"], flight["pairs"], max_pairs=100, max_bytes=1 << 30, extra=extra
    )
    # a piece ends with the value that takes it past the size: an image with its keypoints
    largest_value = max(np.asarray(v["keypoints"]).nbytes for v in flight["images"].values())
    assert len(body.pieces) > 3
    assert all(4096 <= len(p) < 4096 + largest_value + 1024 for p in body.pieces[:-1])
    parsed = parse_batch_body(body.content, 100, MSGPACK)
    assert [p.id for p in parsed.pairs] == [f"p{k}" for k in range(12)]


@pytest.mark.parametrize("piece", [1, 7, 1 << 20])
def test_the_pieces_join_to_what_msgpack_packs_the_body_as(
    monkeypatch: pytest.MonkeyPatch, piece: int
) -> None:
    monkeypatch.setattr(bodies, "BODY_PIECE_BYTES", piece)
    doc = {
        "images": {"a": {"keypoints": {"dtype": "<f4", "shape": [2, 2], "data": bytes(16)}}},
        "columns": {  # a buffer larger than a piece, sent in pieces of its own
            "image1": ["a"],
            "matches": {"dtype": "<u2", "shape": [300, 2], "data": memoryview(bytes(1200))},
        },
        "pairs": [{"image1": "a", "image2": "a", "matches": [[0, 1]] * k} for k in range(40)],
        "method": "hmcc-plus",
        "params": {"result": "inliers"},
        "empty": [],
    }
    pieces = bodies._msgpack_pieces(doc)
    assert b"".join(pieces) == msgpack.packb(doc)
    assert len(pieces) > 1 if piece < 1 << 20 else len(pieces) == 1


@pytest.mark.parametrize("binary", [True, False])
def test_descriptors_and_pairs_to_match_reach_the_server_as_given(binary: bool) -> None:
    """Images with uint8 (as lists) and float32 descriptors, a pair that asks for matching
    beside one with matches: the server reads the same arrays, uint8 as uint8."""
    flight = _flight(np.float64)
    rng = np.random.default_rng(0)
    images = dict(flight["images"])
    names = sorted(images)[:2]
    n0, n1 = (len(images[n]["keypoints"]) for n in names)
    images[names[0]] = {**images[names[0]], "descriptors": rng.integers(0, 256, (n0, 128)).tolist()}
    images[names[1]] = {
        **images[names[1]],
        "descriptors": rng.integers(0, 256, (n1, 128)).astype(np.float32),
    }
    pairs = [{"id": "m", "image1": names[0], "image2": names[1], "match": True}]
    pairs += list(flight["pairs"][:2])
    (body,) = flight_bodies(
        images,
        pairs,
        max_pairs=100,
        max_bytes=1 << 30,
        binary=binary,
        extra={"plane": {"ground_z": 0.0}, "matching": {"max_ratio": 0.75}},
    )
    parsed = parse_batch_body(body.content, 100, body.media_type)
    assert [p.match for p in parsed.pairs] == [True, False, False]
    assert parsed.match_options.max_ratio == 0.75
    for name in names:
        got = parsed.images[name].descriptors
        assert got is not None and got.dtype == np.uint8
        np.testing.assert_array_equal(got, np.asarray(images[name]["descriptors"]))


@pytest.mark.parametrize(
    ("largest", "dtype"), [(65_535, "<u2"), (65_536, "<i4"), (2**31, "<i8"), (-1, "<i4")]
)
def test_matches_go_in_the_narrowest_buffer_that_holds_them(largest: int, dtype: str) -> None:
    """uint16 while every index is below 65 536 (half the bytes of int32); a negative index
    is sent as it is, for the server to refuse by name."""
    import msgpack

    images = {"a": {"camera": {}, "keypoints": np.zeros((3, 2))}}
    matches = np.array([[0, 1], [2, largest]], dtype=np.int64)
    pairs = [{"image1": "a", "image2": "a", "matches": matches}]
    (body,) = flight_bodies(images, pairs, max_pairs=10, max_bytes=1 << 20)
    sent = msgpack.unpackb(body.content)["pairs"]["matches"]  # pairs as columns
    assert sent["dtype"] == dtype
    np.testing.assert_array_equal(
        np.frombuffer(sent["data"], dtype=dtype).reshape(sent["shape"]), matches
    )


def test_a_batch_has_its_pairs_as_columns_only_when_every_pair_is_plain() -> None:
    """Columns hold a pair's id, images and matches: a batch with a pair that asks for
    matching, has keys of its own or no matches goes as rows (the server then names the pair);
    the columns' matches take the widest dtype of the batch's."""
    images = {"a": {"camera": {}, "keypoints": np.zeros((70_000, 2))}}
    small = np.array([[0, 1], [2, 3]])
    pairs: list[dict[str, Any]] = [
        {"image1": "a", "image2": "a", "matches": small},
        {"id": "wide", "image1": "a", "image2": "a", "matches": small + 65_536},
    ]

    def sent(*more: dict[str, Any]) -> Any:
        (body,) = flight_bodies(images, pairs + list(more), max_pairs=10, max_bytes=1 << 30)
        return msgpack.unpackb(body.content)["pairs"]

    columns = sent()
    assert columns["image1"] == columns["image2"] == ["a", "a"]
    assert columns["id"] == [None, "wide"]
    assert np.frombuffer(columns["counts"]["data"], columns["counts"]["dtype"]).tolist() == [2, 2]
    assert columns["matches"]["dtype"] == "<i4" and columns["matches"]["shape"] == [4, 2]
    for odd in (
        {"image1": "a", "image2": "a", "match": True},
        {"image1": "a", "image2": "a", "matches": small, "note": 1},
        {"image1": "a", "image2": "a", "matches": np.zeros((0, 2), dtype=np.int64)},
        {"image1": "a", "image2": "a", "matches": small, "keypoints1": np.zeros((4, 2))},
    ):
        assert isinstance(sent(odd), list), odd
    # a pair without matches is sent (as a row) for the server to refuse by name
    empty = {"image1": "a", "image2": "a", "matches": np.zeros((0, 2), dtype=np.int64)}
    (body,) = flight_bodies(images, [*pairs, empty], max_pairs=10, max_bytes=1 << 30)
    with pytest.raises(ValidationError, match=r"pairs\.2\.matches"):
        parse_batch_body(body.content, 10, body.media_type)
