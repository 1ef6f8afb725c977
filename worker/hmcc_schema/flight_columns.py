"""A binary flight file whose pairs are columns: the form ``hmcc flight`` reads fastest.

In the row form (:mod:`hmcc_schema.flight_file`) each pair is an object, so reading a flight
costs Python work a pair, in the one process that hands the pairs to the children: on the
750-image benchmark flight (18 283 pairs) reading the rows and writing their shared file took
half of ``hmcc flight``'s own CPU time. Here the pairs are one object of columns, as a batch
body's may be (:mod:`hmcc_schema.columns` says the form and reads it), and the rest of the body
(``images``, ``method``, ``params``, ``plane``) as in the row form.

:func:`read_flight_columns` reads one in place: the file mapped, its MessagePack walked with
each buffer's data a view of the mapping, then checked as a batch body whose pairs are columns
(:func:`~hmcc_schema.columns.read_columns`); :mod:`hmcc_worker.shared_flight` hands their
columns to the children as they are. :func:`write_flight_columns` writes one from the same
arguments as :func:`~hmcc_schema.flight_file.write_flight_file`.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from hmcc.flight import Flight

from .columns import _columns, _row, pairs_are_columns, read_columns
from .flight_file import MappedFlightFile, encode_body, wire_array, wire_buffer, write_bytes
from .in_place import walk

__all__ = [
    "column_rows",
    "encode_flight_columns",
    "read_columns_bytes",
    "read_flight_columns",
    "write_flight_columns",
]


def encode_flight_columns(
    images: Mapping[str, Mapping[str, Any]],
    pairs: Iterable[Mapping[str, Any]],
    **extra: Any,
) -> bytes:
    """A flight as MessagePack bytes with its pairs as columns (the module's docstring); the
    arguments as for :func:`~hmcc_schema.flight_file.encode_flight` (each pair ``{id?,
    image1, image2, matches}``). Raises ``ValueError`` for a pair with its own keypoints, one
    that asks for matching or one without matches: those have no column (write rows)."""
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
    return encode_body(images, columns, extra)


def write_flight_columns(
    path: str | Path,
    images: Mapping[str, Mapping[str, Any]],
    pairs: Iterable[Mapping[str, Any]],
    **extra: Any,
) -> int:
    """Write a binary flight file with its pairs as columns (:func:`encode_flight_columns`);
    returns its size in bytes."""
    return write_bytes(path, encode_flight_columns(images, pairs, **extra))


def read_flight_columns(mapped: MappedFlightFile, max_pairs: int = 10**9) -> Flight:
    """The flight of a file whose pairs are columns
    (:func:`~hmcc_schema.columns.pairs_are_columns`), its pairs
    :class:`~hmcc_schema.columns.PairColumns` whose matches are views of the file, in its
    dtype. Raises pydantic's ``ValidationError`` or :class:`hmcc.InputError` naming what is
    wrong."""
    return read_columns(walk(mapped.data), max_pairs)


def read_columns_bytes(data: bytes, max_pairs: int = 10**9) -> Flight | None:
    """:func:`read_flight_columns` of a flight given as bytes (standard input), its arrays
    views of them; None when its pairs are not columns."""
    if not pairs_are_columns(data):
        return None
    return read_columns(walk(data), max_pairs)


def column_rows(doc: dict[str, Any]) -> list[dict[str, Any]]:
    """Pairs as columns (a flight's ``pairs``, as unpacked) as rows: each pair an object, its
    matches a view of the column. Raises :class:`InputError` naming a column that is not one."""
    columns = _columns(doc)
    return [_row(columns, k) for k in range(len(columns))]
