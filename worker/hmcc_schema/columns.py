"""Pairs as columns: a flight's or a batch's pairs as one object of columns, read and checked
all at once.

In the row form each pair is an object (``{id?, image1, image2, matches}``), so reading a
flight costs Python work a pair, in the one process that reads it: the API process for a batch,
``hmcc flight`` for a flight file. As columns the pairs are one object::

    "pairs": {
        "image1": ["a", "a", ...],      # N image ids
        "image2": ["b", "c", ...],
        "id": ["p1", null, ...],        # optional: each pair's id or null
        "counts": <buffer (N,)>,        # each pair's number of matches, > 0 ("<i4" or "<i8")
        "matches": <buffer (M, 2)>      # every pair's matches, pair after pair (M: their sum)
    }

in MessagePack, arrays as buffers (``{"dtype", "shape", "data"}``, the matches in the row
form's dtypes), and the rest of the body (``images``, ``method``, ``params``, ``plane``) as in
the row form. A pair that brings its own keypoints or asks for matching has no column: such a
flight or batch stays in rows.

:func:`~hmcc_schema.in_place.walk` reads the MessagePack with each buffer's data a view of the
bytes it lies in (bytes, or a mapped file: nothing copied); :func:`read_columns` checks the
header (images, method, params, plane) with the batch parser
(:func:`~hmcc_schema.parse.parse_batch`) and the first pair, then every pair at once, column by
column (image ids, counts, index ranges, poses). Pairs that are not plainly valid are read as
rows and parsed as any body, which says what is wrong (naming ``pairs[i]``, as for the row
form). :class:`PairColumns` gives the pairs as the core's :class:`~hmcc.flight.FlightPair` one
at a time, or their columns as they are (:meth:`PairColumns.take`,
:meth:`PairColumns.as_sent`).

:func:`parse_batch_body` is a batch body's entry in either form (the API's ``POST
/v1/batches``), and :mod:`hmcc_schema.flight_columns` a flight file's.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator, Sequence
from typing import Any, overload

import numpy as np
from pydantic import ValidationError

from hmcc import InputError
from hmcc.flight import Flight, FlightPair
from hmcc.method_names import POS_METHODS

from .in_place import MAP, entry, walk
from .models import MAX_MATCHES
from .parse import (
    _BUFFER_DTYPES,
    _BUFFER_KEYS,
    _CHUNK_ROWS,
    _MAX_NAME,
    MSGPACK,
    _check_count,
    parse_batch,
)

__all__ = [
    "PairColumns",
    "pairs_are_columns",
    "parse_batch_body",
    "parse_batch_columns",
    "read_columns",
]

_COLUMNS = frozenset({"image1", "image2", "id", "counts", "matches"})
_MATCH_DTYPES = frozenset(_BUFFER_DTYPES["matches"])
_COUNT_DTYPES = frozenset({"<i4", "<i8"})


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

    def counts(self) -> np.ndarray:
        """Each pair's number of matches, in this selection's order."""
        rows = np.arange(len(self.image1)) if self.rows is None else self.rows
        return self.starts[rows + 1] - self.starts[rows]

    def pair_ids(self) -> list[str | None]:
        """Each pair's id (None: it has none), in this selection's order."""
        if self.ids is None:
            return [None] * len(self)
        return list(self.ids) if self.rows is None else [self.ids[k] for k in self.rows]

    def image_names(self) -> set[str]:
        """The images the pairs of this selection name."""
        rows = range(len(self.image1)) if self.rows is None else self.rows.tolist()
        image1, image2 = self.image1, self.image2
        return {image1[k] for k in rows} | {image2[k] for k in rows}

    def as_sent(self) -> list[FlightPair]:
        """The pairs of this selection, each with its matches a view of the column in its own
        dtype (not an int64 copy): for whoever packs or shares them for the core, which then
        converts them (as :func:`~hmcc_schema.parse.parse_batch` gives them with ``views``)."""
        rows = range(len(self.image1)) if self.rows is None else self.rows.tolist()
        starts, ids = self.starts.tolist(), self.ids
        return [
            FlightPair(
                self.image1[k],
                self.image2[k],
                self.matches[starts[k] : starts[k + 1]],
                id=None if ids is None else ids[k],
            )
            for k in rows
        ]

    def take(self, indices: Sequence[int]) -> PairColumns:
        """Pairs ``indices`` of these, as columns (nothing copied)."""
        rows = np.asarray(indices, dtype=np.int64)
        if self.rows is not None:
            rows = self.rows[rows]
        return PairColumns(self.image1, self.image2, self.ids, self.matches, self.starts, rows)

    @staticmethod
    def joined(parts: Sequence[Sequence[FlightPair]]) -> PairColumns | None:
        """Selections of the same columns, one after the other, as one selection; None when
        ``parts`` are not all selections of one set of columns."""
        first = parts[0] if parts else None
        if not isinstance(first, PairColumns) or not all(
            isinstance(p, PairColumns) and p.matches is first.matches for p in parts
        ):
            return None
        rows = np.concatenate(
            [
                np.arange(len(p.image1)) if p.rows is None else p.rows
                for p in parts
                if isinstance(p, PairColumns)
            ]
        )
        return PairColumns(first.image1, first.image2, first.ids, first.matches, first.starts, rows)


def parse_batch_body(body: bytes, max_pairs: int, media_type: str) -> Flight:
    """A batch body (the API's ``POST /v1/batches``) as a flight, in either form: pairs as
    columns when a MessagePack body has them so (:func:`parse_batch_columns`), else as rows
    (:func:`~hmcc_schema.parse.parse_batch`), each pair's matches as sent (views of the body,
    not one int64 copy of them all: whoever packs or shares the pairs for the core converts
    them). Raises pydantic's ``ValidationError`` or :class:`InputError`."""
    if media_type == MSGPACK and (flight := parse_batch_columns(body, max_pairs)) is not None:
        return flight
    return parse_batch(body, max_pairs, media_type, views=True)


def parse_batch_columns(body: bytes, max_pairs: int) -> Flight | None:
    """A MessagePack batch body whose pairs are columns as a flight (its pairs
    :class:`PairColumns`, their matches views of ``body`` in its dtype); None when its pairs are
    not an object (parse it as rows). Raises pydantic's ``ValidationError`` or
    :class:`InputError` naming what is wrong."""
    if not pairs_are_columns(body):
        return None
    return read_columns(walk(body), max_pairs)


def pairs_are_columns(data: Any) -> bool:
    """Whether the MessagePack ``data`` (bytes, or a mapped file) is a map whose ``pairs`` is
    a map: the pairs as columns. What comes before ``pairs`` is skipped, not kept; nothing
    after it is read."""
    reader = entry(data, "pairs")
    return reader is not None and reader.next_byte() in MAP


def read_columns(doc: Any, max_pairs: int = 10**9) -> Flight:
    """The flight of ``doc`` (as :func:`~hmcc_schema.in_place.walk` reads a body whose pairs
    are columns), its pairs :class:`PairColumns` whose matches are views of its buffers, in
    their dtype; at most ``max_pairs`` pairs. Raises pydantic's ``ValidationError`` or
    :class:`InputError` naming what is wrong."""
    if doc is None:
        raise InputError("body", "not one MessagePack object (cut short, or more after it?)")
    if not isinstance(doc, dict) or not isinstance(doc.get("pairs"), dict):
        raise InputError("body", "not a flight whose pairs are columns")
    columns = _columns(doc["pairs"])
    _check_count(len(columns), max_pairs)
    rest = {key: value for key, value in doc.items() if key != "pairs"}
    if not _plain_heads(columns):
        return _as_rows(rest, columns, max_pairs)
    try:  # the header, checked as any body's, with the first pair
        header = parse_batch({**rest, "pairs": [_row(columns, 0)]}, 1, views=True)
    except (ValidationError, InputError):
        return _as_rows(rest, columns, max_pairs)
    if not _plainly_valid(header, columns):
        return _as_rows(rest, columns, max_pairs)
    return dataclasses.replace(header, pairs=columns)


def _columns(doc: dict[str, Any]) -> PairColumns:
    """The columns of ``doc`` (a body's ``pairs``), or :class:`InputError` naming the one
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
    """Pair ``k`` as a row (its matches a view of the column)."""
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
