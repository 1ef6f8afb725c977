"""Request bodies -> the core's :class:`hmcc.flight.Flight`: validated once, arrays once.

A body is parsed with orjson, its structure (cameras, poses, plane, method, params) validated
by the pydantic models of :mod:`hmcc_schema.models`, and its keypoints and matches converted
straight into numpy arrays and checked vectorised: shape, finiteness, index ranges. That is
the whole cost for a valid body; per-number validation in pydantic would cost more than the
verification itself.

Anything the fast path does not accept goes through the full pydantic model instead, which
says what is wrong (the same field paths and reasons whatever the input) and, where its lax
rules accept what the fast path did not (numbers given as strings, say), gives the values.
Checks across fields follow in both cases and raise :class:`hmcc.InputError`.

A single pair becomes a flight of two images, ``image1`` and ``image2``, and one pair.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import orjson
from pydantic import TypeAdapter, ValidationError

from hmcc import InputError
from hmcc.flight import Flight, FlightImage, FlightPair

from .convert import check_in_frame, to_image, to_plane
from .issues import clip
from .models import (
    MAX_BATCH_IMAGES,
    MAX_KEYPOINTS,
    MAX_MATCHES,
    BatchRequest,
    ImageModel,
    PairRequest,
    _BatchFields,
    _BatchPairFields,
    _PairFields,
)

__all__ = ["PAIR_IMAGES", "parse_batch", "parse_pair"]

#: The image ids of a single pair's flight.
PAIR_IMAGES = ("image1", "image2")
_PAIR_ARRAYS = ("keypoints1", "keypoints2", "matches")
_IMAGES = TypeAdapter(dict[str, ImageModel])
_PAIR_HEADS = TypeAdapter(list[_BatchPairFields])

#: JSON text, or what a JSON parser made of it.
Body = bytes | str | Any


def parse_pair(body: Body) -> Flight:
    """A pair request (JSON text, or the object a JSON parser made of it) as a flight of one
    pair.

    Raises pydantic's ``ValidationError`` or :class:`InputError` naming what is wrong.
    """
    doc = _load(body)
    flight = _fast_pair(doc) if isinstance(doc, dict) else None
    if flight is None:
        model = _full(PairRequest, body)
        kp1, kp2 = _array(model.keypoints1, np.float64), _array(model.keypoints2, np.float64)
        flight = _pair_flight(model, kp1, kp2, _array(model.matches, np.int64))
    return flight


def parse_batch(body: Body, max_pairs: int) -> Flight:
    """A batch request as a flight; at most ``max_pairs`` pairs (an :class:`InputError` on
    ``pairs`` above). Raises pydantic's ``ValidationError`` or :class:`InputError`."""
    doc = _load(body)
    if isinstance(doc, dict) and isinstance(doc.get("pairs"), list):
        _check_count(len(doc["pairs"]), max_pairs)
    flight = _fast_batch(doc) if isinstance(doc, dict) else None
    if flight is None:
        model = _full(BatchRequest, body)
        _check_count(len(model.pairs), max_pairs)
        images = {
            name: to_image(image, _optional(image.keypoints, np.float64), f"images.{name}")
            for name, image in model.images.items()
        }
        pairs = [
            FlightPair(
                p.image1,
                p.image2,
                _array(p.matches, np.int64),
                _optional(p.keypoints1, np.float64),
                _optional(p.keypoints2, np.float64),
                p.id,
            )
            for p in model.pairs
        ]
        flight = _batch_flight(model, images, pairs)
    _check_pairs(flight)
    return flight


# --------------------------------------------------------------------------- fast path


def _fast_pair(doc: dict[str, Any]) -> Flight | None:
    try:
        fields = _PairFields.model_validate({k: v for k, v in doc.items() if k not in _PAIR_ARRAYS})
    except ValidationError:
        return None
    kp1, kp2 = _keypoints(doc.get("keypoints1")), _keypoints(doc.get("keypoints2"))
    if kp1 is None or kp2 is None:
        return None
    matches = _matches(doc.get("matches"), len(kp1), len(kp2))
    return None if matches is None else _pair_flight(fields, kp1, kp2, matches)


def _fast_batch(doc: dict[str, Any]) -> Flight | None:
    images_doc, pairs_doc = doc.get("images"), doc.get("pairs")
    if not (isinstance(images_doc, dict) and 1 <= len(images_doc) <= MAX_BATCH_IMAGES):
        return None
    if not (isinstance(pairs_doc, list) and pairs_doc):
        return None
    if not all(isinstance(v, dict) for v in (*images_doc.values(), *pairs_doc)):
        return None
    try:
        fields = _BatchFields.model_validate(
            {k: v for k, v in doc.items() if k not in ("images", "pairs")}
        )
        image_models = _IMAGES.validate_python(
            {
                name: {k: v for k, v in image.items() if k != "keypoints"}
                for name, image in images_doc.items()
            }
        )
        heads = _PAIR_HEADS.validate_python(
            [{k: v for k, v in p.items() if k not in _PAIR_ARRAYS} for p in pairs_doc]
        )
    except ValidationError:
        return None
    images = {}
    for name, model in image_models.items():
        raw = images_doc[name].get("keypoints")
        keypoints = None if raw is None else _keypoints(raw)
        if raw is not None and keypoints is None:
            return None
        images[name] = to_image(model, keypoints, f"images.{name}")
    pairs = []
    for head, raw in zip(heads, pairs_doc, strict=True):
        own = [raw.get("keypoints1"), raw.get("keypoints2")]
        kps = [None if k is None else _keypoints(k) for k in own]
        if any(k is not None and a is None for k, a in zip(own, kps, strict=True)):
            return None
        # The range check against the pair's own keypoints belongs to this path (the model
        # checks it too); against an image's keypoints it is a check across fields (below).
        limits = [len(a) if a is not None else MAX_KEYPOINTS for a in kps]
        matches = _matches(raw.get("matches"), *limits)
        if matches is None:
            return None
        pairs.append(FlightPair(head.image1, head.image2, matches, kps[0], kps[1], head.id))
    return _batch_flight(fields, images, pairs)


def _keypoints(value: Any) -> np.ndarray | None:
    """(N, 2|4) float64 of a JSON keypoint list, or None when it is not plainly one."""
    if not isinstance(value, list) or not 0 < len(value) <= MAX_KEYPOINTS:
        return None
    try:
        a = np.array(value)
    except (ValueError, TypeError):  # rows of different lengths
        return None
    if a.dtype.kind not in "if" or a.ndim != 2 or a.shape[1] not in (2, 4):
        return None
    a = a.astype(np.float64, copy=False)
    return a if np.isfinite(a).all() else None


def _matches(value: Any, n1: int, n2: int) -> np.ndarray | None:
    """(M, 2) int64 of a JSON match list whose indices fall within ``n1`` / ``n2`` keypoints,
    or None when it is not plainly one."""
    if not isinstance(value, list) or not 0 < len(value) <= MAX_MATCHES:
        return None
    try:
        a = np.array(value)
    except (ValueError, TypeError, OverflowError):
        return None
    if a.dtype.kind != "i" or a.ndim != 2 or a.shape[1] != 2:
        return None
    a = a.astype(np.int64, copy=False)
    if a.min() < 0 or a[:, 0].max() >= n1 or a[:, 1].max() >= n2:
        return None
    return a


# --------------------------------------------------------------------------- both paths


def _load(body: Body) -> Any:
    """The parsed JSON, or None when orjson refuses it (the full model then says why: it also
    reads ``NaN``/``Infinity``, which it refuses field by field)."""
    if not isinstance(body, bytes | str):
        return body
    try:
        return orjson.loads(body)
    except orjson.JSONDecodeError:
        return None


def _full(model: type[Any], body: Body) -> Any:
    """The full model's validation: raises ``ValidationError`` naming every problem."""
    if isinstance(body, bytes | str):
        return model.model_validate_json(body)
    return model.model_validate(body)


def _array(value: Any, dtype: type) -> np.ndarray:
    return np.asarray(value, dtype=dtype)


def _optional(value: Any, dtype: type) -> np.ndarray | None:
    return None if value is None else np.asarray(value, dtype=dtype)


def _check_count(n: int, max_pairs: int) -> None:
    if n > max_pairs:
        raise InputError("pairs", f"{n} pairs; at most {max_pairs} per batch")


def _pair_flight(
    fields: _PairFields, kp1: np.ndarray, kp2: np.ndarray, matches: np.ndarray
) -> Flight:
    plane_z, ground_z = to_plane(fields.plane)
    images = {
        PAIR_IMAGES[0]: to_image(fields.image1, field=PAIR_IMAGES[0]),
        PAIR_IMAGES[1]: to_image(fields.image2, field=PAIR_IMAGES[1]),
    }
    check_in_frame(images[PAIR_IMAGES[0]].camera, kp1, "keypoints1", PAIR_IMAGES[0])
    check_in_frame(images[PAIR_IMAGES[1]].camera, kp2, "keypoints2", PAIR_IMAGES[1])
    pair = FlightPair(PAIR_IMAGES[0], PAIR_IMAGES[1], matches.reshape(-1, 2), kp1, kp2)
    return Flight(images, [pair], fields.method, fields.params, plane_z, ground_z)


def _batch_flight(
    fields: _BatchFields, images: dict[str, FlightImage], pairs: list[FlightPair]
) -> Flight:
    plane_z, ground_z = to_plane(fields.plane)
    return Flight(images, pairs, fields.method, fields.params, plane_z, ground_z)


def _check_pairs(flight: Flight) -> None:
    """Every pair names images of the batch, has keypoints for both sides (its own or its
    image's) and indices within them; raises :class:`InputError` on the first that does not."""
    for i, pair in enumerate(flight.pairs):
        for side, name, own in (
            (1, pair.image1, pair.keypoints1),
            (2, pair.image2, pair.keypoints2),
        ):
            image = flight.images.get(name)
            if image is None:
                raise InputError(f"pairs[{i}].image{side}", f"no image {clip(name)!r} in images")
            if own is not None:
                check_in_frame(image.camera, own, f"pairs[{i}].keypoints{side}", f"images.{name}")
                continue
            if image.keypoints is None:
                raise InputError(
                    f"pairs[{i}].keypoints{side}",
                    f"give the pair's keypoints{side} or images.{name}.keypoints",
                )
            column = pair.matches[:, side - 1]
            bad = np.flatnonzero(column >= len(image.keypoints))
            if len(bad):
                k = int(bad[0])
                raise InputError(
                    f"pairs[{i}].matches",
                    f"matches[{k}][{side - 1}] = {column[k]} is out of range: "
                    f"images.{name} has {len(image.keypoints)} keypoints",
                )
