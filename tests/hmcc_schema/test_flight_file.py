"""The binary flight file: arrays round-trip exactly, JSON and binary give the same flight."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import orjson

from hmcc_schema.flight_file import (
    MappedFlightFile,
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


def test_a_mapped_file_gives_the_flight_of_its_bytes_its_arrays_left_in_the_file(
    tmp_path: Path,
) -> None:
    _, binary = _files(tmp_path, 3)
    mapped = MappedFlightFile.open(binary)
    assert mapped is not None and mapped.pair_count() == 3
    flight, whole = mapped.flight(), read_flight_file(binary)
    assert flight is not None
    data = binary.read_bytes()
    for pair, parsed in zip(flight.pairs, whole.pairs, strict=True):
        at = mapped.offset(pair.matches)
        assert at is not None  # a view of the file, in the file's dtype: nothing copied
        assert data[at : at + pair.matches.nbytes] == pair.matches.tobytes()
        assert pair.matches.dtype == np.dtype("<i4") and parsed.matches.dtype == np.int64
        np.testing.assert_array_equal(pair.matches, parsed.matches)
        assert (pair.image1, pair.image2, pair.id) == (parsed.image1, parsed.image2, parsed.id)
    for name, image in flight.images.items():
        assert image.keypoints is not None and mapped.offset(image.keypoints) is not None
        np.testing.assert_array_equal(image.keypoints, whole.images[name].keypoints)
    assert mapped.offset(whole.pairs[0].matches) is None


def test_a_buffer_whose_data_is_not_its_last_value_is_read_as_a_copy(tmp_path: Path) -> None:
    """Only a buffer's data that ends its object is read in place: its bytes are then the
    object's last ones (a file written by another tool may order the keys otherwise)."""
    _, binary = _files(tmp_path, 3)
    doc = msgpack.unpackb(binary.read_bytes())
    matches = doc["pairs"][1]["matches"]
    doc["pairs"][1]["matches"] = {"data": matches["data"], **matches}  # data first
    binary.write_bytes(msgpack.packb(doc))
    mapped = MappedFlightFile.open(binary)
    assert mapped is not None
    flight, whole = mapped.flight(), read_flight_file(binary)
    assert flight is not None
    for k, (pair, parsed) in enumerate(zip(flight.pairs, whole.pairs, strict=True)):
        np.testing.assert_array_equal(pair.matches, parsed.matches)
        assert (mapped.offset(pair.matches) is None) == (k == 1)


def test_a_json_file_is_not_mapped(tmp_path: Path) -> None:
    as_json, _ = _files(tmp_path, 1)
    assert MappedFlightFile.open(as_json) is None


def test_a_mapped_file_that_is_not_plainly_valid_is_left_to_the_whole_parse(
    tmp_path: Path,
) -> None:
    """Truncated, an index out of range, a buffer of another dtype: no flight (the whole
    file's parse then says what is wrong, in its words)."""
    _, binary = _files(tmp_path, 2)
    data = binary.read_bytes()
    doc = msgpack.unpackb(data)
    bad = {
        "truncated": data[:-10],
        "trailing": data + b"\xc0",
        "index": _packed(doc, "matches", lambda m: m.__setitem__("data", _big_index(m))),
        "dtype": _packed(doc, "matches", lambda m: m.__setitem__("dtype", "<f4")),
    }
    for name, body in bad.items():
        path = tmp_path / f"{name}.msgpack"
        path.write_bytes(body)
        mapped = MappedFlightFile.open(path)
        assert mapped is not None and mapped.flight() is None, name


def _packed(doc: dict[str, Any], key: str, change: Callable[[dict[str, Any]], None]) -> bytes:
    """``doc`` packed again, ``change`` made to the ``key`` buffer of its second pair."""
    doc = msgpack.unpackb(msgpack.packb(doc))
    change(doc["pairs"][1][key])
    return bytes(msgpack.packb(doc))


def _big_index(buffer: dict[str, Any]) -> bytes:
    matches = np.frombuffer(buffer["data"], dtype=buffer["dtype"]).copy()
    matches[-1] = 10**6
    return matches.tobytes()
