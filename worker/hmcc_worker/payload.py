"""A :class:`hmcc.flight.Flight` as bytes, for the queue: a JSON header and raw array buffers.

The API validated the request once; a worker should not parse its numbers again. So a job's
input in Redis is::

    MAGIC | header length (uint32, little-endian) | header (JSON) | array buffers

The header holds the method, the options, the plane, each pair's ids, image names and number
of matches (all the pairs' matches are one array, a pair's are its rows of it), each image's
camera and rough pose, and each array's dtype and shape; the arrays follow as raw
little-endian buffers (keypoints float64, matches uint16 when every pair's came as uint16, else
int32, descriptors uint8 or float32 as given). A batch stores its images once
(:func:`encode_image`, one blob per image) and each chunk names the images it needs
(:func:`encode_flight` with ``images=False``); a single pair carries its images.

Nothing here is pickle: a payload is JSON and ``numpy.frombuffer``. :func:`decode_flight`
checks what it reads (the header's small structure with the contract's own pydantic models,
the arrays' shapes, finiteness and index ranges), so a payload that did not come from the API
fails with ``ValueError`` instead of reaching the core.
"""

from __future__ import annotations

import dataclasses
import struct
from collections.abc import Mapping
from typing import Any

import numpy as np
import orjson
from pydantic import TypeAdapter, ValidationError

from hmcc import METHODS, VerifyOptions
from hmcc.camera import Camera
from hmcc.flight import Flight, FlightImage, FlightPair, RoughPose
from hmcc.guided import GuidedOptions
from hmcc_schema.convert import to_camera
from hmcc_schema.models import MAX_KEYPOINTS, CameraModel, GeodeticPosition, RotationMatrix

__all__ = ["decode_flight", "decode_image", "encode_flight", "encode_image", "image_names"]

_FLIGHT = b"HMCCFLT1"
_IMAGE = b"HMCCIMG1"
_OPTIONS = TypeAdapter(VerifyOptions)
_MATCH_OPTIONS = TypeAdapter(GuidedOptions)
_KEYPOINTS, _MATCHES = np.dtype("<f8"), np.dtype("<i4")
#: Matches kept as uint16 when the body sent them so (the client's form while the indices stay
#: below 65 536): half the bytes of int32 through Redis. A worker older than this refuses such
#: a payload: the API and the workers are upgraded together.
_SMALL_MATCHES = np.dtype("<u2")
_DESCRIPTORS = (np.dtype("|u1"), np.dtype("<f4"))


class _Writer:
    """Collects arrays for the buffer section; returns each one's index for the header."""

    def __init__(self) -> None:
        self.arrays: list[np.ndarray] = []

    def add(self, array: np.ndarray | None, dtype: np.dtype) -> int | None:
        if array is None:
            return None
        self.arrays.append(np.ascontiguousarray(array, dtype=dtype))
        return len(self.arrays) - 1

    def pack(self, magic: bytes, header: dict[str, Any]) -> bytes:
        header["arrays"] = [[a.dtype.str, list(a.shape)] for a in self.arrays]
        head = orjson.dumps(header)
        return b"".join([magic, struct.pack("<I", len(head)), head, *(a.data for a in self.arrays)])


def _unpack(data: bytes, magic: bytes) -> tuple[dict[str, Any], list[np.ndarray]]:
    if not data.startswith(magic):
        raise ValueError("not an hmcc payload of this kind")
    start = len(magic) + 4
    (size,) = struct.unpack_from("<I", data, len(magic))
    header = orjson.loads(data[start : start + size])
    offset, arrays = start + size, []
    for spec in header.get("arrays", []):
        dtype_str, shape = spec
        dtype = np.dtype(dtype_str)
        if dtype not in (_KEYPOINTS, _MATCHES, _SMALL_MATCHES, *_DESCRIPTORS) or not (
            isinstance(shape, list)
            and len(shape) == 2
            and all(isinstance(n, int) and 0 <= n <= 10**8 for n in shape)
        ):
            raise ValueError("payload arrays do not match their header")
        count = shape[0] * shape[1]
        if offset + count * dtype.itemsize > len(data):
            raise ValueError("payload arrays do not match their header")
        arrays.append(np.frombuffer(data, dtype=dtype, count=count, offset=offset).reshape(shape))
        offset += count * dtype.itemsize
    if offset != len(data):
        raise ValueError("payload arrays do not match their header")
    return header, arrays


# --------------------------------------------------------------------------- images


def _image_header(image: FlightImage, writer: _Writer) -> dict[str, Any]:
    c, p = image.camera, image.pose
    return {
        "camera": {
            "width": c.width,
            "height": c.height,
            "fx": c.fx,
            "fy": c.fy,
            "cx": c.cx,
            "cy": c.cy,
            "distortion": None if c.distortion is None else list(c.distortion),
        },
        "pose": None
        if p is None
        else {
            "R": p.R_world_to_cam.tolist(),
            "position": p.position.tolist(),
            "geodetic": p.geodetic,
            "lever_arm": None if p.lever_arm is None else p.lever_arm.tolist(),
            "R_ned_body": None if p.R_ned_body is None else p.R_ned_body.tolist(),
        },
        "keypoints": writer.add(image.keypoints, _KEYPOINTS),
        "descriptors": None
        if image.descriptors is None
        else writer.add(image.descriptors, image.descriptors.dtype.newbyteorder("<")),
    }


def encode_image(image: FlightImage) -> bytes:
    """One image (camera, rough pose, keypoints) as a blob of its own."""
    writer = _Writer()
    return writer.pack(_IMAGE, {"image": _image_header(image, writer)})


def decode_image(data: bytes) -> FlightImage:
    header, arrays = _unpack(data, _IMAGE)
    return _read_image(header["image"], arrays)


def _read_image(head: dict[str, Any], arrays: list[np.ndarray]) -> FlightImage:
    try:
        camera: Camera = to_camera(CameraModel.model_validate(head["camera"]))
    except (ValidationError, KeyError, TypeError, ValueError) as e:
        raise ValueError(f"payload image is not valid: {e}") from None
    rough = None if head.get("pose") is None else _read_pose(head["pose"])
    keypoints = _keypoints(arrays, head.get("keypoints"))
    descriptors = None
    if head.get("descriptors") is not None:
        descriptors = arrays[head["descriptors"]]
        if (
            descriptors.dtype not in _DESCRIPTORS
            or keypoints is None
            or len(descriptors) != len(keypoints)
            or not (descriptors.dtype.kind == "u" or np.isfinite(descriptors).all())
        ):
            raise ValueError("payload descriptors are not (N, D) rows of the keypoints")
    return FlightImage(camera, rough, keypoints, descriptors)


def _read_pose(pose: Any) -> RoughPose:
    try:
        rotation = np.asarray(RotationMatrix.model_validate({"matrix": pose["R"]}).matrix)
        position = np.asarray(pose["position"], dtype=np.float64).reshape(3)
        if pose["geodetic"]:
            GeodeticPosition.model_validate(dict(zip(("lat", "lon", "alt"), position, strict=True)))
        lever = pose["lever_arm"]
        body = pose["R_ned_body"]
        rough = RoughPose(
            rotation,
            position,
            bool(pose["geodetic"]),
            None if lever is None else np.asarray(lever, dtype=np.float64).reshape(3),
            None
            if body is None
            else np.asarray(RotationMatrix.model_validate({"matrix": body}).matrix),
        )
    except (ValidationError, KeyError, TypeError, ValueError) as e:
        raise ValueError(f"payload image is not valid: {e}") from None
    if not np.isfinite(rough.position).all() or (
        rough.lever_arm is not None and not np.isfinite(rough.lever_arm).all()
    ):
        raise ValueError("payload image is not valid: non-finite position")
    return rough


# --------------------------------------------------------------------------- flights


def encode_flight(flight: Flight, *, images: bool = True) -> bytes:
    """A flight as a payload; with ``images=False`` only the names of its images (a chunk of a
    batch whose images are stored once, see :func:`encode_image`)."""
    writer = _Writer()
    # every pair's matches in one array (one conversion, one buffer), each pair its rows
    small = all(p.matches.dtype == np.uint16 for p in flight.pairs)
    dtype = _SMALL_MATCHES if small else _MATCHES
    flat = (
        np.concatenate([p.matches for p in flight.pairs], dtype=dtype, casting="unsafe")
        if flight.pairs
        else np.zeros((0, 2), dtype=dtype)
    )
    all_matches = writer.add(flat, dtype)
    pairs = [
        {
            "id": p.id,
            "image1": p.image1,
            "image2": p.image2,
            "rows": len(p.matches),
            "keypoints1": writer.add(p.keypoints1, _KEYPOINTS),
            "keypoints2": writer.add(p.keypoints2, _KEYPOINTS),
            "match": p.match,
        }
        for p in flight.pairs
    ]
    header: dict[str, Any] = {
        "method": flight.method,
        "options": _option_dict(flight.options),
        "match_options": dataclasses.asdict(flight.match_options),
        "plane_z": flight.plane_z,
        "ground_z": flight.ground_z,
        "matches": all_matches,
        "pairs": pairs,
    }
    if images:
        header["images"] = {n: _image_header(im, writer) for n, im in flight.images.items()}
    else:
        header["image_names"] = sorted(flight.images)
    return writer.pack(_FLIGHT, header)


def image_names(data: bytes) -> list[str]:
    """The names of the images a chunk payload refers to (empty when it carries them)."""
    header, _ = _unpack(data, _FLIGHT)
    return list(header.get("image_names", []))


def decode_flight(data: bytes, images: Mapping[str, FlightImage] | None = None) -> Flight:
    """The flight of a payload; ``images`` supplies those a chunk only names. Raises
    ``ValueError`` for a payload that is not a valid one."""
    header, arrays = _unpack(data, _FLIGHT)
    try:
        method = header["method"]
        if method not in METHODS:
            raise ValueError(f"unknown method {method!r}")
        options = _OPTIONS.validate_python(header["options"])
        match_options = _MATCH_OPTIONS.validate_python(header.get("match_options", {}))
        if "images" in header:
            flight_images = {n: _read_image(h, arrays) for n, h in header["images"].items()}
        else:
            missing = [n for n in header["image_names"] if images is None or n not in images]
            if missing:
                raise ValueError(f"images missing: {missing[:3]}")
            assert images is not None
            flight_images = {n: images[n] for n in header["image_names"]}
        heads = header["pairs"]
        pairs = [
            _read_pair(p, arrays, flight_images, m)
            for p, m in zip(heads, _pair_matches(header, heads, arrays), strict=True)
        ]
        plane_z, ground_z = header["plane_z"], header["ground_z"]
        for z in (plane_z, ground_z):
            if z is not None and not (isinstance(z, int | float) and np.isfinite(z)):
                raise ValueError("plane is not finite")
    except (ValidationError, KeyError, TypeError, IndexError) as e:
        raise ValueError(f"payload is not valid: {e}") from None
    return Flight(flight_images, pairs, method, options, plane_z, ground_z, match_options)


def _pair_matches(
    header: dict[str, Any], heads: list[dict[str, Any]], arrays: list[np.ndarray]
) -> list[np.ndarray]:
    """Each pair's matches: its ``rows`` of the flight's one matches array (or, in a payload
    written before that array, an array of its own)."""
    if header.get("matches") is None:
        return [arrays[p["matches"]] for p in heads]
    flat = arrays[header["matches"]]
    rows = [p["rows"] for p in heads]
    if not all(type(n) is int and n >= 0 for n in rows) or sum(rows) != len(flat):
        raise ValueError("payload matches do not add up to the pairs' rows")
    ends = np.cumsum(rows).tolist()
    return [flat[end - n : end] for n, end in zip(rows, ends, strict=True)]


def _read_pair(
    head: dict[str, Any],
    arrays: list[np.ndarray],
    images: Mapping[str, FlightImage],
    matches: np.ndarray,
) -> FlightPair:
    match = head.get("match", False) is True
    if (
        matches.dtype not in (_MATCHES, _SMALL_MATCHES)
        or matches.shape[1] != 2
        or bool(len(matches)) == match
    ):
        raise ValueError("payload matches are not (M, 2) indices")
    kp1 = _keypoints(arrays, head["keypoints1"])
    kp2 = _keypoints(arrays, head["keypoints2"])
    if match:
        if (
            kp1 is not None
            or kp2 is not None
            or any(images[n].descriptors is None for n in (head["image1"], head["image2"]))
        ):
            raise ValueError("a pair to match has no descriptors for one of its images")
        return FlightPair(
            head["image1"], head["image2"], matches.astype(np.int64), None, None, head["id"], True
        )
    sides = ((head["image1"], kp1), (head["image2"], kp2))
    for col, (name, own) in enumerate(sides):
        keypoints = own if own is not None else images[name].keypoints
        if keypoints is None:
            raise ValueError("a pair has no keypoints for one of its images")
        if matches[:, col].min() < 0 or matches[:, col].max() >= len(keypoints):
            raise ValueError("payload match indices out of range")
    return FlightPair(
        head["image1"], head["image2"], matches.astype(np.int64), kp1, kp2, head["id"]
    )


def _keypoints(arrays: list[np.ndarray], index: int | None) -> np.ndarray | None:
    if index is None:
        return None
    kps = arrays[index]
    if kps.dtype != _KEYPOINTS or kps.shape[1] not in (2, 4) or not 0 < len(kps) <= MAX_KEYPOINTS:
        raise ValueError("payload keypoints are not (N, 2|4)")
    if not np.isfinite(kps).all():
        raise ValueError("payload keypoints are not finite")
    return kps


def _option_dict(options: VerifyOptions) -> dict[str, Any]:
    return dataclasses.asdict(options)
