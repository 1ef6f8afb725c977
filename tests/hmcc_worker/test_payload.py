"""The binary API -> worker payload: the same flight back, and foreign bytes refused."""

from __future__ import annotations

import dataclasses
import json
import struct
from typing import Any

import numpy as np
import pytest

from hmcc.flight import Flight
from hmcc.simulate import SimulationOptions, simulate_pair
from hmcc_schema import parse_batch, parse_pair
from hmcc_worker.payload import (
    decode_flight,
    decode_image,
    encode_flight,
    encode_image,
    image_names,
)


def _pair(seed: int = 0) -> dict[str, Any]:
    pair = simulate_pair(SimulationOptions(n_inliers=80, outlier_ratio=0.4), seed)
    pair.pop("ground_truth")
    return pair


def _same(a: Flight, b: Flight) -> None:
    assert (a.method, a.options, a.plane_z, a.ground_z) == (
        b.method,
        b.options,
        b.plane_z,
        b.ground_z,
    )
    assert [(p.id, p.image1, p.image2) for p in a.pairs] == [
        (p.id, p.image1, p.image2) for p in b.pairs
    ]
    for i in range(len(a.pairs)):
        x, y = a.pair_data(i), b.pair_data(i)
        for name in ("keypoints1", "keypoints2", "matches"):
            np.testing.assert_array_equal(getattr(x, name), getattr(y, name))
        np.testing.assert_array_equal(x.pose1.R_world_to_cam, y.pose1.R_world_to_cam)
        np.testing.assert_array_equal(x.pose2.center, y.pose2.center)
        assert x.camera1 == y.camera1 and x.camera2 == y.camera2


def test_a_pair_comes_back_the_same_and_verifies_the_same() -> None:
    pair = _pair()
    pair["params"] = {"seed": 5, "plus": {"hypotheses": 40}}
    pair["image1"]["camera"]["distortion"] = [-0.01, 0.001, 0.0, 0.0]
    pair["image2"]["pose"]["mounting"] = {"pitch": 2.0, "lever_arm": [0.1, 0.0, 0.2]}
    flight = parse_pair(pair)
    back = decode_flight(encode_flight(flight))
    _same(flight, back)
    assert back.verify(0).inliers.tolist() == flight.verify(0).inliers.tolist()


def test_a_chunk_names_its_images_stored_once() -> None:
    pairs = [_pair(seed) for seed in range(3)]
    batch = parse_batch(
        json.dumps(
            {
                "images": {
                    "a": {**pairs[0]["image1"], "keypoints": pairs[0]["keypoints1"]},
                    "b": {**pairs[0]["image2"], "keypoints": pairs[0]["keypoints2"]},
                    "c": pairs[1]["image2"],
                },
                "plane": pairs[0]["plane"],
                "pairs": [
                    {"id": "p0", "image1": "a", "image2": "b", "matches": pairs[0]["matches"]},
                    {
                        "id": "p1",
                        "image1": "a",
                        "image2": "c",
                        "keypoints2": pairs[1]["keypoints2"],
                        "matches": [
                            [m[0] % len(pairs[0]["keypoints1"]), m[1]] for m in pairs[1]["matches"]
                        ],
                    },
                ],
            }
        ),
        100,
    )
    chunk = batch.subset([1])
    blob = encode_flight(chunk, images=False)
    assert image_names(blob) == ["a", "c"]
    with pytest.raises(ValueError, match="images missing"):
        decode_flight(blob, {})
    images = {name: decode_image(encode_image(im)) for name, im in batch.images.items()}
    _same(chunk, decode_flight(blob, images))
    assert len(blob) < len(encode_flight(chunk))  # the images' keypoints travel apart


def _tampered(flight: Flight, array: int, value: float) -> bytes:
    """The payload of ``flight`` with the first number of array ``array`` overwritten."""
    blob = bytearray(encode_flight(flight))
    (size,) = struct.unpack_from("<I", blob, 8)
    offset = 12 + size
    specs = json.loads(blob[12:offset])["arrays"]
    for dtype, shape in specs[:array]:
        offset += int(np.prod(shape)) * np.dtype(dtype).itemsize
    dtype = np.dtype(specs[array][0])
    struct.pack_into(
        "<i" if dtype.kind == "i" else "<d",
        blob,
        offset,
        int(value) if dtype.kind == "i" else value,
    )
    return bytes(blob)


@pytest.mark.parametrize(
    ("blob", "message"),
    [
        (lambda f: b"not ours", "not an hmcc payload"),
        (lambda f: encode_flight(f)[:-8], "do not match"),
        (lambda f: _tampered(f, 1, float("nan")), "finite"),  # keypoints1
        (lambda f: _tampered(f, 0, 10**9), "out of range"),  # matches
        (lambda f: _tampered(f, 0, -1), "out of range"),
        (lambda f: encode_flight(f).replace(b'"hmcc-plus"', b'"hmcc-mega"'), "unknown method"),
    ],
)
def test_foreign_or_damaged_bytes_are_refused(blob: Any, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        decode_flight(blob(parse_pair(_pair())))


def test_descriptors_travel_with_their_images_once_and_pairs_ask_for_matching() -> None:
    """A batch's images carry their descriptors (dtype kept) in the images' own blobs; a chunk
    of pairs that ask for matching names the images and holds no descriptors; decoded, the
    pairs ask for matching, with the batch's matcher options, and match the same."""
    from tests.support.matching import matching_batch

    body, _ = matching_batch(0, n_inliers=60)
    body["matching"] = {"max_ratio": 0.7}
    body["pairs"].append({"id": "again", "image1": "b", "image2": "a", "match": True})
    flight = parse_batch(body, 10)
    blobs = {name: encode_image(image) for name, image in flight.images.items()}
    images = {name: decode_image(blob) for name, blob in blobs.items()}
    for name, image in images.items():
        original = flight.images[name].descriptors
        assert image.descriptors is not None and original is not None
        assert image.descriptors.dtype == np.uint8
        np.testing.assert_array_equal(image.descriptors, original)
        assert len(blobs[name]) > original.nbytes
    chunk = encode_flight(flight, images=False)
    smallest = min(
        im.descriptors.nbytes for im in flight.images.values() if im.descriptors is not None
    )
    assert len(chunk) < min(4096, smallest)  # names and options only: no arrays of the images
    back = decode_flight(chunk, images)
    assert [p.match for p in back.pairs] == [True, True]
    assert back.match_options.max_ratio == 0.7
    assert back.verify(0).to_dict()["matches"] == flight.verify(0).to_dict()["matches"]


def test_a_pair_to_match_without_descriptors_is_refused() -> None:
    from tests.support.matching import matching_batch

    body, _ = matching_batch(0, n_inliers=60)
    flight = parse_batch(body, 10)
    bare = {n: dataclasses.replace(im, descriptors=None) for n, im in flight.images.items()}
    with pytest.raises(ValueError, match="descriptors"):
        decode_flight(encode_flight(flight, images=False), bare)


def test_an_image_without_a_pose_comes_back_without_one() -> None:
    from tests.support.matching import matching_batch

    body, _ = matching_batch(0, n_inliers=60)
    del body["images"]["b"]["pose"]
    body["method"] = "ransac"
    flight = parse_batch(body, 10)
    image = decode_image(encode_image(flight.images["b"]))
    assert image.pose is None
    back = decode_flight(encode_flight(flight))
    assert back.images["b"].pose is None and back.images["a"].pose is not None
    assert back.verify(0).to_dict()["matches"] == flight.verify(0).to_dict()["matches"]


def test_pairs_keep_their_own_rows_of_the_one_matches_array() -> None:
    """A chunk's matches travel as one array; each pair reads back its own rows, and rows that
    do not add up to the array are refused."""
    flight = parse_pair(_pair())
    pair = flight.pairs[0]
    pairs = [dataclasses.replace(pair, matches=pair.matches[: 5 + k], id=f"p{k}") for k in range(4)]
    several = dataclasses.replace(flight, pairs=pairs)
    blob = encode_flight(several)
    back = decode_flight(blob)
    for a, b in zip(several.pairs, back.pairs, strict=True):
        np.testing.assert_array_equal(a.matches, b.matches)
    lying = blob.replace(b'"rows":5,', b'"rows":6,', 1)
    with pytest.raises(ValueError, match="do not add up"):
        decode_flight(lying)


def _with_matches_as(flight: Flight, dtypes: list[type]) -> Flight:
    pairs = [
        dataclasses.replace(p, matches=p.matches.astype(d))
        for p, d in zip(flight.pairs, dtypes, strict=True)
    ]
    return dataclasses.replace(flight, pairs=pairs)


def test_matches_sent_as_uint16_travel_as_uint16_and_come_back_as_int64() -> None:
    """A chunk whose pairs' matches all came as uint16 (the client's form below 65 536
    keypoints) carries them as uint16: half the bytes of int32; any other dtype among them
    makes it int32. Either way the worker reads the same int64 matches."""
    pair = parse_pair(_pair())
    flight = _with_matches_as(pair, [np.uint16])
    small = encode_flight(flight)
    wide = encode_flight(_with_matches_as(pair, [np.int64]))
    rows = len(flight.pairs[0].matches)
    assert len(wide) - len(small) == rows * 2 * 2
    for blob in (small, wide):
        back = decode_flight(blob)
        assert back.pairs[0].matches.dtype == np.int64
        _same(flight, back)
    pairs = [
        dataclasses.replace(flight.pairs[0], id="a"),
        dataclasses.replace(flight.pairs[0], id="b"),
    ]
    mixed = _with_matches_as(dataclasses.replace(flight, pairs=pairs), [np.uint16, np.int32])
    (size,) = struct.unpack_from("<I", encode_flight(mixed), 8)
    specs = json.loads(encode_flight(mixed)[12 : 12 + size])["arrays"]
    assert specs[0][0] == "<i4"
    _same(mixed, decode_flight(encode_flight(mixed)))


def test_uint16_matches_out_of_range_are_refused() -> None:
    flight = _with_matches_as(parse_pair(_pair()), [np.uint16])
    blob = bytearray(encode_flight(flight))
    (size,) = struct.unpack_from("<I", blob, 8)
    struct.pack_into("<H", blob, 12 + size, 65535)  # the first match's first index
    with pytest.raises(ValueError, match="out of range"):
        decode_flight(bytes(blob))
