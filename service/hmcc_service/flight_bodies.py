"""A flight as request bodies: its pairs split into batches under the service's limits, each
batch carrying the images its pairs name once, with their keypoints.

Bodies are MessagePack with raw little-endian array buffers by default (8 bytes a match, 16 a
keypoint, nothing to parse on the server; see ``hmcc_schema.parse``) or JSON. Arrays may be
given as lists or ndarrays; keypoints keep float32 when given as float32.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np
import orjson

from hmcc_schema.flight_file import wire_array, wire_buffer
from hmcc_schema.parse import JSON, MSGPACK

__all__ = ["BatchBody", "flight_bodies"]

#: Bytes a body aims below, at most (the server's limit may be lower). Each body carries the
#: keypoints of every image its pairs name, so fewer, larger bodies send an image's keypoints
#: fewer times: on the 750-image benchmark flight 16 MiB bodies sent 282 MiB in 21 bodies, 48
#: MiB ones 173 MiB in 5 (the matches alone are 101 MiB). Three such bodies in flight stay far
#: below the API's memory bound, and the server splits each into small jobs at once.
TARGET_BODY_BYTES = 48 * 1024 * 1024
#: JSON writes a number in about this many bytes more than its binary form needs.
_JSON_EXPANSION = 1.6


@dataclass(frozen=True)
class BatchBody:
    """One request body: its bytes and media type, and the flight's pair indices and ids it
    holds, in order."""

    content: bytes
    media_type: str
    indices: list[int]
    ids: list[str | None]


_array = wire_array
_buffer = wire_buffer


def flight_bodies(
    images: Mapping[str, Mapping[str, Any]],
    pairs: Iterable[Mapping[str, Any]],
    *,
    max_pairs: int,
    max_bytes: int,
    binary: bool = True,
    extra: Mapping[str, Any] | None = None,
) -> Iterator[BatchBody]:
    """Batches of at most ``max_pairs`` pairs whose bodies stay under ``max_bytes`` (and
    :data:`TARGET_BODY_BYTES`), pairs in the given order. ``images``: id -> ``{camera, pose,
    keypoints}``; ``pairs``: ``{id?, image1, image2, matches}`` (each may also carry its own
    ``keypoints1``/``keypoints2``); ``extra``: ``method``, ``params``, ``plane`` for every
    batch. A single pair larger than the limit still gets a batch of its own (the server then
    says 413)."""
    budget = min(max_bytes, TARGET_BODY_BYTES) * 0.85
    arrays: dict[str, np.ndarray] = {}  # each image's keypoints, converted once
    batch: list[tuple[int, Mapping[str, Any], np.ndarray]] = []
    names: set[str] = set()
    size = 0.0
    scale = 1.0 if binary else _JSON_EXPANSION

    def cost(pair: Mapping[str, Any], matches: np.ndarray) -> float:
        """Bytes the pair adds to the batch: its arrays, and its images' not yet in it."""
        total = matches.nbytes + sum(
            _array(pair[k], "keypoints").nbytes for k in ("keypoints1", "keypoints2") if k in pair
        )
        for name in (pair["image1"], pair["image2"]):
            # an unknown image is the server's to refuse, naming the pair's field
            if name not in names and "keypoints" in images.get(name, {}):
                if name not in arrays:
                    arrays[name] = _array(images[name]["keypoints"], "keypoints")
                total += arrays[name].nbytes + 512
        return total * scale + 128

    for index, pair in enumerate(pairs):
        matches = _array(pair["matches"], "matches")
        added = cost(pair, matches)
        if batch and (len(batch) >= max_pairs or size + added > budget):
            yield _body(images, arrays, batch, binary, extra)
            batch, names, size = [], set(), 0.0
            added = cost(pair, matches)
        batch.append((index, pair, matches))
        names.update((pair["image1"], pair["image2"]))
        size += added
    if batch:
        yield _body(images, arrays, batch, binary, extra)


def _body(
    images: Mapping[str, Mapping[str, Any]],
    arrays: Mapping[str, np.ndarray],
    batch: list[tuple[int, Mapping[str, Any], np.ndarray]],
    binary: bool,
    extra: Mapping[str, Any] | None,
) -> BatchBody:
    names = sorted({n for _, p, _ in batch for n in (p["image1"], p["image2"]) if n in images})
    image_docs = {}
    for name in names:
        doc = {k: v for k, v in images[name].items() if k != "keypoints"}
        if name in arrays:
            doc["keypoints"] = _buffer(arrays[name]) if binary else arrays[name]
        image_docs[name] = doc
    pair_docs = []
    for _, pair, matches in batch:
        doc = {k: v for k, v in pair.items() if k not in ("matches", "keypoints1", "keypoints2")}
        doc["matches"] = _buffer(matches) if binary else matches
        for key in ("keypoints1", "keypoints2"):
            if key in pair:
                own = _array(pair[key], "keypoints")
                doc[key] = _buffer(own) if binary else own
        pair_docs.append(doc)
    body = {"images": image_docs, "pairs": pair_docs, **(extra or {})}
    if binary:
        content: bytes = msgpack.packb(body)
    else:
        content = orjson.dumps(body, option=orjson.OPT_SERIALIZE_NUMPY)
    return BatchBody(
        content,
        MSGPACK if binary else JSON,
        [i for i, _, _ in batch],
        [p.get("id") for _, p, _ in batch],
    )
