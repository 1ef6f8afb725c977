"""A binary flight file whose pairs are columns: the form ``hmcc flight`` reads fastest.

In the row form (:mod:`hmcc_schema.flight_file`) each pair is an object (``{id?, image1,
image2, matches}``), so reading a flight costs Python work a pair, in the one process that
hands the pairs to the children: on the 750-image benchmark flight (18 283 pairs) reading
the rows and writing their shared file took half of ``hmcc flight``'s own CPU time. Here the
pairs are one object of columns::

    "pairs": {
        "image1": ["a", "a", ...],      # N image ids
        "image2": ["b", "c", ...],
        "id": ["p1", null, ...],        # optional: each pair's id or null
        "counts": <buffer (N,)>,        # each pair's number of matches, > 0 ("<i4" or "<i8")
        "matches": <buffer (M, 2)>      # every pair's matches, pair after pair (M: their sum)
    }

and the rest of the body (``images``, ``method``, ``params``, ``plane``) as in the row form,
arrays as buffers (``{"dtype", "shape", "data"}``, the matches in the row form's dtypes). A pair
that brings its own keypoints or asks for matching has no column: such a flight stays in rows.

:func:`read_flight_columns` reads one in place: the file mapped, its MessagePack walked with
each buffer's data a view of the mapping; the header (images, method, params, plane) checked
by the batch parser (:func:`~hmcc_schema.parse.parse_batch`) with the first pair, then every
pair at once, column by column (image ids, counts, index ranges, poses). A file whose pairs are
not plainly valid is read as rows and parsed as any body, which says what is wrong (naming
``pairs[i]``, as for the row form). :class:`PairColumns` gives the pairs as the core's
:class:`~hmcc.flight.FlightPair` one at a time, and :mod:`hmcc_worker.shared_flight` hands
their columns to the children as they are.

:func:`write_flight_columns` writes one from the same arguments as
:func:`~hmcc_schema.flight_file.write_flight_file`.
"""

from __future__ import annotations

import dataclasses
import mmap
from collections.abc import Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any, overload

import msgpack
import numpy as np
from pydantic import ValidationError

from hmcc import InputError
from hmcc.flight import Flight, FlightPair
from hmcc.method_names import POS_METHODS

from .flight_file import MappedFlightFile, wire_array, wire_buffer
from .models import MAX_MATCHES
from .parse import parse_batch

__all__ = [
    "PairColumns",
    "column_pair_count",
    "column_rows",
    "encode_flight_columns",
    "read_columns_bytes",
    "read_flight_columns",
    "write_flight_columns",
]

_COLUMNS = frozenset({"image1", "image2", "id", "counts", "matches"})
_BUFFER_KEYS = frozenset({"dtype", "shape", "data"})
_MATCH_DTYPES = frozenset({"<i4", "<i8", "<u2", "<u4"})
_COUNT_DTYPES = frozenset({"<i4", "<i8"})
_MAX_NAME = 200


class PairColumns(Sequence[FlightPair]):
    """A flight's pairs as columns: ``image1``, ``image2``, ``ids`` (None: no ids), every
    pair's ``matches`` one after another (M, 2) and where each pair's start (``starts``, N + 1
    rows: the last is M). ``[i]`` is pair ``i`` with int64 matches (a copy: the core's dtype);
    :meth:`take` a selection of them, still columns."""

    def __init__(
        self,
        image1: list[str],
        image2: list[str],
        ids: list[str | None] | None,
        matches: np.ndarray,
        starts: np.ndarray,
        rows: np.ndarray | None = None,
    ) -> None:
        self.image1, self.image2, self.ids = image1, image2, ids
        self.matches, self.starts = matches, starts
        # the pairs of the columns this selection holds (None: all of them, in order)
        self.rows = rows

    def __len__(self) -> int:
        return len(self.image1) if self.rows is None else len(self.rows)

    @overload
    def __getitem__(self, index: int) -> FlightPair: ...

    @overload
    def __getitem__(self, index: slice) -> Sequence[FlightPair]: ...

    def __getitem__(self, index: int | slice) -> FlightPair | Sequence[FlightPair]:
        if isinstance(index, slice):
            return self.take(range(len(self))[index])
        k = self.row(index)
        matches = self.matches[self.starts[k] : self.starts[k + 1]].astype(np.int64)
        pair_id = None if self.ids is None else self.ids[k]
        return FlightPair(self.image1[k], self.image2[k], matches, id=pair_id)

    def __iter__(self) -> Iterator[FlightPair]:
        return (self[i] for i in range(len(self)))

    def row(self, index: int) -> int:
        """The row in the columns of pair ``index`` of this selection."""
        if not -len(self) <= index < len(self):
            raise IndexError(index)
        index %= len(self)
        return index if self.rows is None else int(self.rows[index])

    def take(self, indices: Sequence[int]) -> PairColumns:
        """Pairs ``indices`` of these, as columns (nothing copied)."""
        rows = np.asarray(indices, dtype=np.int64)
        if self.rows is not None:
            rows = self.rows[rows]
        return PairColumns(self.image1, self.image2, self.ids, self.matches, self.starts, rows)


def encode_flight_columns(
    images: Mapping[str, Mapping[str, Any]],
    pairs: Iterable[Mapping[str, Any]],
    **extra: Any,
) -> bytes:
    """A flight as MessagePack bytes with its pairs as columns (the module's docstring); the
    arguments as for :func:`~hmcc_schema.flight_file.encode_flight` (each pair ``{id?,
    image1, image2, matches}``). Raises ``ValueError`` for a pair with its own keypoints, one
    that asks for matching or one without matches: those have no column (write rows)."""
    image_docs = {}
    for name, image in images.items():
        doc = dict(image)
        for key in ("keypoints", "descriptors"):
            if doc.get(key) is not None:
                doc[key] = wire_buffer(wire_array(doc[key], key))
        image_docs[name] = doc
    image1: list[Any] = []
    image2: list[Any] = []
    ids: list[Any] = []
    matches: list[np.ndarray] = []
    for i, pair in enumerate(pairs):
        if set(pair) - {"id", "image1", "image2", "matches"} or pair.get("matches") is None:
            what = sorted(set(pair) - {"id", "image1", "image2"})
            raise ValueError(
                f"pairs[{i}] has {what}: a pair has columns for its id, images and matches only"
            )
        image1.append(pair["image1"])
        image2.append(pair["image2"])
        ids.append(pair.get("id"))
        matches.append(np.asarray(pair["matches"]).reshape(-1, 2))
    counts = np.fromiter(map(len, matches), np.int64, len(matches))
    every = np.concatenate(matches) if matches else np.zeros((0, 2), np.int64)
    columns: dict[str, Any] = {"image1": image1, "image2": image2}
    if any(pair_id is not None for pair_id in ids):
        columns["id"] = ids
    columns["counts"] = wire_buffer(counts.astype("<i8"))
    columns["matches"] = wire_buffer(wire_array(every, "matches"))
    body = {"images": image_docs, "pairs": columns}
    body.update({k: v for k, v in extra.items() if v is not None})
    return bytes(msgpack.packb(body))


def write_flight_columns(
    path: str | Path,
    images: Mapping[str, Mapping[str, Any]],
    pairs: Iterable[Mapping[str, Any]],
    **extra: Any,
) -> int:
    """Write a binary flight file with its pairs as columns (:func:`encode_flight_columns`);
    returns its size in bytes."""
    data = encode_flight_columns(images, pairs, **extra)
    Path(path).write_bytes(data)
    return len(data)


def column_pair_count(mapped: MappedFlightFile) -> int | None:
    """How many pairs the file has when its pairs are columns (the length of its
    ``pairs.image1`` array, from its header: the rest skipped, not read); None when its pairs
    are not an object of columns."""
    data = mapped.data
    unpacker = mapped._unpacker()
    try:
        for _ in range(unpacker.read_map_header()):
            key = unpacker.unpack()
            if key != "pairs":
                unpacker.skip()
                continue
            if data[unpacker.tell()] not in _MAP:
                return None
            for _ in range(unpacker.read_map_header()):
                if unpacker.unpack() == "image1" and data[unpacker.tell()] in _ARRAY:
                    return int(unpacker.read_array_header())
                unpacker.skip()
            return 0
    except (ValueError, TypeError, IndexError, msgpack.UnpackException):
        pass
    return None


# The first bytes of a MessagePack map and array (as in flight_file).
_MAP = frozenset({*range(0x80, 0x90), 0xDE, 0xDF})
_ARRAY = frozenset({*range(0x90, 0xA0), 0xDC, 0xDD})


def read_flight_columns(mapped: MappedFlightFile, max_pairs: int = 10**9) -> Flight:
    """The flight of a file whose pairs are columns (:func:`column_pair_count` not None), its
    pairs :class:`PairColumns` whose matches are views of the file, in its dtype. Raises
    pydantic's ``ValidationError`` or :class:`hmcc.InputError` naming what is wrong."""
    doc = _walk(mapped)
    if doc is None:
        raise InputError("body", "not one MessagePack object (cut short, or more after it?)")
    if not isinstance(doc, dict) or not isinstance(doc.get("pairs"), dict):
        raise InputError("body", "not a flight whose pairs are columns")
    columns = _columns(doc["pairs"])
    n = len(columns.image1)
    rest = {key: value for key, value in doc.items() if key != "pairs"}
    if n > max_pairs or not _plain_heads(columns):
        return _as_rows(rest, columns, max_pairs)
    try:  # the header, checked as any body's, with the first pair
        header = parse_batch({**rest, "pairs": [_row(columns, 0)]}, 1, views=True)
    except (ValidationError, InputError):
        return _as_rows(rest, columns, max_pairs)
    if not _plainly_valid(header, columns):
        return _as_rows(rest, columns, max_pairs)
    return dataclasses.replace(header, pairs=columns)


def read_columns_bytes(data: bytes, max_pairs: int = 10**9) -> Flight | None:
    """:func:`read_flight_columns` of a flight given as bytes (standard input), copied into
    memory of its own that its arrays then view; None when its pairs are not columns."""
    if not data or data[0] not in _MAP:
        return None
    memory = mmap.mmap(-1, len(data))
    memory.write(data)
    mapped = MappedFlightFile("<memory>", memory)
    if column_pair_count(mapped) is None:
        return None
    return read_flight_columns(mapped, max_pairs)


def column_rows(doc: dict[str, Any]) -> list[dict[str, Any]]:
    """Pairs as columns (a flight's ``pairs``, as unpacked) as rows: each pair an object, its
    matches a view of the column. Raises :class:`InputError` naming a column that is not one."""
    columns = _columns(doc)
    return [_row(columns, k) for k in range(len(columns))]


def _walk(mapped: MappedFlightFile) -> Any:
    """The file as :func:`msgpack.unpackb` reads it, but for each ``data`` of a map: where it
    is binary data, a view of the mapping where it lies (a buffer's bytes are neither copied
    nor read). None when it does not unpack whole."""
    reader = _Reader(mapped.data)

    def value() -> Any:
        if reader.next_byte() not in _MAP:
            return reader.unpacker.unpack()
        doc = {}
        for _ in range(reader.unpacker.read_map_header()):
            key = reader.unpacker.unpack()
            data = reader.binary() if key == "data" else None
            doc[key] = value() if data is None else data
        return doc

    try:
        doc = value()
    except (ValueError, TypeError, IndexError, RecursionError, msgpack.UnpackException):
        return None
    return doc if reader.tell() == len(mapped.data) else None


# The first byte of a MessagePack bin, and how many bytes of length follow it.
_BIN = {0xC4: 1, 0xC5: 2, 0xC6: 4}


class _Reader:
    """A MessagePack unpacker over a mapped file that steps over binary data without reading
    it (an unpacker copies every object it reads or skips into its buffer: the flight's
    matches, 100 MB, cost more than the rest of reading it)."""

    def __init__(self, data: Any) -> None:
        self.data = data
        self._start(0)

    def _start(self, at: int) -> None:
        size = len(self.data)
        self.data.seek(at)
        self.base = at
        self.unpacker = msgpack.Unpacker(
            self.data,
            raw=False,
            strict_map_key=True,
            read_size=max(1, min(size - at, 2**16)),
            max_buffer_size=max(size, 1),
        )

    def tell(self) -> int:
        """Where in the file the next object starts."""
        return self.base + int(self.unpacker.tell())

    def next_byte(self) -> int:
        return int(self.data[self.tell()])

    def binary(self) -> memoryview | None:
        """The binary data that comes next, as a view of the file (read past); None, and
        nothing read, when what comes next is not binary data."""
        at = self.tell()
        width = _BIN.get(self.data[at])
        if width is None:
            return None
        start = at + 1 + width
        end = start + int.from_bytes(self.data[at + 1 : start], "big")
        if end > len(self.data):
            raise ValueError("binary data beyond the end of the file")
        self._start(end)
        return memoryview(self.data)[start:end]


def _columns(doc: dict[str, Any]) -> PairColumns:
    """The columns of ``doc`` (the file's ``pairs``), or :class:`InputError` naming the one
    that is not a column of the others' length."""
    unknown = sorted(set(doc) - _COLUMNS)
    if unknown:
        raise InputError(f"pairs.{unknown[0]}", f"not a column; the columns are {sorted(_COLUMNS)}")
    for key in ("image1", "image2", "counts", "matches"):
        if key not in doc:
            raise InputError(
                f"pairs.{key}", "missing: pairs as columns have image1, image2, counts and matches"
            )
    image1, image2, ids = doc["image1"], doc["image2"], doc.get("id")
    for key, column in (("image1", image1), ("image2", image2), ("id", ids)):
        if column is not None and not isinstance(column, list):
            raise InputError(f"pairs.{key}", "a column is an array, one value a pair")
    n = len(image1)
    if not n:
        raise InputError("pairs.image1", "no pairs: at least one")
    for key, column in (("image2", image2), ("id", ids)):
        if column is not None and len(column) != n:
            raise InputError(f"pairs.{key}", f"{len(column)} values; one a pair: {n}")
    counts = _buffer(doc["counts"], "pairs.counts", _COUNT_DTYPES, (n,))
    matches = _buffer(doc["matches"], "pairs.matches", _MATCH_DTYPES, None)
    if matches.ndim != 2 or matches.shape[1] != 2:
        raise InputError("pairs.matches", f"shape {list(matches.shape)}; (M, 2), M: sum of counts")
    bad = np.flatnonzero((counts <= 0) | (counts > MAX_MATCHES))
    if len(bad):
        k = int(bad[0])
        raise InputError(
            f"pairs.counts[{k}]", f"{int(counts[k])} matches; a pair has 1 to {MAX_MATCHES}"
        )
    starts = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(counts, out=starts[1:])
    if starts[-1] != len(matches):
        raise InputError(
            "pairs.matches", f"{len(matches)} rows; the counts add up to {int(starts[-1])}"
        )
    return PairColumns(image1, image2, ids, matches, starts)


def _buffer(
    value: Any, field: str, dtypes: frozenset[str], shape: tuple[int, ...] | None
) -> np.ndarray:
    if not (isinstance(value, dict) and value.keys() == _BUFFER_KEYS):
        raise InputError(field, "a column of numbers is a buffer: {dtype, shape, data}")
    dtype, data = value["dtype"], value["data"]
    if dtype not in dtypes:
        raise InputError(field, f"dtype {str(dtype)[:20]!r}; one of {sorted(dtypes)}")
    try:
        array = np.frombuffer(data, dtype=np.dtype(dtype)).reshape(value["shape"])
    except (ValueError, TypeError):
        raise InputError(field, "its data does not hold its shape") from None
    if shape is not None and array.shape != shape:
        raise InputError(field, f"shape {list(array.shape)}; one value a pair: {list(shape)}")
    return array


def _plain_heads(columns: PairColumns) -> bool:
    """Every image id a non-empty string of at most 200 characters, every id one or null (as
    for a pair of rows); False: the rows' parse says what is wrong."""

    def names(values: list[Any]) -> bool:
        return all(type(v) is str and 0 < len(v) <= _MAX_NAME for v in values)

    ids = columns.ids
    plain_ids = ids is None or all(
        v is None or (type(v) is str and len(v) <= _MAX_NAME) for v in ids
    )
    return names(columns.image1) and names(columns.image2) and plain_ids


def _plainly_valid(header: Flight, columns: PairColumns) -> bool:
    """Every pair names images of the flight that have keypoints (and poses, where the method
    uses them), its indices within them: the rows' check (``parse._check_pairs``) for all the
    pairs at once. False: the rows' parse says what is wrong."""
    images = header.images
    needs_pose = header.method in POS_METHODS
    counts = {
        name: len(image.keypoints)
        for name, image in images.items()
        if image.keypoints is not None and (image.pose is not None or not needs_pose)
    }
    try:
        limit1 = np.fromiter(map(counts.__getitem__, columns.image1), np.int64, len(columns))
        limit2 = np.fromiter(map(counts.__getitem__, columns.image2), np.int64, len(columns))
    except KeyError:  # an image not in the flight, or without keypoints (or pose)
        return False
    maxima = _maxima(columns.matches, columns.starts)
    if maxima is None:
        return False
    return not ((maxima[:, 0] >= limit1).any() or (maxima[:, 1] >= limit2).any())


#: Rows of matches checked at a time (a chunk's copy stays in the cache).
_CHUNK_ROWS = 1 << 17


def _maxima(matches: np.ndarray, starts: np.ndarray) -> np.ndarray | None:
    """Each pair's largest index in either column, (N, 2) int64, a chunk of about
    :data:`_CHUNK_ROWS` rows at a time; None when an index is negative."""
    n = len(starts) - 1
    maxima = np.empty((n, 2), dtype=np.int64)
    first = 0
    while first < n:
        # the most pairs from ``first`` whose rows fit a chunk (at least one pair)
        fit = int(np.searchsorted(starts, starts[first] + _CHUNK_ROWS, side="right")) - 1
        last = min(max(first + 1, fit), n)
        chunk = np.asarray(matches[starts[first] : starts[last]])
        if chunk.dtype.kind == "i" and chunk.min() < 0:
            return None
        maxima[first:last] = np.maximum.reduceat(chunk, starts[first:last] - starts[first], axis=0)
        first = last
    return maxima


def _row(columns: PairColumns, k: int) -> dict[str, Any]:
    """Pair ``k`` as a row (its matches a view of the file)."""
    row: dict[str, Any] = {
        "image1": columns.image1[k],
        "image2": columns.image2[k],
        "matches": columns.matches[columns.starts[k] : columns.starts[k + 1]],
    }
    if columns.ids is not None:
        row["id"] = columns.ids[k]
    return row


def _as_rows(rest: dict[str, Any], columns: PairColumns, max_pairs: int) -> Flight:
    """The flight parsed as rows, each pair an object: what is wrong said as for any body
    (or, where the rows are valid after all, their flight)."""
    rows = [_row(columns, k) for k in range(len(columns.image1))]
    return parse_batch({**rest, "pairs": rows}, max_pairs, views=True)
