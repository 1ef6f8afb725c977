"""A flight in a file: the batch body (``images`` with their keypoints, ``pairs`` with their
matches, ``method``, ``params``, ``plane``) without its size limit, as JSON (the contract) or as
the body's MessagePack form with raw little-endian array buffers (``{"dtype", "shape",
"data"}``, see :mod:`hmcc_schema.parse`): one format for a request body and a flight file.

The binary file is read without parsing a number: on the 750-image benchmark flight (13.3 M
matches) it is 139 MB against 236 MB of JSON, and it parses into the core's
:class:`~hmcc.flight.Flight` in about 0.6 s of CPU where the JSON takes 4 s (simdjson; 15 s
through ``orjson.loads`` and lists).

:func:`write_flight_file` writes one from arrays (lists or ndarrays; keypoints keep float32 when
given as float32, matches are int32 when they fit); :func:`read_flight_file` reads either kind
(told apart by the first byte: a JSON object starts with ``{``, a MessagePack map never does).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import msgpack
import numpy as np

from hmcc.flight import Flight

from .parse import JSON, MSGPACK, parse_batch

__all__ = [
    "encode_flight",
    "flight_media_type",
    "read_flight_file",
    "wire_array",
    "wire_buffer",
    "write_flight_file",
]

_PAIR_ARRAYS = {"matches": "matches", "keypoints1": "keypoints", "keypoints2": "keypoints"}


def wire_array(value: Any, kind: str) -> np.ndarray:
    """``value`` as the dtype it travels in: matches (``kind`` "matches") ``<i4`` when they fit,
    else ``<i8``; keypoints ``<f4`` when given as float32, else ``<f8``; descriptors uint8
    when they are integers 0 to 255, else ``<f4``. The client encodes
    its batch bodies by the same rules (``hmcc_client.bodies``, which imports nothing of ours:
    a change to one is a change to both)."""
    if kind == "matches":
        a = np.asarray(value)
        if a.dtype.kind in "iu" and (a.size == 0 or int(a.max(initial=0)) < 2**31):
            return a.astype("<i4", copy=False)
        return np.asarray(value, dtype="<i8")
    a = np.asarray(value)
    if kind == "descriptors":
        if a.dtype == np.uint8:
            return a
        if a.dtype.kind in "iuf" and a.size and np.isfinite(a).all():
            if (a == np.round(a)).all() and a.min() >= 0 and a.max() <= 255:
                return a.astype(np.uint8)
        return a.astype("<f4")
    return a.astype("<f4" if a.dtype == np.float32 else "<f8", copy=False)


def wire_buffer(array: np.ndarray) -> dict[str, Any]:
    """An array as MessagePack carries it: its raw bytes, dtype and shape."""
    return {"dtype": array.dtype.str, "shape": list(array.shape), "data": array.tobytes()}


def encode_flight(
    images: Mapping[str, Mapping[str, Any]],
    pairs: Iterable[Mapping[str, Any]],
    **extra: Any,
) -> bytes:
    """A flight as MessagePack bytes with raw array buffers. ``images``: id -> ``{camera, pose,
    keypoints?, descriptors?}``; ``pairs``: ``{id?, image1, image2, matches, keypoints1?,
    keypoints2?}`` (or ``match: True`` instead of matches); ``extra``: ``method``, ``params``,
    ``plane``, ``matching`` (None values left out)."""
    image_docs = {}
    for name, image in images.items():
        doc = dict(image)
        for key in ("keypoints", "descriptors"):
            if doc.get(key) is not None:
                doc[key] = wire_buffer(wire_array(doc[key], key))
        image_docs[name] = doc
    pair_docs = []
    for pair in pairs:
        doc = dict(pair)
        for key, kind in _PAIR_ARRAYS.items():
            if doc.get(key) is not None:
                doc[key] = wire_buffer(wire_array(doc[key], kind))
        pair_docs.append(doc)
    body = {"images": image_docs, "pairs": pair_docs}
    body.update({k: v for k, v in extra.items() if v is not None})
    return bytes(msgpack.packb(body))


def write_flight_file(
    path: str | Path,
    images: Mapping[str, Mapping[str, Any]],
    pairs: Iterable[Mapping[str, Any]],
    **extra: Any,
) -> int:
    """Write a binary flight file (see :func:`encode_flight`); returns its size in bytes."""
    data = encode_flight(images, pairs, **extra)
    Path(path).write_bytes(data)
    return len(data)


def flight_media_type(raw: bytes) -> str:
    """:data:`~hmcc_schema.parse.JSON` when ``raw`` starts (after white space) with ``{``,
    else :data:`~hmcc_schema.parse.MSGPACK`."""
    return JSON if raw.lstrip()[:1] == b"{" else MSGPACK


def read_flight_file(path: str | Path, max_pairs: int = 10**9) -> Flight:
    """The flight in a JSON or binary flight file. Raises pydantic's ``ValidationError`` or
    :class:`hmcc.InputError` naming what is wrong (as for a batch body)."""
    raw = Path(path).read_bytes()
    return parse_batch(raw, max_pairs, flight_media_type(raw))
