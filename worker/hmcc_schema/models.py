"""The JSON request formats (a public contract): pydantic models of their structure.

``PairRequest`` is the body of ``POST /v1/verifications`` (and of a pair file on the command
line), ``BatchRequest`` the body of ``POST /v1/batches``. These models are the contract's
documentation (the OpenAPI document is generated from them) and its error reports: field
paths and reasons come from pydantic's ``loc`` and messages. Valid bodies do not go through
the array fields here, though: :mod:`hmcc_schema.parse` reads keypoints and matches straight
into numpy arrays and checks them vectorised, and falls back to these models only to say what
is wrong. Conventions are documented in the README ("Conventions").

The rules across fields are in the JSON Schema of the models too, where JSON Schema can say
them (``json_schema_extra``: one focal or fx and fy, z or ground_z, a mounting only with a
yaw/pitch/roll attitude, keypoint rows all of one width, the known methods), so a body the
OpenAPI document accepts passes these models. What depends on values elsewhere in the body
(match indices against the keypoints, keypoints against the camera's frame) or is arithmetic
(a rotation matrix) is said in the descriptions.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Discriminator,
    Field,
    GetCoreSchemaHandler,
    Tag,
    ValidationInfo,
    field_validator,
    model_validator,
)
from pydantic_core import CoreSchema, PydanticCustomError, core_schema

from hmcc import VerifyOptions
from hmcc.camera import FRAME_MARGIN
from hmcc.method_names import DEFAULT_METHOD
from hmcc.method_names import METHOD_NAMES as METHODS
from hmcc.stage_options import GuidedOptions, PairOptions

from .issues import clip

__all__ = [
    "MAX_BATCH_IMAGES",
    "MAX_KEYPOINTS",
    "MAX_MATCHES",
    "BatchImage",
    "BatchPair",
    "BatchRequest",
    "MAX_DESCRIPTOR_LENGTH",
    "CameraModel",
    "Descriptors",
    "GeodeticPosition",
    "ImageModel",
    "Keypoints",
    "LocalPosition",
    "Matches",
    "Mounting",
    "OmegaPhiKappa",
    "PairRequest",
    "PairsRequest",
    "Plane",
    "PoseModel",
    "RotationMatrix",
    "YawPitchRoll",
]

#: Upper bounds that keep one request's work and memory bounded.
MAX_KEYPOINTS = 200_000
MAX_MATCHES = 100_000
MAX_BATCH_IMAGES = 10_000
#: The longest descriptor (values per row): SIFT's is 128.
MAX_DESCRIPTOR_LENGTH = 1024

Finite = Annotated[float, Field(allow_inf_nan=False)]


def _not_a_boolean(value: Any) -> Any:
    if isinstance(value, bool):
        raise PydanticCustomError("number_type", "Input should be a number, not a boolean")
    return value


def _refuse_booleans(node: Any, handler: GetCoreSchemaHandler, seen: set[str]) -> Any:
    """``node`` (a core schema or a part of one), every integer and float in it refusing
    ``true`` and ``false``: pydantic's lax mode reads them as 1 and 0, and a boolean is never a
    number of the contract (numbers given as strings still read). Reaches the options of the
    core (``params``: dataclasses pydantic reads) through their definitions too."""
    if isinstance(node, list):
        node[:] = [_refuse_booleans(item, handler, seen) for item in node]
        return node
    if not isinstance(node, dict):
        return node
    kind = node.get("type")
    if kind in ("int", "float"):
        return core_schema.no_info_before_validator_function(_not_a_boolean, node)
    if kind == "function-before" and node["function"].get("function") is _not_a_boolean:
        return node  # a nested model's schema, done when it was built
    if kind == "definition-ref":
        if node["schema_ref"] not in seen:
            seen.add(node["schema_ref"])
            _refuse_booleans(handler.resolve_ref_schema(node), handler, seen)
        return node
    for key, value in node.items():
        if key not in ("metadata", "serialization"):
            node[key] = _refuse_booleans(value, handler, seen)
    return node


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)

    @classmethod
    def __get_pydantic_core_schema__(
        cls, source: type[BaseModel], handler: GetCoreSchemaHandler
    ) -> CoreSchema:
        return _refuse_booleans(handler(source), handler, set())


def _given(*names: str) -> dict[str, Any]:
    """JSON Schema: every one of ``names`` is present and not null (the models' None is "not
    given", so an explicit null counts as absent)."""
    return {"required": list(names), "properties": {n: {"not": {"type": "null"}} for n in names}}


class CameraModel(_Model):
    """Pinhole intrinsics in pixels; give ``fx`` and ``fy``, or a single ``focal`` (exactly one
    of the two ways).

    The principal point defaults to the image centre ((width - 1) / 2, (height - 1) / 2).
    ``distortion``: OpenCV (k1, k2, p1, p2[, k3]); keypoints are undistorted before use.
    """

    model_config = ConfigDict(
        json_schema_extra={
            "oneOf": [
                {**_given("focal"), "not": {"anyOf": [_given("fx"), _given("fy")]}},
                {**_given("fx", "fy"), "not": _given("focal")},
            ]
        }
    )

    width: int = Field(gt=0, le=100_000)
    height: int = Field(gt=0, le=100_000)
    fx: Finite | None = Field(default=None, gt=0, description="With `fy`, instead of `focal`.")
    fy: Finite | None = Field(default=None, gt=0, description="With `fx`, instead of `focal`.")
    focal: Finite | None = Field(
        default=None, gt=0, description="Both focal lengths, instead of `fx` and `fy`."
    )
    cx: Finite | None = None
    cy: Finite | None = None
    distortion: list[Finite] | None = Field(
        default=None,
        min_length=4,
        max_length=5,
        description="The frame and its margin must undistort to finite points (else 422).",
    )

    @model_validator(mode="after")
    def _one_focal(self) -> CameraModel:
        if self.focal is None and (self.fx is None or self.fy is None):
            raise ValueError("give fx and fy, or focal (pixels)")
        if self.focal is not None and (self.fx is not None or self.fy is not None):
            raise ValueError("give either focal or fx/fy, not both")
        return self


class LocalPosition(_Model):
    """Local metric position: x east, y north, z up, metres."""

    x: Finite
    y: Finite
    z: Finite


class GeodeticPosition(_Model):
    """WGS84 latitude/longitude (degrees) and ellipsoidal height ``alt`` (metres)."""

    lat: Finite = Field(ge=-90, le=90)
    lon: Finite = Field(ge=-180, le=180)
    alt: Finite


class YawPitchRoll(_Model):
    """Platform attitude, aerospace, degrees: yaw clockwise from north, pitch nose up,
    roll right wing down, applied Z-Y-X to a north-east-down body frame."""

    yaw: Finite
    pitch: Finite
    roll: Finite


class OmegaPhiKappa(_Model):
    """Photogrammetric camera attitude, degrees: R(camera->world) = Rx(omega) Ry(phi) Rz(kappa),
    camera frame x right, y image-up, z backward."""

    omega: Finite
    phi: Finite
    kappa: Finite


class RotationMatrix(_Model):
    """Explicit world(ENU)-to-camera rotation, camera frame x right, y down, z forward."""

    matrix: Annotated[
        list[Annotated[list[Finite], Field(min_length=3, max_length=3)]],
        Field(
            min_length=3,
            max_length=3,
            description="3 x 3, row by row; a rotation: orthonormal with determinant +1, to "
            "1e-3 (else 422).",
        ),
    ]

    @field_validator("matrix")
    @classmethod
    def _rotation(cls, m: list[list[float]]) -> list[list[float]]:
        r = np.asarray(m, dtype=np.float64)
        # Entries bounded first: r @ r.T of huge entries overflows (inf/nan compare False).
        if not (
            np.abs(r).max() <= 1.0 + 1e-3
            and np.abs(r @ r.T - np.eye(3)).max() <= 1e-3
            and np.linalg.det(r) > 0
        ):
            raise ValueError("not a rotation (must be orthonormal with determinant +1)")
        return m


class Mounting(_Model):
    """Camera mounting on the platform: Z-Y-X yaw/pitch/roll (degrees) relative to the nadir
    mount (pitch +45 = front oblique, roll +45 = left oblique) and a lever arm in the body frame
    (metres: x nose, y right wing, z down)."""

    yaw: Finite = 0.0
    pitch: Finite = 0.0
    roll: Finite = 0.0
    lever_arm: Annotated[list[Finite], Field(min_length=3, max_length=3)] | None = None


def _position_kind(v: Any) -> str:
    if isinstance(v, dict):
        return "geodetic" if ("lat" in v or "lon" in v) else "local"
    return "geodetic" if isinstance(v, GeodeticPosition) else "local"


def _attitude_kind(v: Any) -> str:
    if isinstance(v, dict):
        keys = set(v)
    elif isinstance(v, BaseModel):
        keys = set(type(v).model_fields)
    else:  # not an object at all: the default branch reports the type error
        keys = set()
    if "matrix" in keys:
        return "matrix"
    if keys & {"omega", "phi", "kappa"}:
        return "omega_phi_kappa"
    return "yaw_pitch_roll"


class PoseModel(_Model):
    """The rough pose: a position, an attitude and, with a yaw/pitch/roll (platform) attitude
    only, the camera's mounting."""

    model_config = ConfigDict(
        json_schema_extra={
            "if": _given("mounting"),
            "then": {"properties": {"attitude": {"required": ["yaw", "pitch", "roll"]}}},
        }
    )

    position: Annotated[
        Annotated[LocalPosition, Tag("local")] | Annotated[GeodeticPosition, Tag("geodetic")],
        Discriminator(_position_kind),
    ] = Field(
        description="Both images of a pair give it the same way, x/y/z or lat/lon/alt (else "
        "the pair fails with `invalid_input`)."
    )
    attitude: Annotated[
        Annotated[YawPitchRoll, Tag("yaw_pitch_roll")]
        | Annotated[OmegaPhiKappa, Tag("omega_phi_kappa")]
        | Annotated[RotationMatrix, Tag("matrix")],
        Discriminator(_attitude_kind),
    ]
    mounting: Mounting | None = Field(
        default=None, description="Only with a yaw/pitch/roll attitude (the platform's)."
    )

    @model_validator(mode="after")
    def _mounting_needs_platform(self) -> PoseModel:
        if self.mounting is not None and not isinstance(self.attitude, YawPitchRoll):
            raise ValueError(
                "mounting applies to a platform attitude (yaw/pitch/roll); omega/phi/kappa "
                "and matrix attitudes are the camera's own"
            )
        return self


class ImageModel(_Model):
    camera: CameraModel
    pose: PoseModel


class Plane(_Model):
    """The projection plane, one of: ``{"z": Z0}`` exactly that plane (ENU metres);
    ``{"ground_z": G}`` the ground height, the plane goes below it by
    ``params.ground.plane_depth_fraction`` of the flying height (our rule; its default gives
    the paper's one instance, -100 m for a site near 0 m flown at 300 m);
    ``{"z": "auto"}`` (the default) the same with G estimated from the matches. Not both
    ``z`` and ``ground_z``."""

    model_config = ConfigDict(json_schema_extra={"not": _given("z", "ground_z")})

    z: Finite | Literal["auto"] | None = None
    ground_z: Finite | None = None

    @model_validator(mode="after")
    def _one_way(self) -> Plane:
        if self.z is not None and self.ground_z is not None:
            raise ValueError("give either z or ground_z, not both")
        return self


Keypoints = Annotated[
    list[Annotated[list[Finite], Field(min_length=2, max_length=4)]],
    Field(
        min_length=1,
        max_length=MAX_KEYPOINTS,
        description="Pixels, `[x, y]` or `[x, y, size, angle_deg]`, every row the same width. "
        f"Each within its image's frame widened by {FRAME_MARGIN:.0%} of the width and height "
        f"on every side (-{FRAME_MARGIN:g} x width <= x <= {1 + FRAME_MARGIN:g} x width, "
        "likewise y; else 422).",
        # All rows [x, y], or all [x, y, size, angle_deg].
        json_schema_extra={"anyOf": [{"items": {"maxItems": 2}}, {"items": {"minItems": 4}}]},
    ),
]


# An index is below MAX_KEYPOINTS (the range check against the actual keypoints follows);
# bounding it here also keeps it within int64 for that check.
Matches = Annotated[
    list[
        Annotated[
            list[Annotated[int, Field(ge=0, lt=MAX_KEYPOINTS)]],
            Field(min_length=2, max_length=2),
        ]
    ],
    Field(
        min_length=1,
        max_length=MAX_MATCHES,
        description="`[i, j]`: keypoint i of the first image matches keypoint j of the "
        "second. i is below the number of the first image's keypoints, j below the second's "
        "(else 422).",
    ),
]


Descriptors = Annotated[
    list[Annotated[list[Finite], Field(min_length=1, max_length=MAX_DESCRIPTOR_LENGTH)]],
    Field(
        min_length=1,
        max_length=MAX_KEYPOINTS,
        description="One row per keypoint of the image, in the keypoints' order (else 422), "
        f"every row the same length D (at most {MAX_DESCRIPTOR_LENGTH}; SIFT: 128): integers "
        "0 to 255 (uint8, as SIFT's) or any finite numbers (float32). The pairs that ask for "
        "matching compare the angle between descriptors. In MessagePack also a raw buffer "
        '`{"dtype": "|u1" or "<f4", "shape": [N, D], "data": <bytes>}`.',
    ),
]


def _check_descriptors(rows: list[list[float]] | None) -> list[list[float]] | None:
    if rows is not None and len({len(r) for r in rows}) > 1:
        raise ValueError("every descriptor must have the same length")
    return rows


def _check_keypoints(kps: list[list[float]] | None) -> list[list[float]] | None:
    if kps is None:
        return None
    widths = {len(k) for k in kps}
    if not widths <= {2, 4} or len(widths) != 1:
        raise ValueError("every keypoint must be [x, y] or every one [x, y, size, angle_deg]")
    return kps


def _check_matches(matches: list[list[int]] | None, info: ValidationInfo) -> list[list[int]] | None:
    """Every index must point at a keypoint (``info.data`` holds the validated keypoints)."""
    if matches is None:
        return None
    for col, name in ((0, "keypoints1"), (1, "keypoints2")):
        kps = info.data.get(name)
        if kps is None:
            continue
        column = np.fromiter((m[col] for m in matches), dtype=np.int64, count=len(matches))
        bad = np.flatnonzero(column >= len(kps))
        if len(bad):
            i = int(bad[0])
            raise ValueError(
                f"matches[{i}][{col}] = {column[i]} is out of range: "
                f"{name} has {len(kps)} keypoints"
            )
    return matches


def _check_method(method: str) -> str:
    if method not in METHODS:
        raise ValueError(f"unknown method {clip(method)!r}; one of {list(METHODS)}")
    return method


#: ``method``: a name :data:`hmcc.METHODS` knows.
_METHOD = Field(
    default=DEFAULT_METHOD,
    description="`hmcc-plus` and `hmcc-lean` fit fundamental matrices only: another "
    "`params.ransac.model` with them is refused (422).",
    json_schema_extra={"enum": list(METHODS)},
)


class _PairFields(_Model):
    """A pair request without its arrays (what :mod:`hmcc_schema.parse` validates here)."""

    image1: ImageModel
    image2: ImageModel
    plane: Plane = Plane()
    method: str = _METHOD
    params: VerifyOptions = VerifyOptions()
    ground_truth: dict[str, Any] | None = Field(
        default=None, description="Ignored by the verifier (written by `hmcc simulate`)."
    )

    _known_method = field_validator("method")(_check_method)


class PairRequest(_PairFields):
    """One image pair: cameras, rough poses, keypoints, candidate matches, method."""

    keypoints1: Keypoints
    keypoints2: Keypoints
    matches: Matches

    _rectangular = field_validator("keypoints1", "keypoints2")(_check_keypoints)
    _in_range = field_validator("matches")(_check_matches)


class BatchImage(_Model):
    """An image of a batch: its camera and pose and, optionally, its keypoints, sent once for
    every pair that names it (such pairs send only their matches), and their descriptors (for
    the pairs that ask for matching). An image without a pose: only with a method that does
    not use the poses (an estimator); its pairs that ask for matching are matched by brute
    force."""

    model_config = ConfigDict(
        json_schema_extra={"dependentRequired": {"descriptors": ["keypoints"]}}
    )

    camera: CameraModel
    pose: PoseModel | None = Field(
        default=None,
        description="Required unless the batch's `method` ignores the poses (`ransac`, "
        "`magsac++`, ... : not `hmcc-plus`, `hmcc-lean`, `hmcc-ransac`, `hmcc`; else 422). "
        "Without one, the image's pairs are verified without poses and, when they ask for "
        "matching, matched by brute force.",
    )
    keypoints: Keypoints | None = None
    descriptors: Descriptors | None = Field(
        default=None, description="Only with `keypoints`: one descriptor per keypoint."
    )

    _rectangular = field_validator("keypoints")(_check_keypoints)
    _same_length = field_validator("descriptors")(_check_descriptors)


class _BatchPairFields(_Model):
    id: str | None = Field(default=None, max_length=200)
    image1: str = Field(min_length=1, max_length=200, description="A key of `images`.")
    image2: str = Field(min_length=1, max_length=200, description="A key of `images`.")
    match: bool = Field(
        default=False,
        description="Match the two images' descriptors (guided by the rough poses, options "
        "in the batch's `matching`) instead of bringing `matches`: both images carry "
        "`keypoints` and `descriptors`, the pair neither `matches` nor keypoints of its own "
        "(else 422). The result then holds the `matches` found, `inliers` indexing them, "
        "and the matcher's figures (`matching`).",
    )


class BatchPair(_BatchPairFields):
    """One pair of a batch: the ids of its two images in ``BatchRequest.images``, its candidate
    matches (or ``match: true``), and its keypoints unless its images carry them; ``id`` is
    the caller's own label, echoed in results."""

    model_config = ConfigDict(
        json_schema_extra={
            "if": {"required": ["match"], "properties": {"match": {"const": True}}},
            "then": {
                "not": {"anyOf": [_given("matches"), _given("keypoints1"), _given("keypoints2")]}
            },
            "else": _given("matches"),
        }
    )

    keypoints1: Keypoints | None = Field(
        default=None,
        description="The pair's own keypoints of image1; required unless that image carries "
        "`keypoints` (the pair's take precedence).",
    )
    keypoints2: Keypoints | None = Field(default=None, description="Likewise for image2.")
    matches: Matches | None = Field(
        default=None, description="Required unless the pair asks for matching (`match`)."
    )

    _rectangular = field_validator("keypoints1", "keypoints2")(_check_keypoints)
    _in_range = field_validator("matches")(_check_matches)

    @model_validator(mode="after")
    def _matches_or_match(self) -> BatchPair:
        if self.match and self.matches is not None:
            raise ValueError("give matches or match: true, not both")
        if self.match and (self.keypoints1 is not None or self.keypoints2 is not None):
            raise ValueError(
                "a pair that asks for matching uses its images' keypoints and descriptors "
                "(no keypoints1/keypoints2 of its own)"
            )
        if not self.match and self.matches is None:
            raise ValueError("give matches, or match: true to have the images matched")
        return self


class _BatchFields(_Model):
    plane: Plane = Plane()
    method: str = _METHOD
    params: VerifyOptions = VerifyOptions()
    matching: GuidedOptions = Field(
        default=GuidedOptions(),
        description="The matcher's options, for the pairs that ask for matching (`match`): "
        "the rough poses' errors (which set the search radius), the ratio test, the mutual "
        "check (`cross_check`), brute force where the poses do not fit. The ground's height "
        "comes from `plane` (`ground_z`, else `z`; one of them is required then).",
    )

    _known_method = field_validator("method")(_check_method)


class BatchRequest(_BatchFields):
    """Many pairs of one flight: each image's camera and pose (and keypoints) once, then the
    pairs; method, params and plane apply to every pair. At most ``HMCC_MAX_BATCH_PAIRS``
    pairs (a service setting)."""

    images: Annotated[dict[str, BatchImage], Field(min_length=1, max_length=MAX_BATCH_IMAGES)]
    pairs: Annotated[list[BatchPair], Field(min_length=1)]


class PairsRequest(_Model):
    """The images of a flight (each one's camera and rough pose, as in a batch; no keypoints)
    and how to choose the pairs worth matching among them: footprints on the ground that
    overlap by more than ``params.min_overlap`` of the smaller one. The ground is
    ``ground_z`` (metres, on the positions' height scale: ellipsoidal for lat/lon/alt) or
    ``flying_height`` metres below each camera; exactly one of the two."""

    model_config = ConfigDict(
        json_schema_extra={
            "oneOf": [
                {**_given("ground_z"), "not": _given("flying_height")},
                {**_given("flying_height"), "not": _given("ground_z")},
            ]
        }
    )

    images: Annotated[
        dict[Annotated[str, Field(min_length=1, max_length=200)], ImageModel],
        Field(
            min_length=2,
            max_length=MAX_BATCH_IMAGES,
            description="Image id -> camera and pose. Every position given the same way, "
            "x/y/z or lat/lon/alt (else 422).",
        ),
    ]
    ground_z: Finite | None = Field(
        default=None, description="The ground's height (metres), below every camera."
    )
    flying_height: Finite | None = Field(
        default=None, gt=0, description="Each camera's height above the ground (metres)."
    )
    params: PairOptions = PairOptions()
