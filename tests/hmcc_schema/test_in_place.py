"""MessagePack read in place: what :func:`walk` gives is what ``msgpack.unpackb`` gives, but
each buffer's data in maps a view of the bytes; :func:`entry` peeks."""

from __future__ import annotations

import mmap
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest

from hmcc import InputError
from hmcc_schema.in_place import entry, walk
from hmcc_schema.parse import MAX_DEPTH


def _buffer(a: np.ndarray) -> dict[str, Any]:
    return {"dtype": a.dtype.str, "shape": list(a.shape), "data": a.tobytes()}


def _plain(doc: Any) -> Any:
    """``doc`` with its views made bytes (what ``unpackb`` gives)."""
    if isinstance(doc, dict):
        return {k: _plain(v) for k, v in doc.items()}
    if isinstance(doc, list):
        return [_plain(v) for v in doc]
    return bytes(doc) if isinstance(doc, memoryview) else doc


BODY = {
    "images": {"a": {"keypoints": _buffer(np.arange(8, dtype="<f4").reshape(4, 2))}},
    "pairs": {
        "image1": ["a", "a"],
        "image2": ["a", "a"],
        "counts": _buffer(np.array([2, 1], "<i8")),
        "matches": _buffer(np.array([[0, 1], [2, 3], [1, 0]], "<i4")),
    },
    "rows": [{"matches": _buffer(np.array([[1, 0]], "<i4"))}],
    "names": ["x", "y", "z"],
    "params": {"data": 3, "nested": [[1, 2], []]},
}


def _views(doc: Any) -> list[memoryview]:
    if isinstance(doc, dict):
        return [v for value in doc.values() for v in _views(value)]
    if isinstance(doc, list):
        return [v for value in doc for v in _views(value)]
    return [doc] if isinstance(doc, memoryview) else []


def test_walk_gives_what_unpackb_gives_with_every_buffer_a_view(tmp_path: Path) -> None:
    data = msgpack.packb(BODY)
    doc = walk(data)
    assert _plain(doc) == msgpack.unpackb(data)
    views = _views(doc)
    assert len(views) == 3  # the keypoints, the counts and the matches (arrays: unpacked whole)
    for view in views:  # each where its bytes lie in the data
        assert view.obj is not None and bytes(view) in data
    path = tmp_path / "body.msgpack"
    path.write_bytes(data)
    with open(path, "rb") as f:
        mapped = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
    doc = walk(mapped)
    assert _plain(doc) == msgpack.unpackb(data) and len(_views(doc)) == 3


def test_walk_refuses_what_does_not_unpack_whole() -> None:
    data = msgpack.packb(BODY)
    assert walk(data[:-3]) is None  # cut short
    assert walk(data + b"\x01") is None  # more after it
    assert walk(b"") is None


def test_walk_refuses_nesting_past_the_limit() -> None:
    deep: Any = {}
    for _ in range(MAX_DEPTH + 1):
        deep = {"k": deep}
    with pytest.raises(InputError, match="nested more than"):
        walk(msgpack.packb(deep))
    allowed = deep["k"]["k"]  # MAX_DEPTH maps, one in another
    assert walk(msgpack.packb(allowed)) == allowed


def test_entry_finds_a_top_level_key_without_reading_the_rest() -> None:
    data = msgpack.packb(BODY)
    reader = entry(data, "pairs")
    assert reader is not None and reader.unpacker.read_map_header() == 4
    assert entry(data, "nowhere") is None
    assert entry(msgpack.packb([1, 2]), "pairs") is None
    assert entry(b"", "pairs") is None
    # what follows the key is not read: a broken tail does not matter
    assert entry(msgpack.packb({"pairs": 1}) + b"\xc1\xc1", "pairs") is not None
