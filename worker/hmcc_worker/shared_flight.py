"""A flight the compute pool's children read from one shared file, not from every task.

:meth:`ComputePool.map_flight` pickles each task's flight: its pairs' matches and the
keypoints of every image they name. On the 750-image benchmark flight that is some 5 MB a task
(72 tasks on 2 children, several images' keypoints sent again with every task), pickled and
sent by the one process that hands tasks out while the children wait. Here the flight's arrays
(images' keypoints, pairs' matches and own keypoints) are written once to a file, in memory
where there is room (:func:`scratch_dir`), beside the rest of the flight (cameras, poses, the
pairs' image ids, where each array lies); a task then pickles as the file's path and its pair
indices (a few hundred bytes). A child opens a flight's file once (the rest unpickled, the
arrays mapped copy-on-write: its pages are shared by the children through the page cache) and
takes each task's pairs from it.

A flight read from a mapped binary flight file (:class:`~hmcc_schema.flight_file.MappedFlightFile`,
``hmcc flight``) is not written again: each of its arrays that is a view of that file is
written as where it lies in the flight file itself, which the children map in turn (and copy
each array they take from it: there it lies unaligned, in the file's dtype; a pair's matches
become int64, as the parse gives them).

The pool's guarantees stand: :meth:`SharedFlight.subset` is a shared flight too, so a chunk
whose child dies is still re-run pair by pair, each pair a task of its own.
"""

from __future__ import annotations

import dataclasses
import operator
import os
import pickle
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from tempfile import TemporaryDirectory
from typing import TYPE_CHECKING, Any

import numpy as np

from hmcc.flight import Flight, FlightImage, FlightPair

if TYPE_CHECKING:
    from hmcc_schema.columns import PairColumns
    from hmcc_schema.flight_file import MappedFlightFile

__all__ = ["SharedFlight", "open_shared", "scratch_dir", "shared_flight"]

#: Memory-backed, where there is one (Linux).
_MEMORY_DIR = Path("/dev/shm")
_ARRAYS = "arrays.bin"
_SKELETON = "flight.pickle"
#: Arrays start at multiples of this many bytes (numpy's views want aligned data).
_ALIGN = 64

# A slot: where an array lies (offset, dtype, shape, whether in the flight file rather than
# the arrays file), or None.
_Slot = tuple[int, str, tuple[int, ...], bool] | None
#: Zero bytes the arrays file is padded with (at most an alignment's worth).
_PADDING = memoryview(bytes(_ALIGN))
#: Buffers one ``os.writev`` call takes at most: the system's IOV_MAX (1024 on Linux), at
#: least POSIX's minimum (16) where it does not say.
_IOV_MAX = max(16, os.sysconf("SC_IOV_MAX") if "SC_IOV_MAX" in os.sysconf_names else 16)
_NBYTES = operator.attrgetter("nbytes")


def _write_all(fd: int, buffers: Sequence[Any]) -> None:
    """``buffers`` (C-contiguous arrays and other bytes-like objects) written to the file
    ``fd`` in order, up to :data:`_IOV_MAX` a system call: a batch's thousands of small arrays
    (each pair's matches) written one by one cost a call each, about a third of writing the
    file in the API process."""
    for start in range(0, len(buffers), _IOV_MAX):
        group = buffers[start : start + _IOV_MAX]
        written = os.writev(fd, group)
        if written < sum(map(_NBYTES, group)):  # a short write: the rest, one by one
            rest = memoryview(b"".join(group))[written:]
            while rest:
                rest = rest[os.write(fd, rest) :]


@dataclasses.dataclass(frozen=True)
class SharedFlight(Flight):
    """A :class:`Flight` (the parent's, arrays and all) that pickles as ``folder`` and the
    indices of its pairs in the flight written there; unpickled, it is the shared flight of
    those pairs read from the shared file (``indices`` still tell where they are in the whole
    flight)."""

    folder: str = ""
    indices: tuple[int, ...] = ()

    def subset(self, indices: Sequence[int]) -> SharedFlight:
        """The shared flight of pairs ``indices`` (of this one), images as they are."""
        take = getattr(self.pairs, "take", None)  # pairs as columns: nothing copied
        return dataclasses.replace(
            self,
            pairs=take(indices) if take is not None else [self.pairs[i] for i in indices],
            indices=tuple(self.indices[i] for i in indices),
        )

    def __reduce__(self) -> tuple[Any, ...]:
        return open_shared, (self.folder, self.indices)


def scratch_dir(size: int) -> str | None:
    """The memory-backed :data:`_MEMORY_DIR` when it has twice ``size`` bytes free (a
    container's is often 64 MB), else the temporary directory (None)."""
    try:
        stats = os.statvfs(_MEMORY_DIR)
    except OSError:
        return None
    free = stats.f_bavail * stats.f_frsize
    return str(_MEMORY_DIR) if free >= 2 * size and os.access(_MEMORY_DIR, os.W_OK) else None


@dataclasses.dataclass(frozen=True)
class _PairTable:
    """Every pair of a shared flight, column by column: one pickle of a few arrays and lists
    rather than a tuple a pair (that took a quarter of writing the benchmark flight's shared
    file, and again of each child's opening it). A pair's matches are ``rows`` by 2 of
    ``dtypes[dtype]`` at ``offset`` in the arrays file, or in the flight file where
    ``in_source``; ``own``: the slots of the keypoints of the pairs that bring their own."""

    image1: list[str]
    image2: list[str]
    ids: list[str | None]
    match: np.ndarray
    offset: np.ndarray
    rows: np.ndarray
    dtype: np.ndarray
    dtypes: list[str]
    in_source: np.ndarray
    own: dict[int, tuple[_Slot, _Slot]]


@contextmanager
def shared_flight(flight: Flight, source: MappedFlightFile | None = None) -> Iterator[SharedFlight]:
    """``flight`` written to a shared file (removed at the end) as a :class:`SharedFlight` of
    all its pairs; those of its arrays that are views of ``source`` (the flight file it was
    read from) as where they lie in that file. Pairs given as columns
    (:class:`~hmcc_schema.columns.PairColumns`) keep them: their matches one array,
    each pair's where its rows start in it."""
    from hmcc_schema.columns import PairColumns

    pairs = flight.pairs
    columns = pairs if isinstance(pairs, PairColumns) else None
    matches = [] if columns is not None else [np.ascontiguousarray(p.matches) for p in pairs]
    own = {
        i: (p.keypoints1, p.keypoints2)
        for i, p in enumerate(() if columns is not None else pairs)
        if p.keypoints1 is not None or p.keypoints2 is not None
    }
    arrays = [a for i in flight.images.values() for a in (i.keypoints, i.descriptors)]
    arrays += [a for pair in own.values() for a in pair]
    if columns is not None:
        arrays.append(columns.matches)
    # where each array lies in the flight file (-1 or None: not a view of it)
    in_file = source.offsets(matches) if source is not None else np.full(len(matches), -1)
    present = [a for a in arrays if a is not None]
    at = source.offsets(present) if source is not None else np.full(len(present), -1)
    placed = {id(a): int(o) for a, o in zip(present, at, strict=True) if o >= 0}
    nbytes = np.fromiter((m.nbytes for m in matches), np.int64, len(matches))
    written = in_file < 0
    size = sum(a.nbytes + _ALIGN for a in arrays if a is not None and placed.get(id(a)) is None)
    size += int(nbytes[written].sum()) + _ALIGN * int(written.sum())
    with TemporaryDirectory(prefix="hmcc-flight-", dir=scratch_dir(size)) as folder:
        buffers: list[Any] = []  # what the arrays file holds, in order (padding included)
        offset = 0

        def put(a: np.ndarray | None) -> _Slot:
            nonlocal offset
            if a is None:
                return None
            at = placed.get(id(a))
            if at is not None:
                return (at, a.dtype.str, a.shape, True)
            pad = -offset % _ALIGN
            if pad:
                buffers.append(_PADDING[:pad])
                offset += pad
            a = np.ascontiguousarray(a)
            if a.nbytes:  # (an empty one has no bytes to write, and no view of them)
                buffers.append(a)
            slot = (offset, a.dtype.str, a.shape, False)
            offset += a.nbytes
            return slot

        images = {
            name: (image.camera, image.pose, put(image.keypoints), put(image.descriptors))
            for name, image in flight.images.items()
        }
        if columns is not None:
            table = _column_table(columns, put(columns.matches))
        else:
            own_slots = {i: (put(k1), put(k2)) for i, (k1, k2) in own.items()}
            # the matches not in the flight file, one after another, each at an aligned offset
            padded = -(-nbytes // _ALIGN) * _ALIGN
            padded[~written] = 0
            base = -(-offset // _ALIGN) * _ALIGN
            if base > offset:
                buffers.append(_PADDING[: base - offset])
            offsets = np.where(written, base + np.cumsum(padded) - padded, in_file)
            for m, n, room in zip(matches, nbytes.tolist(), padded.tolist(), strict=True):
                if room:
                    buffers.append(m)
                    if room > n:
                        buffers.append(_PADDING[: room - n])
            kinds: dict[str, int] = {}
            table = _PairTable(
                [p.image1 for p in pairs],
                [p.image2 for p in pairs],
                [p.id for p in pairs],
                np.fromiter((p.match for p in pairs), bool, len(pairs)),
                offsets,
                np.fromiter(map(len, matches), np.int64, len(matches)),
                np.fromiter((kinds.setdefault(m.dtype.str, len(kinds)) for m in matches), np.int16),
                list(kinds),
                ~written,
                own_slots,
            )
        with (Path(folder) / _ARRAYS).open("wb", buffering=0) as file:
            _write_all(file.fileno(), buffers)
        rest = (
            None if source is None else source.path,
            images,
            table,
            flight.method,
            flight.options,
            flight.plane_z,
            flight.ground_z,
            flight.match_options,
        )
        with (Path(folder) / _SKELETON).open("wb") as out:
            pickle.dump(rest, out, protocol=pickle.HIGHEST_PROTOCOL)
        yield SharedFlight(
            flight.images,
            flight.pairs,
            flight.method,
            flight.options,
            flight.plane_z,
            flight.ground_z,
            flight.match_options,
            folder=folder,
            indices=tuple(range(len(flight.pairs))),
        )


def _column_table(columns: PairColumns, slot: _Slot) -> _PairTable:
    """The table of pairs given as columns whose matches lie at ``slot``."""
    assert slot is not None
    at, dtype, _, in_source = slot
    n = len(columns)
    rows = np.arange(n) if columns.rows is None else columns.rows
    picked = columns.rows is not None
    starts = columns.starts
    ids = columns.ids
    return _PairTable(
        [columns.image1[k] for k in rows] if picked else list(columns.image1),
        [columns.image2[k] for k in rows] if picked else list(columns.image2),
        [None] * n if ids is None else [ids[k] for k in rows] if picked else list(ids),
        np.zeros(n, dtype=bool),
        at + starts[rows] * 2 * np.dtype(dtype).itemsize,
        starts[rows + 1] - starts[rows],
        np.zeros(n, dtype=np.int16),
        [dtype],
        np.full(n, in_source),
        {},
    )


class _Opened:
    """In a child: a flight's file opened, its pairs and images built as tasks name them (a
    child verifies its share of the pairs only; building every pair's views at the first
    task cost 0.45 CPU s a child on the 750-image benchmark flight)."""

    def __init__(self, folder: str) -> None:
        self.folder = folder
        with (Path(folder) / _SKELETON).open("rb") as f:
            source, images, table, *self.rest = pickle.load(f)
        self.table: _PairTable = table
        # Python numbers: a task's pairs are read one at a time
        self.offsets, self.rows = table.offset.tolist(), table.rows.tolist()
        self.kinds, self.in_source = table.dtype.tolist(), table.in_source.tolist()
        self.match = table.match.tolist()
        self.image_slots: dict[str, Any] = images
        self.images: dict[str, FlightImage] = {}
        # copy-on-write: the core gets writeable arrays, as unpickled ones are; pages shared
        self.data = _mapped(Path(folder) / _ARRAYS)
        self.source = _mapped(Path(source)) if source is not None else self.data

    def array(self, slot: _Slot, dtype: type | None = None) -> np.ndarray | None:
        """The array of ``slot`` (in ``dtype`` if given): one in the flight file copied out
        (there it lies unaligned, and the file is kept as it is), one in the arrays file a
        view of it."""
        if slot is None:
            return None
        offset, stored, shape, in_source = slot
        dt = np.dtype(stored)
        n = int(np.prod(shape)) * dt.itemsize
        data = self.source if in_source else self.data
        array = np.asarray(data[offset : offset + n]).view(dt).reshape(shape)
        if in_source:
            return array.astype(dtype or dt)
        return array if dtype is None else array.astype(dtype, copy=False)

    def pair(self, index: int) -> FlightPair:
        t = self.table
        slot = (
            self.offsets[index],
            t.dtypes[self.kinds[index]],
            (self.rows[index], 2),
            self.in_source[index],
        )
        matches = self.array(slot, np.int64)  # the parse's dtype, where read in place
        assert matches is not None  # a pair's matches are always written
        k1, k2 = t.own.get(index, (None, None))
        return FlightPair(
            t.image1[index],
            t.image2[index],
            matches,
            self.array(k1),
            self.array(k2),
            t.ids[index],
            self.match[index],
        )

    def image(self, name: str) -> FlightImage:
        image = self.images.get(name)
        if image is None:
            camera, pose, kps, desc = self.image_slots[name]
            image = self.images[name] = FlightImage(camera, pose, self.array(kps), self.array(desc))
        return image


def _mapped(path: Path) -> np.ndarray:
    """The bytes of ``path``, mapped copy-on-write (a file of none: an empty array)."""
    if not path.stat().st_size:
        return np.zeros(0, np.uint8)
    return np.memmap(path, dtype=np.uint8, mode="c")


# In a child: the flight last opened (a child works on one flight at a time).
_opened: _Opened | None = None


def open_shared(folder: str, indices: Sequence[int]) -> SharedFlight:
    """The flight of pairs ``indices`` of the flight written in ``folder`` (opened once per
    process), only the images they name."""
    global _opened
    if _opened is None or _opened.folder != folder:
        _opened = None  # the previous flight's mapping goes first
        _opened = _Opened(folder)
    pairs = [_opened.pair(i) for i in indices]
    names = {p.image1 for p in pairs} | {p.image2 for p in pairs}
    method, options, plane_z, ground_z, match_options = _opened.rest
    return SharedFlight(
        {name: _opened.image(name) for name in names},
        pairs,
        method,
        options,
        plane_z,
        ground_z,
        match_options,
        folder=folder,
        indices=tuple(indices),
    )
