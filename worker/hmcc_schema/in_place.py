"""MessagePack read in place: a body or a binary flight file unpacked with its buffers' data left
where it lies (bytes, or a mapped file: nothing copied), and a peek at one top-level entry
without reading the rest.

msgpack's ``Unpacker`` copies every object it reads or skips into its own buffer: a flight's
matches (100 MB on the benchmark flight) cost more than the rest of reading it. :class:`Reader`
steps over binary data instead (a new unpacker from just past it); :func:`walk` unpacks a
document so, each ``data`` of a map that is binary made a view of the data; :func:`entry`
finds a top-level key, skipping what comes before it.
"""

from __future__ import annotations

import io
from typing import Any

import msgpack

from hmcc import InputError

from .parse import MAX_DEPTH, _depth_reason

__all__ = ["ARRAY", "MAP", "Reader", "entry", "walk"]

#: The first byte of a MessagePack map, of an array.
MAP = frozenset({*range(0x80, 0x90), 0xDE, 0xDF})
ARRAY = frozenset({*range(0x90, 0xA0), 0xDC, 0xDD})
# The first byte of a bin, and how many bytes of length follow it.
_BIN = {0xC4: 1, 0xC5: 2, 0xC6: 4}
#: What an unpacker that fails on malformed data raises.
UNPACK_ERRORS = (ValueError, TypeError, IndexError, msgpack.UnpackException)


class Reader:
    """A MessagePack unpacker over bytes or a mapped file that steps over binary data without
    reading it (:meth:`binary`)."""

    def __init__(self, data: Any) -> None:
        self.data = data
        # read as a file (bytes: a BytesIO over them, which shares them until written to)
        self.file = data if hasattr(data, "seek") else io.BytesIO(data)
        self._start(0)

    def _start(self, at: int) -> None:
        size = len(self.data)
        self.file.seek(at)
        self.base = at
        self.unpacker = msgpack.Unpacker(
            self.file,
            raw=False,
            strict_map_key=True,
            read_size=max(1, min(size - at, 2**16)),
            max_buffer_size=max(size, 1),
        )

    def tell(self) -> int:
        """Where in the data the next object starts."""
        return self.base + int(self.unpacker.tell())

    def next_byte(self) -> int:
        return int(self.data[self.tell()])

    def binary(self) -> memoryview | None:
        """The binary data that comes next, as a view of the data (read past); None, and
        nothing read, when what comes next is not binary data."""
        at = self.tell()
        width = _BIN.get(self.data[at])
        if width is None:
            return None
        start = at + 1 + width
        end = start + int.from_bytes(self.data[at + 1 : start], "big")
        if end > len(self.data):
            raise ValueError("binary data beyond the end")
        self._start(end)
        return memoryview(self.data)[start:end]


def walk(data: Any) -> Any:
    """``data`` (MessagePack: bytes, or a mapped file) as :func:`msgpack.unpackb` reads it,
    but for each ``data`` of a map: where it is binary data, a view of ``data`` where it lies
    (a buffer's bytes are neither copied nor read). None when it does not unpack whole; an
    :class:`InputError` when it nests deeper than :data:`~hmcc_schema.parse.MAX_DEPTH`.
    Arrays are unpacked whole: a body whose pairs are rows is read by the parse, and a binary
    flight file of rows by :meth:`~hmcc_schema.flight_file.MappedFlightFile.flight` (this
    walk, descending each pair, took 0.2 s for a flight's 18 283 rows where that one takes
    0.08 s)."""
    reader = Reader(data)

    def value(depth: int) -> Any:
        if reader.next_byte() not in MAP:
            return reader.unpacker.unpack()
        if depth == MAX_DEPTH:
            raise InputError("body", _depth_reason("MessagePack"))
        doc = {}
        for _ in range(reader.unpacker.read_map_header()):
            key = reader.unpacker.unpack()
            found = reader.binary() if key == "data" else None
            doc[key] = value(depth + 1) if found is None else found
        return doc

    try:
        doc = value(0)
    except InputError:
        raise
    except msgpack.StackError:  # arrays nested deeper than the unpacker's own stack
        raise InputError("body", _depth_reason("MessagePack")) from None
    except UNPACK_ERRORS:
        return None
    return doc if reader.tell() == len(data) else None


def entry(data: Any, key: str) -> Reader | None:
    """A reader of ``data`` (MessagePack: bytes, or a mapped file) at the value of its
    top-level map's ``key``, what comes before it skipped (not kept); None when ``data`` is
    not a map with that key (and something after it)."""
    if not len(data) or data[0] not in MAP:
        return None
    reader = Reader(data)
    try:
        for _ in range(reader.unpacker.read_map_header()):
            if reader.unpacker.unpack() == key:
                return reader if reader.tell() < len(data) else None  # a value follows
            reader.unpacker.skip()
    except UNPACK_ERRORS:
        pass
    return None
