"""Request bodies: a pair or a batch as JSON, and a flight as batch bodies, its pairs split
under the service's limits, each batch carrying the images its pairs name once, with their
keypoints.

Flight bodies are MessagePack with raw little-endian array buffers by default (4 bytes a
match while the indices stay below 65 536, 16 a keypoint, a byte per value of uint8
descriptors, nothing to parse on the server: the server's ``hmcc_schema.parse`` reads
``{"dtype", "shape", "data"}`` maps as arrays) or JSON. Arrays may be given as lists or
ndarrays; keypoints keep float32 when given as float32; matches are sent as uint16 when every
index is below 65 536 (else int32, else int64); descriptors are sent as uint8 when they are
integers 0 to 255 (SIFT's), else as float32. A pair that asks for matching (``"match": True``)
has no matches; its images carry ``descriptors``. Encoding needs numpy and msgpack only.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np

__all__ = [
    "JSON",
    "MSGPACK",
    "BODY_PIECE_BYTES",
    "BatchBody",
    "Pair",
    "batch_body",
    "flight_bodies",
    "pair_body",
    "pairs_body",
]

#: The media types of request bodies (the server's ``hmcc_schema.parse`` names the same).
JSON = "application/json"
MSGPACK = "application/vnd.hmcc+msgpack"

#: A pair: a JSON-ready mapping (the public pair format), or its JSON text already encoded.
Pair = Mapping[str, Any] | str | bytes

#: Bytes a body aims below, at most (the server's limit may be lower). Each body carries the
#: keypoints of every image its pairs name, so fewer, larger bodies send an image's keypoints
#: fewer times: on the 750-image benchmark flight 16 MiB bodies sent 282 MiB in 21 bodies, 48
#: MiB ones 173 MiB in 5 (the matches alone are 101 MiB). Three such bodies in flight stay far
#: below the API's memory bound, and the server splits each into small jobs at once.
TARGET_BODY_BYTES = 48 * 1024 * 1024
#: Characters JSON takes for one float of an array, at most about (a float64's shortest repr
#: has up to 17 significant digits, plus sign, point, exponent and separator; a float32 is
#: written as the float64 of its value, as long).
_JSON_FLOAT_CHARS = 24


#: About the bytes of one piece of a request body. A MessagePack body is packed a value at a
#: time into pieces of about this size (not into one buffer that grows, then copied) and sent
#: piece by piece: httpcore sends a body of one piece by sending what the socket takes and
#: slicing off the rest, a copy of the rest each time (a 40 MB body copied some 30 times).
BODY_PIECE_BYTES = 1 << 20


@dataclass(frozen=True)
class BatchBody:
    """One request body: its bytes in pieces (sent one after the other) and media type, and
    the flight's pair indices and ids it holds, in order."""

    pieces: tuple[bytes, ...]
    media_type: str
    indices: list[int]
    ids: list[str | None]

    @property
    def content(self) -> bytes:
        """The whole body (the pieces joined: a copy)."""
        return b"".join(self.pieces)


def pair_body(pair: Pair) -> bytes:
    """The JSON body of one pair (text and bytes are sent as they are)."""
    if isinstance(pair, bytes):
        return pair
    if isinstance(pair, str):
        return pair.encode()
    return _json(pair)


def batch_body(
    images: Mapping[str, Any],
    pairs: Iterable[Mapping[str, Any]],
    method: str | None = None,
    params: Mapping[str, Any] | None = None,
    plane: Mapping[str, Any] | None = None,
    matching: Mapping[str, Any] | None = None,
) -> bytes:
    """The JSON body of one batch, as given (no splitting, keypoints per pair or per image;
    ``matching``: the matcher's options for pairs that ask for matching)."""
    body: dict[str, Any] = {"images": dict(images), "pairs": list(pairs)}
    for key, value in (
        ("method", method),
        ("params", params),
        ("plane", plane),
        ("matching", matching),
    ):
        if value is not None:
            body[key] = value
    return _json(body)


def pairs_body(
    images: Mapping[str, Mapping[str, Any]],
    ground_z: float | None = None,
    flying_height: float | None = None,
    params: Mapping[str, Any] | None = None,
) -> bytes:
    """The JSON body of a pairs request: each image's ``camera`` and ``pose`` (anything else
    an image carries, its keypoints say, is left out), the ground and the options."""
    body: dict[str, Any] = {
        "images": {
            name: {k: v for k, v in image.items() if k in ("camera", "pose")}
            for name, image in images.items()
        }
    }
    for key, value in (("ground_z", ground_z), ("flying_height", flying_height)):
        if value is not None:
            body[key] = value
    if params is not None:
        body["params"] = params
    return _json(body)


def _jsonable(value: Any) -> Any:
    """ndarrays and numpy scalars for :func:`json.dumps` (anything else is a TypeError)."""
    if isinstance(value, np.ndarray | np.generic):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} is not JSON serializable")


def _json(body: Any) -> bytes:
    return json.dumps(body, default=_jsonable, separators=(",", ":")).encode()


def _array(value: Any, kind: str) -> np.ndarray:
    if kind == "descriptors":
        a = np.asarray(value)
        if a.dtype == np.uint8:
            return a
        if a.dtype.kind in "iuf" and a.size and np.isfinite(a).all():
            if (a == np.round(a)).all() and a.min() >= 0 and a.max() <= 255:
                return a.astype(np.uint8)
        return a.astype("<f4")
    if kind == "matches":
        a = np.asarray(value)
        if a.dtype.kind in "iu" and a.size:
            low, high = int(a.min()), int(a.max())
            if low >= 0 and high < 2**16:  # the indices of up to 65 536 keypoints
                return a.astype("<u2", copy=False)
            if high < 2**31:
                return a.astype("<i4", copy=False)
        elif a.dtype.kind in "iu":
            return a.astype("<i4", copy=False)
        return np.asarray(value, dtype="<i8")
    a = np.asarray(value)
    return a.astype("<f4" if a.dtype == np.float32 else "<f8", copy=False)


def _nbytes(array: np.ndarray) -> int:
    return array.nbytes


def _json_chars(array: np.ndarray) -> int:
    """Characters ``array`` takes in a JSON body, about and rather more than fewer: an (N, 2)
    array is ``[[a,b],...]``, three characters a row besides its two numbers."""
    if array.dtype.kind == "f":
        per_number = _JSON_FLOAT_CHARS
    else:
        per_number = len(str(int(np.abs(array).max(initial=0)))) + 2  # digits, sign, comma
    return array.size * per_number + 2 * len(array) + 2


def _buffer(array: np.ndarray) -> dict[str, Any]:
    """A raw array as MessagePack holds it (its bytes packed from the array, not copied first)."""
    data = np.ascontiguousarray(array)
    raw = memoryview(data).cast("B") if data.size else b""  # type: ignore[arg-type]
    return {"dtype": data.dtype.str, "shape": list(data.shape), "data": raw}


def flight_bodies(
    images: Mapping[str, Mapping[str, Any]],
    pairs: Iterable[Mapping[str, Any]],
    *,
    max_pairs: int,
    max_bytes: int,
    binary: bool = True,
    columns: bool = True,
    extra: Mapping[str, Any] | None = None,
) -> Iterator[BatchBody]:
    """Batches of at most ``max_pairs`` pairs whose bodies stay under ``max_bytes`` (and
    :data:`TARGET_BODY_BYTES`), pairs in the given order. ``images``: id -> ``{camera, pose,
    keypoints, descriptors?}``; ``pairs``: ``{id?, image1, image2, matches}`` (each may also
    carry its own ``keypoints1``/``keypoints2``), or ``{id?, image1, image2, match: True}``
    to have the images' descriptors matched; ``extra``: ``method``, ``params``, ``plane``,
    ``matching`` for every batch. A single pair larger than the limit still gets a batch of
    its own (the server then says 413). ``columns`` (MessagePack only): a batch whose every
    pair is ``{id?, image1, image2, matches}`` has its pairs as columns, one array each (the
    server reads them at once, not pair by pair)."""
    budget = min(max_bytes, TARGET_BODY_BYTES) * 0.85
    arrays: dict[str, np.ndarray] = {}  # each image's keypoints, converted once
    descriptors: dict[str, np.ndarray] = {}  # likewise their descriptors
    batch: list[tuple[int, Mapping[str, Any], np.ndarray | None]] = []
    names: set[str] = set()
    size = 0.0
    size_of = _nbytes if binary else _json_chars

    def cost(pair: Mapping[str, Any], matches: np.ndarray | None) -> float:
        """Bytes the pair adds to the batch: its arrays, and its images' not yet in it."""
        total = (0 if matches is None else size_of(matches)) + sum(
            size_of(_array(pair[k], "keypoints")) for k in ("keypoints1", "keypoints2") if k in pair
        )
        for name in (pair["image1"], pair["image2"]):
            # an unknown image is the server's to refuse, naming the pair's field
            if name not in names and "keypoints" in images.get(name, {}):
                if name not in arrays:
                    arrays[name] = _array(images[name]["keypoints"], "keypoints")
                    if "descriptors" in images[name]:
                        descriptors[name] = _array(images[name]["descriptors"], "descriptors")
                total += size_of(arrays[name]) + 512
                if name in descriptors:
                    total += size_of(descriptors[name])
        return total + 128

    for index, pair in enumerate(pairs):
        matches = None if pair.get("match") else _array(pair["matches"], "matches")
        added = cost(pair, matches)
        if batch and (len(batch) >= max_pairs or size + added > budget):
            yield _body(images, arrays, descriptors, batch, binary, columns, extra)
            batch, names, size = [], set(), 0.0
            added = cost(pair, matches)
        batch.append((index, pair, matches))
        names.update((pair["image1"], pair["image2"]))
        size += added
    if batch:
        yield _body(images, arrays, descriptors, batch, binary, columns, extra)


def _body(
    images: Mapping[str, Mapping[str, Any]],
    arrays: Mapping[str, np.ndarray],
    descriptors: Mapping[str, np.ndarray],
    batch: list[tuple[int, Mapping[str, Any], np.ndarray | None]],
    binary: bool,
    columns: bool,
    extra: Mapping[str, Any] | None,
) -> BatchBody:
    names = sorted({n for _, p, _ in batch for n in (p["image1"], p["image2"]) if n in images})
    image_docs = {}
    for name in names:
        doc = {k: v for k, v in images[name].items() if k not in ("keypoints", "descriptors")}
        if name in arrays:
            doc["keypoints"] = _buffer(arrays[name]) if binary else arrays[name]
        if name in descriptors:
            doc["descriptors"] = _buffer(descriptors[name]) if binary else descriptors[name]
        image_docs[name] = doc
    if binary and columns and all(_plain_pair(pair, m) for _, pair, m in batch):
        body = {"pairs": _pair_columns(batch), "images": image_docs, **(extra or {})}
        return BatchBody(
            _msgpack_pieces(body),
            MSGPACK,
            [i for i, _, _ in batch],
            [p.get("id") for _, p, _ in batch],
        )
    pair_docs = []
    for _, pair, matches in batch:
        doc = {k: v for k, v in pair.items() if k not in ("matches", "keypoints1", "keypoints2")}
        if matches is not None:
            doc["matches"] = _buffer(matches) if binary else matches
        for key in ("keypoints1", "keypoints2"):
            if key in pair:
                own = _array(pair[key], "keypoints")
                doc[key] = _buffer(own) if binary else own
        pair_docs.append(doc)
    body = {"images": image_docs, "pairs": pair_docs, **(extra or {})}
    return BatchBody(
        _msgpack_pieces(body) if binary else (_json(body),),
        MSGPACK if binary else JSON,
        [i for i, _, _ in batch],
        [p.get("id") for _, p, _ in batch],
    )


#: The keys of a pair that has columns.
_COLUMN_KEYS = frozenset({"id", "image1", "image2", "matches"})


def _plain_pair(pair: Mapping[str, Any], matches: np.ndarray | None) -> bool:
    """Whether ``pair`` has columns: its id, images and matches (``matches``: (M, 2), M > 0),
    nothing else. Any other pair is sent as a row, for the server to say what is wrong."""
    return (
        pair.keys() <= _COLUMN_KEYS
        and matches is not None
        and matches.ndim == 2
        and matches.shape[1] == 2
        and len(matches) > 0
    )


def _pair_columns(batch: list[tuple[int, Mapping[str, Any], np.ndarray | None]]) -> dict[str, Any]:
    """The pairs of ``batch`` as columns: ``image1``, ``image2``, ``id`` (when a pair has one),
    ``counts`` and every pair's ``matches`` one after another, in the widest dtype of theirs."""
    matches = [m for _, _, m in batch if m is not None]  # every one (:func:`_plain_pair`)
    dtype = np.result_type(*{m.dtype for m in matches})
    doc: dict[str, Any] = {
        "image1": [p["image1"] for _, p, _ in batch],
        "image2": [p["image2"] for _, p, _ in batch],
    }
    ids = [p.get("id") for _, p, _ in batch]
    if any(i is not None for i in ids):
        doc["id"] = ids
    doc["counts"] = _buffer(np.fromiter(map(len, matches), "<i4", len(matches)))
    doc["matches"] = _buffer(np.concatenate(matches, dtype=dtype))
    return doc


def _msgpack_pieces(doc: Mapping[str, Any]) -> tuple[bytes, ...]:
    """``msgpack.packb(doc)``, byte for byte, in pieces of about :data:`BODY_PIECE_BYTES`: the
    values of ``doc`` and, where a value is a map or a list, each of its entries packed one at
    a time; an entry that is a buffer larger than a piece (a batch's matches as a column) in
    pieces of its data."""
    packer = msgpack.Packer()
    pieces: list[bytes] = []
    parts: list[bytes] = []
    size = 0

    def put(packed: bytes) -> None:
        nonlocal size
        parts.append(packed)
        size += len(packed)
        if size >= BODY_PIECE_BYTES:
            pieces.append(b"".join(parts))
            parts.clear()
            size = 0

    def entry(value: Any) -> None:
        if not (isinstance(value, Mapping) and _is_large_buffer(value)):
            put(packer.pack(value))
            return
        put(packer.pack_map_header(len(value)))
        for k, v in value.items():
            put(packer.pack(k))
            if k != "data":
                put(packer.pack(v))
                continue
            data = memoryview(v).cast("B")
            put(_bin_header(len(data)))
            for start in range(0, len(data), BODY_PIECE_BYTES):
                put(bytes(data[start : start + BODY_PIECE_BYTES]))

    put(packer.pack_map_header(len(doc)))
    for key, value in doc.items():
        put(packer.pack(key))
        if isinstance(value, Mapping):
            put(packer.pack_map_header(len(value)))
            for k, v in value.items():
                put(packer.pack(k))
                entry(v)
        elif isinstance(value, list):
            put(packer.pack_array_header(len(value)))
            for v in value:
                put(packer.pack(v))
        else:
            put(packer.pack(value))
    if parts:
        pieces.append(b"".join(parts))
    return tuple(pieces)


def _is_large_buffer(value: Mapping[str, Any]) -> bool:
    data = value.get("data")
    return (
        value.keys() == {"dtype", "shape", "data"}
        and isinstance(data, bytes | memoryview)
        and memoryview(data).nbytes > BODY_PIECE_BYTES
    )


def _bin_header(n: int) -> bytes:
    """The head of MessagePack binary data of ``n`` bytes (bin 8, 16 or 32)."""
    if n < 1 << 8:
        return b"\xc4" + n.to_bytes(1, "big")
    if n < 1 << 16:
        return b"\xc5" + n.to_bytes(2, "big")
    return b"\xc6" + n.to_bytes(4, "big")
