"""The JSON pair format: a public contract, validated with pydantic, reused by the API.

``PairRequest`` is the request body of one pair; :func:`to_pair_data` converts it once into the
core's arrays. Errors name the field (pydantic's ``loc``) and the reason; checks that need
numbers from several fields raise :class:`hmcc.errors.InputError` with a dotted field path.
Conventions are documented in the README ("Conventions").
"""

from __future__ import annotations

import re
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Discriminator,
    Field,
    Tag,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)

from .camera import Camera
from .errors import InputError
from .pipeline import DEFAULT_METHOD, METHODS, PairData, Verification, VerifyOptions, verify
from .pose import (
    Pose,
    camera_pose,
    geodetic_to_enu,
    rotation_body_to_ned,
    rotation_from_omega_phi_kappa,
    rotation_from_yaw_pitch_roll,
)

__all__ = [
    "BatchPair",
    "BatchRequest",
    "FieldIssue",
    "MAX_KEYPOINTS",
    "MAX_MATCHES",
    "PairRequest",
    "to_pair_data",
    "validation_issues",
    "verify_request",
]

#: Upper bounds that keep one request's work and memory bounded.
MAX_KEYPOINTS = 200_000
MAX_MATCHES = 100_000
MAX_BATCH_PAIRS = 10_000
MAX_BATCH_IMAGES = 10_000

Finite = Annotated[float, Field(allow_inf_nan=False)]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)


class CameraModel(_Model):
    """Pinhole intrinsics in pixels; give ``fx``/``fy`` or a single ``focal``.

    The principal point defaults to the image centre ((width - 1) / 2, (height - 1) / 2).
    ``distortion``: OpenCV (k1, k2, p1, p2[, k3]); keypoints are undistorted before use.
    """

    width: int = Field(gt=0, le=100_000)
    height: int = Field(gt=0, le=100_000)
    fx: Finite | None = Field(default=None, gt=0)
    fy: Finite | None = Field(default=None, gt=0)
    focal: Finite | None = Field(default=None, gt=0)
    cx: Finite | None = None
    cy: Finite | None = None
    distortion: list[Finite] | None = Field(default=None, min_length=4, max_length=5)

    @model_validator(mode="after")
    def _one_focal(self) -> CameraModel:
        if self.focal is None and (self.fx is None or self.fy is None):
            raise ValueError("give fx and fy, or focal (pixels)")
        if self.focal is not None and (self.fx is not None or self.fy is not None):
            raise ValueError("give either focal or fx/fy, not both")
        return self

    def to_camera(self) -> Camera:
        fx = self.fx if self.fx is not None else self.focal
        fy = self.fy if self.fy is not None else self.focal
        assert fx is not None and fy is not None
        dist = None
        if self.distortion is not None:
            d = [*self.distortion, 0.0][:5]
            dist = (d[0], d[1], d[2], d[3], d[4])
        return Camera(
            self.width,
            self.height,
            fx,
            fy,
            (self.width - 1) / 2.0 if self.cx is None else self.cx,
            (self.height - 1) / 2.0 if self.cy is None else self.cy,
            dist,
        )


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
        Field(min_length=3, max_length=3),
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
    position: Annotated[
        Annotated[LocalPosition, Tag("local")] | Annotated[GeodeticPosition, Tag("geodetic")],
        Discriminator(_position_kind),
    ]
    attitude: Annotated[
        Annotated[YawPitchRoll, Tag("yaw_pitch_roll")]
        | Annotated[OmegaPhiKappa, Tag("omega_phi_kappa")]
        | Annotated[RotationMatrix, Tag("matrix")],
        Discriminator(_attitude_kind),
    ]
    mounting: Mounting | None = None

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
    ``params.ground.plane_depth_fraction`` of the flying height (the paper's choice);
    ``{"z": "auto"}`` (the default) the same with G estimated from the matches."""

    z: Finite | Literal["auto"] | None = None
    ground_z: Finite | None = None

    @model_validator(mode="after")
    def _one_way(self) -> Plane:
        if self.z is not None and self.ground_z is not None:
            raise ValueError("give either z or ground_z, not both")
        return self


Keypoints = Annotated[
    list[Annotated[list[Finite], Field(min_length=2, max_length=4)]],
    Field(min_length=1, max_length=MAX_KEYPOINTS),
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
    Field(min_length=1, max_length=MAX_MATCHES),
]


def _check_keypoints(kps: list[list[float]]) -> list[list[float]]:
    widths = {len(k) for k in kps}
    if not widths <= {2, 4} or len(widths) != 1:
        raise ValueError("every keypoint must be [x, y] or every one [x, y, size, angle_deg]")
    return kps


def _check_matches(matches: list[list[int]], info: ValidationInfo) -> list[list[int]]:
    """Every index must point at a keypoint (``info.data`` holds the validated keypoints)."""
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
        raise ValueError(f"unknown method {method!r}; one of {list(METHODS)}")
    return method


class PairRequest(_Model):
    """One image pair: cameras, rough poses, keypoints, candidate matches, method."""

    image1: ImageModel
    image2: ImageModel
    keypoints1: Keypoints
    keypoints2: Keypoints
    matches: Matches
    plane: Plane = Plane()
    method: str = DEFAULT_METHOD
    params: VerifyOptions = VerifyOptions()
    ground_truth: dict[str, Any] | None = Field(
        default=None, description="Ignored by the verifier (written by `hmcc simulate`)."
    )

    _rectangular = field_validator("keypoints1", "keypoints2")(_check_keypoints)
    _in_range = field_validator("matches")(_check_matches)
    _known_method = field_validator("method")(_check_method)


class BatchPair(_Model):
    """One pair of a batch: the ids of its two images in ``BatchRequest.images``, its
    keypoints and candidate matches; ``id`` is the caller's own label, echoed in results."""

    id: str | None = Field(default=None, max_length=200)
    image1: str = Field(min_length=1, max_length=200)
    image2: str = Field(min_length=1, max_length=200)
    keypoints1: Keypoints
    keypoints2: Keypoints
    matches: Matches

    _rectangular = field_validator("keypoints1", "keypoints2")(_check_keypoints)
    _in_range = field_validator("matches")(_check_matches)


class BatchRequest(_Model):
    """Many pairs of one flight: each image's camera and pose once, then the pairs; method,
    params and plane apply to every pair."""

    images: Annotated[dict[str, ImageModel], Field(min_length=1, max_length=MAX_BATCH_IMAGES)]
    pairs: Annotated[list[BatchPair], Field(min_length=1, max_length=MAX_BATCH_PAIRS)]
    plane: Plane = Plane()
    method: str = DEFAULT_METHOD
    params: VerifyOptions = VerifyOptions()

    _known_method = field_validator("method")(_check_method)

    def check_images(self) -> BatchRequest:
        """Every pair names images that are in ``images``; raises :class:`InputError`."""
        for i, pair in enumerate(self.pairs):
            for side in ("image1", "image2"):
                image_id = getattr(pair, side)
                if image_id not in self.images:
                    raise InputError(f"pairs[{i}].{side}", f"no image {image_id!r} in images")
        return self

    def pair_requests(self) -> list[PairRequest]:
        """The pairs as :class:`PairRequest` (no re-validation: this batch was validated)."""
        self.check_images()
        return [
            PairRequest.model_construct(
                image1=self.images[p.image1],
                image2=self.images[p.image2],
                keypoints1=p.keypoints1,
                keypoints2=p.keypoints2,
                matches=p.matches,
                plane=self.plane,
                method=self.method,
                params=self.params,
                ground_truth=None,
            )
            for p in self.pairs
        ]


def _pose(image: ImageModel, origin: tuple[float, float, float] | None) -> Pose:
    pose = image.pose
    pos = pose.position
    if isinstance(pos, GeodeticPosition):
        assert origin is not None
        position = geodetic_to_enu(pos.lat, pos.lon, pos.alt, origin)[0]
    else:
        position = np.array([pos.x, pos.y, pos.z])
    att = pose.attitude
    lever = None
    r_ned_body = None
    if isinstance(att, YawPitchRoll):
        mount = pose.mounting or Mounting()
        R = rotation_from_yaw_pitch_roll(
            att.yaw, att.pitch, att.roll, (mount.yaw, mount.pitch, mount.roll)
        )
        r_ned_body = rotation_body_to_ned(att.yaw, att.pitch, att.roll)
        lever = None if mount.lever_arm is None else np.asarray(mount.lever_arm)
    elif isinstance(att, OmegaPhiKappa):
        R = rotation_from_omega_phi_kappa(att.omega, att.phi, att.kappa)
    else:
        R = np.asarray(att.matrix, dtype=np.float64)
    return camera_pose(position, R, lever, r_ned_body)


def _origin(req: PairRequest) -> tuple[float, float, float] | None:
    """The shared local tangent frame of a WGS84 pair: mean lat/lon, height 0."""
    positions = [req.image1.pose.position, req.image2.pose.position]
    geodetic = [p for p in positions if isinstance(p, GeodeticPosition)]
    if not geodetic:
        return None
    if len(geodetic) != 2:
        raise InputError(
            "image2.pose.position",
            "both images must give their position the same way (x/y/z or lat/lon/alt)",
        )
    return (
        float(np.mean([p.lat for p in geodetic])),
        float(np.mean([p.lon for p in geodetic])),
        0.0,
    )


def to_pair_data(req: PairRequest) -> PairData:
    """Convert a validated request to the core's arrays (the one conversion at the edge)."""
    origin = _origin(req)
    pose1 = _pose(req.image1, origin)
    pose2 = _pose(req.image2, origin)
    if np.linalg.norm(pose1.center - pose2.center) > 1e6:
        raise InputError("image2.pose.position", "the cameras are more than 1000 km apart")
    return PairData(
        req.image1.camera.to_camera(),
        pose1,
        req.image2.camera.to_camera(),
        pose2,
        np.asarray(req.keypoints1, dtype=np.float64),
        np.asarray(req.keypoints2, dtype=np.float64),
        np.asarray(req.matches, dtype=np.int64).reshape(-1, 2),
        None if req.plane.z in (None, "auto") else float(req.plane.z),
        req.plane.ground_z,
    )


def verify_request(req: PairRequest) -> Verification:
    """Validate-once entry point: request model -> arrays -> :func:`hmcc.pipeline.verify`."""
    return verify(to_pair_data(req), req.method, req.params)


_UNION_TAGS = {"local", "geodetic", "yaw_pitch_roll", "omega_phi_kappa", "matrix"}
_BRANCH_LABELS = re.compile(r"^(float|int|str|bool|literal\[.*\]|function-.*)$")


class FieldIssue(BaseModel):
    """One problem with a request: a dotted field path and the reason."""

    field: str
    reason: str


def _field_path(loc: tuple[int | str, ...]) -> str:
    """``("matches", 3, 1)`` -> ``"matches[3][1]"``; union tags are dropped."""
    path = ""
    for i, part in enumerate(loc):
        if isinstance(part, int):
            path += f"[{part}]"
        elif part in _UNION_TAGS and i > 0 and loc[i - 1] in ("position", "attitude"):
            continue
        elif _BRANCH_LABELS.match(part):
            continue
        else:
            path += f".{part}" if path else str(part)
    return path or "body"


def validation_issues(error: ValidationError | InputError) -> list[FieldIssue]:
    """What the caller must fix, one entry per problem, without internals."""
    if isinstance(error, InputError):
        return [FieldIssue(field=error.field, reason=error.reason)]
    # A dict keeps the first-seen order and dedupes in O(1): a body can carry ~10^5 errors.
    unique: dict[tuple[str, str], None] = {}
    for e in error.errors(include_url=False, include_input=False):
        key = (_field_path(tuple(e["loc"])), str(e["msg"]).removeprefix("Value error, "))
        unique.setdefault(key, None)
    return [FieldIssue(field=field, reason=reason) for field, reason in unique]
