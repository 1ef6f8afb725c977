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

:class:`MappedFlightFile` reads a binary file in place: the file mapped in memory, a walk
over its MessagePack (the document's, its images' and pairs' maps; each array unpacked alone)
gives each array's buffer as a view of the mapping where it lies, and the parse checks the
flight as it checks any body (:func:`~hmcc_schema.parse.parse_batch` with ``views``). The
arrays stay in the file: ``hmcc flight``'s children read their own pairs' arrays from it.
"""

from __future__ import annotations

import mmap
import os
import stat
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
from pydantic import ValidationError

from hmcc import InputError
from hmcc.flight import Flight

from .in_place import ARRAY, MAP, UNPACK_ERRORS, entry
from .parse import JSON, MSGPACK, parse_batch

__all__ = [
    "MappedFlightFile",
    "encode_body",
    "encode_flight",
    "flight_media_type",
    "read_flight_file",
    "wire_array",
    "wire_buffer",
    "write_bytes",
    "write_flight_file",
]

_PAIR_ARRAYS = {"matches": "matches", "keypoints1": "keypoints", "keypoints2": "keypoints"}
#: The keys of an image's and of a pair's arrays.
_IMAGE_ARRAYS = frozenset({"keypoints", "descriptors"})
_PAIR_BUFFERS = frozenset(_PAIR_ARRAYS)


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
    pair_docs = []
    for pair in pairs:
        doc = dict(pair)
        for key, kind in _PAIR_ARRAYS.items():
            if doc.get(key) is not None:
                doc[key] = wire_buffer(wire_array(doc[key], kind))
        pair_docs.append(doc)
    return encode_body(images, pair_docs, extra)


def encode_body(
    images: Mapping[str, Mapping[str, Any]], pairs: Any, extra: Mapping[str, Any]
) -> bytes:
    """A flight's MessagePack bytes: ``images`` with their arrays as buffers, ``pairs`` as
    given (rows or columns, their arrays buffers already), then ``extra`` but its None
    values."""
    image_docs = {}
    for name, image in images.items():
        doc = dict(image)
        for key in _IMAGE_ARRAYS:
            if doc.get(key) is not None:
                doc[key] = wire_buffer(wire_array(doc[key], key))
        image_docs[name] = doc
    body = {"images": image_docs, "pairs": pairs}
    body.update({k: v for k, v in extra.items() if v is not None})
    return bytes(msgpack.packb(body))


def write_flight_file(
    path: str | Path,
    images: Mapping[str, Mapping[str, Any]],
    pairs: Iterable[Mapping[str, Any]],
    **extra: Any,
) -> int:
    """Write a binary flight file (see :func:`encode_flight`); returns its size in bytes."""
    return write_bytes(path, encode_flight(images, pairs, **extra))


def write_bytes(path: str | Path, data: bytes) -> int:
    """Write ``data`` to ``path``; returns its size in bytes."""
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


class MappedFlightFile:
    """A binary flight file mapped in memory, read-only (:meth:`open`): its pairs counted from
    a header (:meth:`pair_count`), its flight read with its arrays left in the file
    (:meth:`flight`), and where in the file an array of that flight lies (:meth:`offset`)."""

    def __init__(self, path: str, data: mmap.mmap) -> None:
        self.path = path
        self.data = data
        self._address = np.frombuffer(data, dtype=np.uint8).ctypes.data

    @classmethod
    def open(cls, path: str | Path) -> MappedFlightFile | None:
        """``path`` mapped when it is a binary flight file (its first byte opens a MessagePack
        map), else None (a JSON file, an empty one, not a regular file: a pipe is read as it
        comes). Raises ``OSError`` when it does not open."""
        with open(path, "rb") as f:
            if not stat.S_ISREG(os.fstat(f.fileno()).st_mode):
                return None
            first = f.read(1)
            if not first or first[0] not in MAP:
                return None
            data = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
        return cls(str(Path(path).resolve()), data)

    def pair_count(self) -> int:
        """How many pairs the file has, from its ``pairs``' header (an array of rows, or the
        ``image1`` column of pairs as columns; what comes before skipped, not read); 0 when
        there is no such entry (the parse says why)."""
        reader = entry(self.data, "pairs")
        try:
            if reader is None:
                return 0
            if reader.next_byte() in ARRAY:
                return int(reader.unpacker.read_array_header())
            if reader.next_byte() in MAP:
                for _ in range(reader.unpacker.read_map_header()):
                    if reader.unpacker.unpack() == "image1" and reader.next_byte() in ARRAY:
                        return int(reader.unpacker.read_array_header())
                    reader.unpacker.skip()
        except UNPACK_ERRORS:
            pass
        return 0

    def flight(self, max_pairs: int = 10**9) -> Flight | None:
        """The file's flight, checked as any batch body is (:func:`parse_batch`), its arrays
        views of the file where the parse keeps them as they are (each pair's matches, in
        their own dtype: see ``views`` there); None when the file is not plainly a valid
        flight: :func:`read_flight_file` then says why, in the same words as for any body."""
        doc = self._walk()
        if doc is None:
            return None
        try:
            return parse_batch(doc, max_pairs, views=True)
        except (ValidationError, InputError):
            return None

    def offset(self, array: np.ndarray) -> int | None:
        """Where ``array``'s data starts in the file, when it is a (contiguous) view of the
        mapping; else None."""
        start = int(self.offsets([array])[0])
        return None if start < 0 else start

    def offsets(self, arrays: list[np.ndarray]) -> np.ndarray:
        """:meth:`offset` of each array, -1 for one that is not a view of the mapping (a
        flight's every pair's matches at once: 1 microsecond an array)."""
        address, size = self._address, len(self.data)
        out = np.fromiter(
            (
                a.__array_interface__["data"][0] - address if a.flags.c_contiguous else -1
                for a in arrays
            ),
            np.int64,
            len(arrays),
        )
        nbytes = np.fromiter((a.nbytes for a in arrays), np.int64, len(arrays))
        out[(out < 0) | (out + nbytes > size)] = -1
        return out

    def _unpacker(self) -> msgpack.Unpacker:
        """An unpacker reading the file from its start (its ``tell()``: where in the file),
        its limits those of :func:`msgpack.unpackb` on the whole file."""
        size = max(len(self.data), 1)
        self.data.seek(0)
        return msgpack.Unpacker(
            self.data,
            raw=False,
            strict_map_key=True,
            read_size=min(size, 2**16),
            max_buffer_size=size,
        )

    def _walk(self) -> dict[str, Any] | None:
        """The file as :func:`msgpack.unpackb` reads it, but for the data of the images' and
        pairs' array buffers: views of the mapping (a walk over the MessagePack of the
        document, of its images and pairs; the rest unpacked whole). None when it does not
        unpack (or holds more than one object)."""
        data, view = self.data, memoryview(self.data)
        unpacker = self._unpacker()

        def is_map() -> bool:
            return data[unpacker.tell()] in MAP

        def buffer() -> Any:
            """An array, unpacked whole: a buffer object's data (a bin) made a view of the
            file where it is the object's last value, as :func:`wire_buffer` writes it (its
            bytes are then the object's last ones; else it stays a copy)."""
            value = unpacker.unpack()
            raw = value.get("data") if isinstance(value, dict) else None
            if type(raw) is bytes and next(reversed(value)) == "data":
                end = unpacker.tell()
                value["data"] = view[end - len(raw) : end]
            return value

        def entries(arrays: frozenset[str]) -> Any:
            if not is_map():
                return unpacker.unpack()
            doc = {}
            for _ in range(unpacker.read_map_header()):
                key = unpacker.unpack()
                doc[key] = buffer() if key in arrays else unpacker.unpack()
            return doc

        try:
            if not is_map():
                return None
            doc: dict[str, Any] = {}
            for _ in range(unpacker.read_map_header()):
                key = unpacker.unpack()
                if key == "images" and is_map():
                    count = unpacker.read_map_header()
                    doc[key] = {unpacker.unpack(): entries(_IMAGE_ARRAYS) for _ in range(count)}
                elif key == "pairs" and data[unpacker.tell()] in ARRAY:
                    count = unpacker.read_array_header()
                    doc[key] = [entries(_PAIR_BUFFERS) for _ in range(count)]
                else:
                    doc[key] = unpacker.unpack()
        except (ValueError, TypeError, IndexError, msgpack.UnpackException):
            return None
        return doc if unpacker.tell() == len(data) else None
