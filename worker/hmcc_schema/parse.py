"""Request bodies -> the core's :class:`hmcc.flight.Flight`: validated once, arrays once.

Keypoints and matches go straight into numpy arrays and are checked vectorised (shape,
finiteness, index ranges); the rest of a body (cameras, poses, plane, method, params) is
validated by the pydantic models of :mod:`hmcc_schema.models`. That is the whole cost of a
valid body: per-number validation in pydantic, or even building a Python object per number
(orjson), would cost more than the verification itself.

Three encodings of the same body:

* JSON (``application/json``, the contract): parsed with simdjson, whose arrays of numbers are
  read as flat buffers (``as_buffer``), with each row's length checked;
* MessagePack (``application/vnd.hmcc+msgpack``), where an array may also be given as
  ``{"dtype": "<f8", "shape": [n, 2], "data": <bytes>}`` (little-endian float32/64 keypoints,
  int32/64 or uint16/32 matches): read without copying;
* an already parsed object (the command line, library callers), arrays as lists or ndarrays.

A pairs request (:func:`parse_pairs`: images' cameras and poses, no arrays) goes through its
model alone.

A body nested deeper than :data:`MAX_DEPTH` arrays and objects is refused in every encoding:
pydantic's JSON parser stops there, and MessagePack (or an already parsed object) is refused
with the same reason (a 422 naming ``body``), before anything walks it.

Anything the fast path does not accept goes through the full pydantic model instead (JSON text
in JSON mode), which says what is wrong (the same field paths and reasons whatever the input)
and, where its lax rules accept what the fast path did not (numbers given as strings, say),
gives the values. Checks across fields follow in both cases and raise :class:`hmcc.InputError`.

A single pair becomes a flight of two images, ``image1`` and ``image2``, and one pair.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sized
from dataclasses import dataclass
from itertools import chain
from typing import TYPE_CHECKING, Any, NamedTuple, cast

import msgpack
import numpy as np
import simdjson
from pydantic import BaseModel, TypeAdapter, ValidationError

from hmcc import InputError
from hmcc.flight import Flight, FlightImage, FlightPair
from hmcc.method_names import POS_METHODS
from hmcc.stage_options import PairOptions

if TYPE_CHECKING:
    from hmcc.footprint import FlightPairs

from .convert import check_in_frame, descriptor_array, to_image, to_plane
from .issues import clip
from .models import (
    MAX_BATCH_IMAGES,
    MAX_DESCRIPTOR_LENGTH,
    MAX_KEYPOINTS,
    MAX_MATCHES,
    BatchImage,
    BatchRequest,
    PairRequest,
    PairsRequest,
    _BatchFields,
    _BatchPairFields,
    _PairFields,
)

__all__ = [
    "JSON",
    "MAX_DEPTH",
    "MSGPACK",
    "PAIR_IMAGES",
    "PairsQuery",
    "parse_batch",
    "parse_pair",
    "parse_pairs",
]

#: The image ids of a single pair's flight.
PAIR_IMAGES = ("image1", "image2")
#: Media types of a body.
JSON = "application/json"
MSGPACK = "application/vnd.hmcc+msgpack"

#: Arrays and objects nested at most this deep: the recursion limit of pydantic's JSON parser
#: (jiter), which says "recursion limit exceeded" past it; MessagePack is held to the same.
MAX_DEPTH = 200

_PAIR_ARRAYS = ("keypoints1", "keypoints2", "matches")
_IMAGES = TypeAdapter(dict[str, BatchImage])
_PAIR_HEADS = TypeAdapter(list[_BatchPairFields])
#: The keys of a batch's pair, and the longest id or image id (:class:`_BatchPairFields`).
_PAIR_KEYS = frozenset({"id", "image1", "image2", "match", *_PAIR_ARRAYS})
_MAX_NAME = 200
_BUFFER_DTYPES = {
    "keypoints": {"<f4", "<f8"},
    "matches": {"<i4", "<i8", "<u2", "<u4"},
    "descriptors": {"|u1", "<f4"},
}
_BUFFER_KEYS = frozenset({"dtype", "shape", "data"})
_DTYPES = {name: np.dtype(name) for names in _BUFFER_DTYPES.values() for name in names}
#: A matching pair's matches until it is matched.
_NO_MATCHES = np.zeros((0, 2), dtype=np.int64)


class _PairHead(NamedTuple):
    """A pair's fields besides its arrays, checked by :func:`_plain_heads`."""

    id: str | None
    image1: str
    image2: str
    match: bool


@dataclass
class _Unread:
    """An array the fast path could not read (the full model will say why)."""

    raw: Any


def parse_pair(body: Any, media_type: str = JSON) -> Flight:
    """A pair request as a flight of one pair. ``body``: JSON text (or MessagePack bytes, as
    ``media_type`` says), or the object a parser made of it.

    Raises pydantic's ``ValidationError`` or :class:`InputError` naming what is wrong.
    """
    doc = _load(body, media_type, _pair_arrays)
    flight = _fast_pair(doc) if isinstance(doc, dict) else None
    if flight is None:
        model = _full(PairRequest, body, media_type)
        kp1, kp2 = _array(model.keypoints1, np.float64), _array(model.keypoints2, np.float64)
        flight = _pair_flight(model, kp1, kp2, _array(model.matches, np.int64))
    return flight


def parse_batch(
    body: Any, max_pairs: int, media_type: str = JSON, *, views: bool = False
) -> Flight:
    """A batch request as a flight; at most ``max_pairs`` pairs (an :class:`InputError` on
    ``pairs`` above). Raises pydantic's ``ValidationError`` or :class:`InputError`.

    ``views``: each pair's matches as read (a view of its buffer, in its own dtype, when the
    body carries buffers), not slices of one int64 array of all the pairs' matches: for a
    flight whose buffers are views of a mapped file (:mod:`hmcc_schema.flight_file`), or a
    batch the service packs or shares for its workers at once, so that nothing of the
    matches is copied but their check (the core wants int64 matches: whoever verifies such a
    flight converts them)."""
    doc = _load(body, media_type, _batch_arrays)
    if isinstance(doc, dict) and isinstance(doc.get("pairs"), list):
        _check_count(len(doc["pairs"]), max_pairs)
    fast = _fast_batch(doc, views) if isinstance(doc, dict) else None
    if fast is not None:
        flight, maxima = fast
    else:
        model = _full(BatchRequest, body, media_type)
        _check_count(len(model.pairs), max_pairs)
        images = {
            name: to_image(
                image,
                _optional(image.keypoints, np.float64),
                f"images.{name}",
                _full_descriptors(image.descriptors, f"images.{name}.descriptors"),
            )
            for name, image in model.images.items()
        }
        pairs = [
            FlightPair(
                p.image1,
                p.image2,
                _NO_MATCHES if p.matches is None else _array(p.matches, np.int64),
                _optional(p.keypoints1, np.float64),
                _optional(p.keypoints2, np.float64),
                p.id,
                p.match,
            )
            for p in model.pairs
        ]
        flight = _batch_flight(model, images, pairs)
        maxima = _full_maxima(pairs)
    _check_pairs(flight, maxima)
    return flight


@dataclass(frozen=True)
class PairsQuery:
    """A pairs request, validated: each image's camera and rough pose, the ground (one of
    ``ground_z`` and ``flying_height``, metres) and the options."""

    images: dict[str, FlightImage]
    ground_z: float | None
    flying_height: float | None
    params: PairOptions

    def choose(self, max_candidates: int | None = None) -> FlightPairs:
        """The pairs (:func:`hmcc.footprint.flight_pairs`); :class:`InputError` naming the
        image whose pose does not fit."""
        from hmcc.footprint import flight_pairs  # SciPy and numba: only where pairs are chosen

        return flight_pairs(
            {name: image.camera for name, image in self.images.items()},
            # every image of a pairs request has a pose (ImageModel requires it)
            {name: image.pose for name, image in self.images.items() if image.pose is not None},
            ground_z=self.ground_z,
            flying_height=self.flying_height,
            options=self.params,
            max_candidates=max_candidates,
        )


def parse_pairs(body: Any, media_type: str = JSON) -> PairsQuery:
    """A pairs request (:class:`~hmcc_schema.models.PairsRequest`): JSON text, MessagePack
    bytes (as ``media_type`` says) or an already parsed object. Raises pydantic's
    ``ValidationError`` or :class:`InputError` naming what is wrong."""
    if isinstance(body, bytes | str) and media_type != MSGPACK:
        model = PairsRequest.model_validate_json(body)  # its parser bounds the depth
    else:
        doc = _load(body, media_type, lambda doc, read: None)  # the depth, first
        model = PairsRequest.model_validate(_as_lists(doc))
    if (model.ground_z is None) == (model.flying_height is None):
        field = "ground_z" if model.ground_z is None else "flying_height"
        raise InputError(field, "give ground_z or flying_height (metres), exactly one")
    images = {name: to_image(image, field=f"images.{name}") for name, image in model.images.items()}
    return PairsQuery(images, model.ground_z, model.flying_height, model.params)


# --------------------------------------------------------------------------- reading


def _load(body: Any, media_type: str, arrays: Callable[[dict[str, Any], Any], None]) -> Any:
    """The body as plain Python objects, its arrays of numbers as ndarrays (or :class:`_Unread`);
    None when it does not parse (the full model then says why: it also reads ``NaN`` and
    ``Infinity``, and refuses them field by field). The fast path is only ever faster: if it
    fails for any reason, the full model decides."""
    try:
        doc = _read(body, media_type, arrays)
    except InputError:
        raise
    except Exception:  # the full model reports whatever this could not read
        return None
    if _too_deep(doc):
        if isinstance(body, bytes | str) and media_type != MSGPACK:
            return None  # the JSON parser of the full model refuses it in its own words
        encoding = "MessagePack" if media_type == MSGPACK else "body"
        raise InputError("body", _depth_reason(encoding))
    return doc


def _read(body: Any, media_type: str, arrays: Callable[[dict[str, Any], Any], None]) -> Any:
    if isinstance(body, bytes | str) and media_type == MSGPACK:
        try:
            doc = msgpack.unpackb(body, raw=False, strict_map_key=True)
        except msgpack.StackError:  # nested deeper than the unpacker's own stack (1024)
            raise InputError("body", _depth_reason("MessagePack")) from None
        except (ValueError, TypeError, msgpack.UnpackException):
            return None
        if isinstance(doc, dict):
            arrays(doc, _from_object)
        return doc
    if isinstance(body, bytes | str):
        raw = body.encode() if isinstance(body, str) else body
        try:
            parsed = simdjson.Parser().parse(raw)
        except (ValueError, RuntimeError, TypeError):
            return None
        if not isinstance(parsed, simdjson.Object):
            return _plain(parsed)
        doc = _entries(parsed)  # arrays stay proxies for now
        arrays(doc, _from_simdjson)
        return _plain(doc)
    if isinstance(body, dict):
        doc = dict(body)
        arrays(doc, _from_object)
        return doc
    return body


def _too_deep(doc: Any) -> bool:
    """Whether ``doc`` nests lists and dicts (an :class:`_Unread` array's too) deeper than
    :data:`MAX_DEPTH`; level by level, without recursion. Arrays the fast path read are
    ndarrays by now, so this walks the small rest of a valid body: mostly leaves, told by
    their exact type at once (a batch's pairs' ids, image names and arrays: three
    ``isinstance`` a leaf took some 15 ms of a 7000-pair batch)."""
    level, depth = [doc], 0
    while level:
        deeper: list[Any] = []
        for node in level:
            kind = type(node)
            if kind in _LEAVES:
                continue
            if kind is _Unread:
                node = node.raw
            if isinstance(node, dict):
                deeper.extend(node.values())
            elif isinstance(node, list):
                deeper.extend(node)
            else:
                continue
            if depth == MAX_DEPTH:
                return True
        level = deeper
        depth += 1
    return False


#: Types that hold no lists or dicts (their subclasses take the general path).
_LEAVES = frozenset({str, bytes, int, float, bool, type(None), np.ndarray})


def _depth_reason(encoding: str) -> str:
    return (
        f"Invalid {encoding}: recursion limit exceeded "
        f"(arrays and objects nested more than {MAX_DEPTH} deep)"
    )


def _pair_arrays(doc: dict[str, Any], read: Callable[[Any, str], Any]) -> None:
    for name in _PAIR_ARRAYS:
        if name in doc:
            doc[name] = read(doc[name], "matches" if name == "matches" else "keypoints")


def _batch_arrays(doc: dict[str, Any], read: Callable[[Any, str], Any]) -> None:
    images: Any = doc.get("images")
    pairs: Any = doc.get("pairs")
    if _is_object(images):
        doc["images"] = images = _entries(images)
        for name, image in images.items():
            if _is_object(image):
                image = images[name] = _entries(image)
                if "keypoints" in image:
                    image["keypoints"] = read(image["keypoints"], "keypoints")
                if "descriptors" in image:
                    _check_buffer_dtype(image["descriptors"], f"images.{name}.descriptors")
                    image["descriptors"] = read(image["descriptors"], "descriptors")
    if _is_list(pairs):
        doc["pairs"] = pairs = list(pairs)
        for i, pair in enumerate(pairs):
            if _is_object(pair):
                pairs[i] = pair = _entries(pair)
                _pair_arrays(pair, read)


def _check_buffer_dtype(value: Any, field: str) -> None:
    """A descriptors buffer of another dtype is refused here, naming it (the full model would
    read a float64 buffer as lists of numbers)."""
    if isinstance(value, dict) and value.keys() == _BUFFER_KEYS:
        if value["dtype"] not in _BUFFER_DTYPES["descriptors"]:
            raise InputError(
                field,
                f"a buffer of dtype {clip(str(value['dtype']))!r}; descriptors are '|u1' "
                "(uint8) or '<f4' (float32)",
            )


def _entries(obj: Any) -> dict[str, Any]:
    """An object's members, a simdjson object's still proxies: its ``items()`` would convert
    every nested array to Python lists. Looking a key up finds its first value and stops at a
    NUL: an object with a key twice (the last counts, as for the model) or a NUL in one is
    converted whole (no field has such a key; the model then decides)."""
    if isinstance(obj, dict):
        return dict(obj)
    keys = list(obj.keys())
    if len(set(keys)) != len(keys) or any("\x00" in key for key in keys):
        return dict(obj.items())
    return {key: obj[key] for key in keys}


def _is_object(value: Any) -> bool:
    return isinstance(value, dict | simdjson.Object)


def _is_list(value: Any) -> bool:
    return isinstance(value, list | simdjson.Array)


def _from_simdjson(value: Any, kind: str) -> Any:
    """An array of rows of numbers as an ndarray, read from simdjson's buffer (no Python
    object per number); anything else :class:`_Unread`."""
    if not isinstance(value, simdjson.Array):
        return _Unread(_plain(value))
    try:
        floats = kind != "matches"
        flat = np.frombuffer(
            value.as_buffer(of_type="d" if floats else "i"),
            dtype=np.float64 if floats else np.int64,
        )
        rows = len(value)
        first: Any = value[0] if rows else ()
        width = len(first)
        # a row that is a number has no len (TypeError); the buffer holds numbers only
        lengths = set(map(len, cast(Iterable[Sized], value)))
        if rows and (flat.size != rows * width or lengths != {width}):
            raise ValueError("rows of different lengths")
    except (ValueError, TypeError, IndexError, RuntimeError):
        return _Unread(_plain(value))
    return flat.reshape(rows, width) if rows else flat


def _from_object(value: Any, kind: str) -> Any:
    """An array of an already parsed body: a buffer object (MessagePack), an ndarray or
    nested lists of plain numbers; anything else :class:`_Unread`."""
    if isinstance(value, dict) and value.keys() == _BUFFER_KEYS:
        try:
            dtype, shape, data = value["dtype"], value["shape"], value["data"]
            if dtype not in _BUFFER_DTYPES[kind] or not isinstance(data, bytes | memoryview):
                raise ValueError("unsupported buffer")
            array = np.frombuffer(data, dtype=_DTYPES[dtype]).reshape(shape)
        except (ValueError, TypeError):
            return _Unread(value)
        return array
    try:
        array = np.asarray(value)
    except (ValueError, TypeError, OverflowError):  # rows of different lengths
        return _Unread(value)
    if array.dtype.kind not in "iuf" or (isinstance(value, list) and _holds_a_boolean(value)):
        return _Unread(value)
    return array


def _holds_a_boolean(rows: list[Any]) -> bool:
    """Whether a row holds ``true`` or ``false``, which numpy reads as 1 and 0 among numbers
    (a boolean is not a number of the contract); about 35 ns a number."""
    try:
        return bool in set(map(type, chain.from_iterable(rows)))
    except TypeError:  # not rows: numbers (the shape refuses them anyway)
        return bool in set(map(type, rows))


def _plain(value: Any) -> Any:
    """Plain Python objects of a (small) part of a simdjson document."""
    if isinstance(value, simdjson.Object):
        return {key: _plain(item) for key, item in value.items()}
    if isinstance(value, simdjson.Array):
        return value.as_list()
    if isinstance(value, dict):
        return {key: _plain(v) for key, v in value.items()}
    if isinstance(value, list):
        return [_plain(v) for v in value]
    return value


def _full(model: type[BaseModel], body: Any, media_type: str) -> Any:
    """The full model's validation: raises ``ValidationError`` naming every problem."""
    if isinstance(body, bytes | str) and media_type != MSGPACK:
        return model.model_validate_json(body)
    if isinstance(body, bytes | str):
        try:
            body = msgpack.unpackb(body, raw=False, strict_map_key=True)
        except (ValueError, TypeError, msgpack.UnpackException):
            body = None  # the model says the body is not an object
    return model.model_validate(_as_lists(body))


def _as_lists(value: Any) -> Any:
    """Buffer objects and ndarrays as the nested lists the models describe. Recursive: only
    ever given a body :func:`_load` found at most :data:`MAX_DEPTH` deep."""
    if isinstance(value, dict):
        if value.keys() == _BUFFER_KEYS:
            for kind in _BUFFER_DTYPES:
                array = _from_object(value, kind)
                if not isinstance(array, _Unread):
                    return array.tolist()
            return value
        return {k: _as_lists(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_as_lists(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    return value


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


def _fast_batch(doc: dict[str, Any], views: bool = False) -> tuple[Flight, np.ndarray] | None:
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
                name: {k: v for k, v in image.items() if k not in ("keypoints", "descriptors")}
                for name, image in images_doc.items()
            }
        )
        heads: list[Any] = _plain_heads(pairs_doc) or _PAIR_HEADS.validate_python(
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
        raw_desc = images_doc[name].get("descriptors")
        descriptors = None if raw_desc is None else _descriptors(raw_desc)
        if raw_desc is not None and descriptors is None:
            return None
        images[name] = to_image(model, keypoints, f"images.{name}", descriptors)
    # One pass over the pairs: the matches of those that bring them, as read, and the keypoints
    # they index where the pair brings its own (else within an image's, a check across fields
    # in _check_pairs); a pair that asks for matching brings neither.
    given: list[np.ndarray] = []
    own: list[tuple[int, np.ndarray | None, np.ndarray | None]] = []  # (k, kp1, kp2) of given
    for head, raw in zip(heads, pairs_doc, strict=True):
        matches, kp1, kp2 = raw.get("matches"), raw.get("keypoints1"), raw.get("keypoints2")
        if head.match:
            if matches is not None or kp1 is not None or kp2 is not None:
                return None  # the model says what may not be there
            continue
        if kp1 is not None or kp2 is not None:
            kp1 = None if kp1 is None else _keypoints(kp1)
            kp2 = None if kp2 is None else _keypoints(kp2)
            if (kp1 is None) != (raw.get("keypoints1") is None) or (kp2 is None) != (
                raw.get("keypoints2") is None
            ):
                return None
            own.append((len(given), kp1, kp2))
        if not _plain_matches(matches):
            return None
        given.append(matches)
    # All the pairs' matches at once: one copy in their own dtype (small: as sent), one check
    # of their signs and each pair's largest indices, then one conversion to int64 of which
    # the pairs take slices. With views, the pairs keep their own arrays instead, checked a
    # chunk at a time.
    if views:
        flat, starts = _flat([], None)
        maxima = _chunked_maxima(given)
    else:
        flat, starts = _flat(given, None)
        maxima = _signed_maxima(flat, starts)
    if maxima is None:
        return None
    limits = np.full((len(given), 2), MAX_KEYPOINTS, dtype=np.int64)
    for k, kp1, kp2 in own:
        limits[k] = (
            MAX_KEYPOINTS if kp1 is None else len(kp1),
            MAX_KEYPOINTS if kp2 is None else len(kp2),
        )
    if (maxima >= limits).any():
        return None
    if not views:
        flat = flat.astype(np.int64, copy=False)
    bounds = [*starts.tolist(), len(flat)]
    own_keypoints = {k: (kp1, kp2) for k, kp1, kp2 in own}
    pairs, k = [], 0
    brought = np.ones(len(heads), dtype=bool)  # the pairs that bring matches
    for i, head in enumerate(heads):
        if head.match:
            pairs.append(
                FlightPair(head.image1, head.image2, _NO_MATCHES, None, None, head.id, True)
            )
            brought[i] = False
            continue
        matches = given[k] if views else flat[bounds[k] : bounds[k + 1]]
        kp1, kp2 = own_keypoints.get(k, (None, None))
        pairs.append(FlightPair(head.image1, head.image2, matches, kp1, kp2, head.id))
        k += 1
    full = np.full((len(pairs), 2), -1, dtype=np.int64)
    full[brought] = maxima
    return _batch_flight(fields, images, pairs), full


def _keypoints(value: Any) -> np.ndarray | None:
    """(N, 2|4) float64 keypoints read by the fast path, or None when they are not plainly
    that (the full model then says why)."""
    if not isinstance(value, np.ndarray) or value.dtype.kind not in "iuf":
        return None
    if value.ndim != 2 or value.shape[1] not in (2, 4) or not 0 < len(value) <= MAX_KEYPOINTS:
        return None
    a = value.astype(np.float64, copy=False)
    return a if np.isfinite(a).all() else None


def _descriptors(value: Any) -> np.ndarray | None:
    """(N, D) uint8 or float32 descriptors read by the fast path, or None when they are not
    plainly that (the full model then says why)."""
    if not isinstance(value, np.ndarray) or value.dtype.kind not in "iuf" or value.ndim != 2:
        return None
    if not (0 < len(value) <= MAX_KEYPOINTS and 0 < value.shape[1] <= MAX_DESCRIPTOR_LENGTH):
        return None
    return descriptor_array(value)


def _full_descriptors(value: Any, field: str) -> np.ndarray | None:
    """The full model's descriptors (lists of finite numbers) as an array."""
    if value is None:
        return None
    array = descriptor_array(np.asarray(value, dtype=np.float64))
    if array is None:
        raise InputError(field, "values beyond float32's range")
    return array


def _matches(value: Any, n1: int, n2: int) -> np.ndarray | None:
    """(M, 2) int64 matches read by the fast path whose indices fall within ``n1`` / ``n2``
    keypoints, or None when they are not plainly that."""
    if not isinstance(value, np.ndarray) or value.dtype.kind not in "iu":
        return None
    if value.ndim != 2 or value.shape[1] != 2 or not 0 < len(value) <= MAX_MATCHES:
        return None
    a = value.astype(np.int64)
    if a.min() < 0 or a[:, 0].max() >= n1 or a[:, 1].max() >= n2:
        return None
    return a


def _plain_heads(pairs: list[dict[str, Any]]) -> list[_PairHead] | None:
    """The pairs' ``id``, ``image1``, ``image2`` and ``match`` when each is plainly valid (a
    Python check, about a microsecond a pair); None: the model decides (and says why)."""
    heads = []
    for p in pairs:
        if not _PAIR_KEYS.issuperset(p):
            return None
        image1, image2, pair_id, match = (
            p.get("image1"),
            p.get("image2"),
            p.get("id"),
            p.get("match", False),
        )
        if not (
            type(image1) is str
            and type(image2) is str
            and 0 < len(image1) <= _MAX_NAME
            and 0 < len(image2) <= _MAX_NAME
            and (pair_id is None or (type(pair_id) is str and len(pair_id) <= _MAX_NAME))
            and type(match) is bool
        ):
            return None
        heads.append(_PairHead(pair_id, image1, image2, match))
    return heads


def _plain_matches(value: Any) -> bool:
    """(M, 2) integers, 0 < M <= MAX_MATCHES, as the fast path reads them."""
    return (
        isinstance(value, np.ndarray)
        and value.dtype.kind in "iu"
        and value.ndim == 2
        and value.shape[1] == 2
        and 0 < len(value) <= MAX_MATCHES
    )


def _flat(arrays: list[np.ndarray], dtype: type | None = np.int64) -> tuple[np.ndarray, np.ndarray]:
    """``arrays`` (each (M, 2), M > 0) as one array (of ``dtype``, None: theirs, promoted),
    and where each starts in it."""
    if not arrays:
        return np.zeros((0, 2), dtype=np.int64), np.zeros(0, dtype=np.int64)
    starts = np.zeros(len(arrays), dtype=np.int64)
    np.cumsum([len(a) for a in arrays[:-1]], out=starts[1:])
    if dtype is None:
        return np.concatenate(arrays), starts
    return np.concatenate(arrays, dtype=dtype, casting="unsafe"), starts


def _maxima(flat: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """Each array's largest index in either column, (N, 2), from :func:`_flat`."""
    if not len(starts):
        return np.zeros((0, 2), dtype=np.int64)
    return np.maximum.reduceat(flat, starts, axis=0)


def _signed_maxima(flat: np.ndarray, starts: np.ndarray) -> np.ndarray | None:
    """:func:`_maxima` as int64 (uint64 ones beyond any image's keypoints made
    :data:`MAX_KEYPOINTS`), or None when an index is negative, or when uint64 and signed
    indices met (numpy makes them float64)."""
    if flat.dtype.kind not in "iu" or (flat.dtype.kind == "i" and len(flat) and flat.min() < 0):
        return None
    maxima = _maxima(flat, starts)
    if maxima.dtype == np.uint64:
        maxima = np.minimum(maxima, np.uint64(MAX_KEYPOINTS))
    return maxima.astype(np.int64, copy=False)


#: Rows of matches checked at a time by :func:`_chunked_maxima`.
_CHUNK_ROWS = 1 << 17


def _chunked_maxima(arrays: list[np.ndarray]) -> np.ndarray | None:
    """:func:`_signed_maxima` of ``arrays`` (each (M, 2), M > 0) copied into one array a chunk
    of about :data:`_CHUNK_ROWS` rows at a time, not all at once: a flight's matches at once
    are some 100 MB of new memory, whose first touch cost ten times the check itself (0.2 of
    the 0.5 CPU s of parsing the 18 283-pair benchmark flight), where a chunk's memory is
    reused by the next."""
    ends = np.cumsum(np.fromiter(map(len, arrays), np.int64, len(arrays)))
    maxima = np.empty((len(arrays), 2), dtype=np.int64)
    start = 0
    while start < len(arrays):
        before = int(ends[start - 1]) if start else 0
        stop = max(start + 1, int(np.searchsorted(ends, before + _CHUNK_ROWS, side="right")))
        chunk = _signed_maxima(*_flat(arrays[start:stop], None))
        if chunk is None:
            return None
        maxima[start:stop] = chunk
        start = stop
    return maxima


# --------------------------------------------------------------------------- both paths


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
    return Flight(images, pairs, fields.method, fields.params, plane_z, ground_z, fields.matching)


def _check_pairs(flight: Flight, maxima: np.ndarray) -> None:
    """Every pair names images of the batch, has keypoints for both sides (its own or its
    image's) and indices within them, or asks for matching images that carry keypoints and
    descriptors of one length, the ground's height given; raises :class:`InputError` on the
    first that does not. ``maxima``: each pair's largest index in either column
    (:func:`_full_maxima`), so that the indices are checked for all pairs at once."""
    if _plainly_valid(flight, maxima):
        return
    limits = np.empty((len(flight.pairs), 2), dtype=np.int64)
    for i, pair in enumerate(flight.pairs):
        _check_posed(flight, i)
        if pair.match:
            _check_matching(flight, i)
            limits[i] = 0
            continue
        for side, name, own in (
            (1, pair.image1, pair.keypoints1),
            (2, pair.image2, pair.keypoints2),
        ):
            image = flight.images.get(name)
            if image is None:
                raise InputError(f"pairs[{i}].image{side}", f"no image {clip(name)!r} in images")
            if own is not None:
                check_in_frame(image.camera, own, f"pairs[{i}].keypoints{side}", f"images.{name}")
                limits[i, side - 1] = len(own)
                continue
            if image.keypoints is None:
                raise InputError(
                    f"pairs[{i}].keypoints{side}",
                    f"give the pair's keypoints{side} or images.{name}.keypoints",
                )
            limits[i, side - 1] = len(image.keypoints)
    beyond = np.flatnonzero((maxima >= limits).any(axis=1))
    if len(beyond):  # the first pair with an index out of range, and which one
        i = int(beyond[0])
        pair = flight.pairs[i]
        for side, name in ((1, pair.image1), (2, pair.image2)):
            column, n = pair.matches[:, side - 1], int(limits[i, side - 1])
            bad = np.flatnonzero(column >= n)
            if len(bad):
                k = int(bad[0])
                where = (
                    f"pairs[{i}] has {n} keypoints{side}"
                    if (pair.keypoints1, pair.keypoints2)[side - 1] is not None
                    else f"images.{name} has {n} keypoints"
                )
                raise InputError(
                    f"pairs[{i}].matches",
                    f"matches[{k}][{side - 1}] = {column[k]} is out of range: {where}",
                )


def _plainly_valid(flight: Flight, maxima: np.ndarray) -> bool:
    """What :func:`_check_pairs` checks, for all pairs at once, when nothing is amiss and no
    pair asks for matching or brings keypoints of its own: every image it names is in the
    batch, with keypoints and, if the method uses them, a pose, and each pair's indices lie
    within its images' keypoints. False: the pair by pair check decides (and says why)."""
    images = flight.images
    if flight.method in POS_METHODS and any(im.pose is None for im in images.values()):
        return False
    counts = {name: len(im.keypoints) for name, im in images.items() if im.keypoints is not None}
    try:
        limits = [
            (counts[p.image1], counts[p.image2])
            for p in flight.pairs
            if not p.match and p.keypoints1 is None and p.keypoints2 is None
        ]
    except KeyError:  # an image not in the batch, or without keypoints
        return False
    if len(limits) != len(flight.pairs):
        return False
    return not (maxima >= np.asarray(limits, dtype=np.int64).reshape(-1, 2)).any()


def _full_maxima(pairs: list[FlightPair]) -> np.ndarray:
    """Each pair's largest index in either column (-1 for a pair without matches)."""
    maxima = np.full((len(pairs), 2), -1, dtype=np.int64)
    given = [i for i, p in enumerate(pairs) if len(p.matches)]
    flat, starts = _flat([pairs[i].matches for i in given])
    maxima[given] = _maxima(flat, starts)
    return maxima


def _check_posed(flight: Flight, i: int) -> None:
    """Pair ``i``'s images have poses, unless the method ignores them."""
    if flight.method not in POS_METHODS:
        return
    pair = flight.pairs[i]
    for name in (pair.image1, pair.image2):
        image = flight.images.get(name)
        if image is not None and image.pose is None:
            raise InputError(
                f"images.{name}.pose",
                f"method {flight.method!r} uses the rough poses (pairs[{i}] names this image); "
                "without a pose only an estimator verifies (ransac, magsac++, ...)",
            )


def _check_matching(flight: Flight, i: int) -> None:
    """Pair ``i`` asks for matching: both images carry keypoints and descriptors, of one
    length, and the plane gives the ground's height."""
    pair = flight.pairs[i]
    lengths = []
    for side, name in ((1, pair.image1), (2, pair.image2)):
        image = flight.images.get(name)
        if image is None:
            raise InputError(f"pairs[{i}].image{side}", f"no image {clip(name)!r} in images")
        if image.descriptors is None:
            raise InputError(
                f"images.{name}.descriptors",
                f"pairs[{i}] asks for matching: its images need keypoints and descriptors",
            )
        lengths.append(image.descriptors.shape[1])
    if lengths[0] != lengths[1]:
        raise InputError(
            f"pairs[{i}]",
            f"its images' descriptors differ in length ({lengths[0]} and {lengths[1]}): "
            "matching compares descriptors of one kind",
        )
    if flight.plane_z is None and flight.ground_z is None:
        raise InputError(
            "plane",
            f"pairs[{i}] asks for matching, which predicts positions on the ground: give "
            "plane.ground_z (the ground's height, metres) or plane.z",
        )
