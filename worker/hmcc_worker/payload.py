"""The job input between API and worker, binary: validated once by the API, not re-parsed.

Parsing the numbers of a pair's JSON is most of a worker's non-compute time (~1.2 ms per
1 000 matches), and the API has just done it. So the RQ queue stores each job's request as::

    MAGIC | header length (uint32, little-endian) | header (JSON) | array buffers

The header is the request without its arrays (cameras, poses, plane, method, params; for a
batch chunk also each pair's id and image ids) plus each array's dtype and shape; the arrays
follow as raw little-endian buffers (``keypoints1``, ``keypoints2``, ``matches`` of each pair,
in order). Nothing here is pickle: a payload is bytes read by ``numpy.frombuffer`` and JSON.
:func:`decode` re-validates the header with the same pydantic models and checks the arrays'
shapes, finiteness and index ranges, so a payload that did not come from the API fails
cleanly.
"""

from __future__ import annotations

import json
import struct
from typing import Any

import numpy as np

from hmcc.schema import BatchRequest, PairRequest

__all__ = ["MAGIC", "decode", "encode"]

MAGIC = b"HMCCBIN1"
_ARRAYS = ("keypoints1", "keypoints2", "matches")
_DTYPES = {"keypoints1": "<f8", "keypoints2": "<f8", "matches": "<i8"}
_PLACEHOLDER = {"keypoints1": [[0.0, 0.0]], "keypoints2": [[0.0, 0.0]], "matches": [[0, 0]]}


def _arrays(item: Any) -> list[np.ndarray]:
    return [np.asarray(getattr(item, name), dtype=_DTYPES[name]) for name in _ARRAYS]


def encode(request: PairRequest | BatchRequest) -> bytes:
    """A validated request as a binary payload."""
    if isinstance(request, PairRequest):
        kind = "pair"
        fields = request.model_dump(mode="json", exclude={*_ARRAYS, "ground_truth"})
        arrays = _arrays(request)
    else:
        kind = "chunk"
        fields = request.model_dump(mode="json", exclude={"pairs": {"__all__": set(_ARRAYS)}})
        arrays = [a for pair in request.pairs for a in _arrays(pair)]
    header = json.dumps(
        {"kind": kind, "request": fields, "arrays": [list(a.shape) for a in arrays]}
    ).encode()
    return b"".join(
        [MAGIC, struct.pack("<I", len(header)), header, *(a.tobytes() for a in arrays)]
    )


def decode(data: bytes) -> PairRequest | BatchRequest:
    """The request back; raises ``ValueError`` (or pydantic's) for a payload that is not one."""
    if not data.startswith(MAGIC):
        raise ValueError("not an hmcc binary payload")
    start = len(MAGIC) + 4
    (size,) = struct.unpack_from("<I", data, len(MAGIC))
    header = json.loads(data[start:start + size])
    offset = start + size
    arrays: list[np.ndarray] = []
    for i, shape in enumerate(header["arrays"]):
        dtype = np.dtype(_DTYPES[_ARRAYS[i % 3]])
        if not (isinstance(shape, list) and len(shape) == 2
                and all(isinstance(n, int) and n >= 0 for n in shape)):
            raise ValueError("payload arrays do not match their header")
        count = shape[0] * shape[1]
        if offset + count * dtype.itemsize > len(data):
            raise ValueError("payload arrays do not match their header")
        array = np.frombuffer(data, dtype=dtype, count=count, offset=offset).reshape(shape)
        offset += count * dtype.itemsize
        arrays.append(array)
    if offset != len(data) or len(arrays) % 3:
        raise ValueError("payload arrays do not match their header")
    groups = [dict(zip(_ARRAYS, arrays[i:i + 3], strict=True)) for i in range(0, len(arrays), 3)]
    for group in groups:
        _check(group)
    fields = header["request"]
    if header["kind"] == "pair":
        if len(groups) != 1:
            raise ValueError("a pair payload has one set of arrays")
        pair = PairRequest.model_validate({**fields, **_PLACEHOLDER})
        return pair.model_copy(update=groups[0])
    pairs = fields.get("pairs")
    if not isinstance(pairs, list) or len(pairs) != len(groups):
        raise ValueError("a chunk payload has one set of arrays per pair")
    fields["pairs"] = [{**p, **_PLACEHOLDER} for p in pairs]
    chunk = BatchRequest.model_validate(fields)
    return chunk.model_copy(
        update={"pairs": [p.model_copy(update=g) for p, g in zip(chunk.pairs, groups, strict=True)]}
    )


def _check(group: dict[str, np.ndarray]) -> None:
    """What the schema checked at the API, again, vectorised."""
    kp1, kp2, matches = group["keypoints1"], group["keypoints2"], group["matches"]
    for kps in (kp1, kp2):
        if kps.ndim != 2 or kps.shape[1] not in (2, 4) or not len(kps):
            raise ValueError("keypoints must be (N, 2) or (N, 4), N >= 1")
        if not np.isfinite(kps).all():
            raise ValueError("keypoints must be finite")
    if matches.ndim != 2 or matches.shape[1] != 2 or not len(matches):
        raise ValueError("matches must be (M, 2), M >= 1")
    if matches.min() < 0 or matches[:, 0].max() >= len(kp1) or matches[:, 1].max() >= len(kp2):
        raise ValueError("match indices out of range")
