"""The binary flight file: arrays round-trip exactly, JSON and binary give the same flight."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import orjson

from hmcc_schema.flight_file import (
    encode_flight,
    flight_media_type,
    read_flight_file,
    write_flight_file,
)
from hmcc_schema.parse import JSON, MSGPACK
from tests.support.flights import small_flight


def _files(tmp_path: Path, n: int) -> tuple[Path, Path]:
    flight = small_flight(n)
    flight.pop("truth")
    as_json = tmp_path / "flight.json"
    as_json.write_text(json.dumps(flight, default=lambda a: np.asarray(a).tolist()))
    binary = tmp_path / "flight.msgpack"
    write_flight_file(binary, flight.pop("images"), flight.pop("pairs"), **flight)
    return as_json, binary


def test_json_and_binary_files_give_the_same_flight_and_results(tmp_path: Path) -> None:
    as_json, binary = _files(tmp_path, 3)
    assert flight_media_type(as_json.read_bytes()) == JSON
    assert flight_media_type(binary.read_bytes()) == MSGPACK
    a, b = read_flight_file(as_json), read_flight_file(binary)
    assert a.images.keys() == b.images.keys() and a.method == b.method
    assert (a.plane_z, a.ground_z, a.options) == (b.plane_z, b.ground_z, b.options)
    for name, image in a.images.items():
        other = b.images[name]
        assert image.camera == other.camera
        np.testing.assert_array_equal(image.pose.position, other.pose.position)
        assert image.keypoints is not None and other.keypoints is not None
        np.testing.assert_array_equal(image.keypoints, other.keypoints)
    for i, (p, q) in enumerate(zip(a.pairs, b.pairs, strict=True)):
        assert (p.id, p.image1, p.image2) == (q.id, q.image1, q.image2)
        np.testing.assert_array_equal(p.matches, q.matches)
        np.testing.assert_array_equal(a.verify(i).inliers, b.verify(i).inliers)


def test_arrays_keep_their_values_and_float32_keypoints_stay_float32() -> None:
    import msgpack

    rng = np.random.default_rng(0)
    kp32 = (rng.random((5, 2)) * 100).astype(np.float32)
    kp64 = rng.random((6, 2)) * 100
    matches = np.array([[0, 1], [4, 5]], dtype=np.int64)
    body = msgpack.unpackb(
        encode_flight(
            {"a": {"keypoints": kp32}, "b": {"keypoints": kp64}},
            [{"image1": "a", "image2": "b", "matches": matches}],
            method="hmcc",
            plane=None,
        )
    )
    assert "plane" not in body and body["method"] == "hmcc"
    a, b = body["images"]["a"]["keypoints"], body["images"]["b"]["keypoints"]
    assert a["dtype"] == "<f4" and b["dtype"] == "<f8" and a["shape"] == [5, 2]
    np.testing.assert_array_equal(np.frombuffer(a["data"], "<f4").reshape(5, 2), kp32)
    np.testing.assert_array_equal(np.frombuffer(b["data"], "<f8").reshape(6, 2), kp64)
    m = body["pairs"][0]["matches"]
    assert m["dtype"] == "<i4"
    np.testing.assert_array_equal(np.frombuffer(m["data"], "<i4").reshape(2, 2), matches)


def test_a_binary_file_of_pairs_to_match_carries_uint8_descriptors(tmp_path: Path) -> None:
    """Images with descriptors and a pair that asks for matching: the binary file holds the
    descriptors as a byte a value and gives the same matches as the JSON file."""
    from tests.support.matching import json_ready, matching_batch

    body, _ = matching_batch(0, n_inliers=60)
    json_file, binary_file = tmp_path / "f.json", tmp_path / "f.msgpack"
    json_file.write_bytes(orjson.dumps(json_ready(body)))
    extra = {k: v for k, v in body.items() if k not in ("images", "pairs")}
    size = write_flight_file(binary_file, body["images"], body["pairs"], **extra)
    arrays = sum(im["descriptors"].size + im["keypoints"].nbytes for im in body["images"].values())
    assert size < arrays + 4096  # a byte a descriptor value, the rest small
    results = []
    for path in (json_file, binary_file):
        flight = read_flight_file(path)
        assert flight.images["a"].descriptors is not None
        assert flight.images["a"].descriptors.dtype == np.uint8
        results.append(flight.verify(0).to_dict()["matches"])
    assert results[0] == results[1]
