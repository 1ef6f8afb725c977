"""A flight's keypoints sent to the compute pool's children through a file, not with each task.

Every task of :meth:`ComputePool.map_flight` pickles the images its pairs name, keypoints and
all: some 2.5 MB a task on the Brighton database, pushed through the pool's pipe while the
child waits (8-10 ms a task on a loaded 2-core machine, 0.3 ms for a task without them). Here
the flight's keypoints are written once to a file (in memory where there is room:
:func:`scratch_dir`) and each image pickles as its camera, its pose and where its keypoints lie
in that file; the child maps them from the page cache (copy-on-write: an array of its own, as
unpickling gives).

Light on purpose (no pycolmap): the pool's children import this module with their first task.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from tempfile import TemporaryDirectory
from typing import Any

import numpy as np

from hmcc.flight import Flight, FlightImage

__all__ = ["keypoints_in_file", "scratch_dir"]


@dataclasses.dataclass(frozen=True)
class _FiledImage(FlightImage):
    """A :class:`FlightImage` whose keypoints pickle as their place in ``path``."""

    path: str = ""
    offset: int = 0

    def __reduce__(self) -> tuple[Any, ...]:
        assert self.keypoints is not None
        shape = self.keypoints.shape
        return _read_image, (self.camera, self.pose, self.path, self.offset, shape)


def _read_image(
    camera: Any, pose: Any, path: str, offset: int, shape: tuple[int, ...]
) -> FlightImage:
    # mapped, not read: unpickling holds the pool's channel (no other child takes a task or
    # sends a result meanwhile), so the pages are read later, by the verification, and only
    # those of the matched keypoints; copy-on-write, so the array is writeable like a read one
    mapped = np.memmap(path, dtype=np.float64, mode="c", offset=offset, shape=shape)
    return FlightImage(camera, pose, np.asarray(mapped))


@contextmanager
def keypoints_in_file(flight: Flight) -> Iterator[Flight]:
    """``flight`` whose images' keypoints pickle as a place in a file (written here, removed
    at the end); images without keypoints, and pairs, pickle as they are."""
    size = sum(i.keypoints.nbytes for i in flight.images.values() if i.keypoints is not None)
    with TemporaryDirectory(prefix="hmcc-keypoints-", dir=scratch_dir(size)) as folder:
        path = Path(folder) / "keypoints.f64"
        images: dict[str, FlightImage] = {}
        offset = 0
        with path.open("wb") as out:
            for name, image in flight.images.items():
                kps = image.keypoints
                if kps is None or kps.dtype != np.float64:
                    images[name] = image
                    continue
                kps = np.ascontiguousarray(kps)
                out.write(kps.data)
                images[name] = _FiledImage(
                    image.camera, image.pose, kps, path=str(path), offset=offset
                )
                offset += kps.nbytes
        yield dataclasses.replace(flight, images=images)


#: Memory-backed, where there is one (Linux).
_MEMORY_DIR = Path("/dev/shm")


def scratch_dir(size: int) -> str | None:
    """Where the keypoints file goes: the memory-backed :data:`_MEMORY_DIR` when it has twice
    ``size`` bytes free (a container's is often 64 MB), else the temporary directory (None).

    A file on disk is written into the page cache too, but behind the database's own writes
    and whatever else is being flushed: 6.7 ms for the Brighton keypoints (3.4 MB) after a
    copy of the database, against 1.0 ms on an idle disk and 1.8 ms in memory."""
    try:
        stats = os.statvfs(_MEMORY_DIR)
    except OSError:
        return None
    free = stats.f_bavail * stats.f_frsize
    return str(_MEMORY_DIR) if free >= 2 * size and os.access(_MEMORY_DIR, os.W_OK) else None
