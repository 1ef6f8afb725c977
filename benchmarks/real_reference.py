"""The real-data reference of ``bench_real``: every raw match of the Brighton Beach images
labelled by a bundle-adjusted reconstruction, not by one estimator's inlier set (issue #29).

* **Features and matches**: COLMAP's SIFT (pycolmap, CPU, :data:`MAX_IMAGE_SIZE`, one shared
  camera) and exhaustive matching without geometric verification, built as
  ``bench_colmap.raw_database`` builds it (COLMAP's matching defaults: ratio 0.8, cross-check);
  the relaxed sets (:data:`MATCHING_SETS`) match the same features again with a looser ratio
  test and no cross-check.
* **Reconstruction**: a copy of the strict database verified by
  ``pycolmap.geometric_verification`` (COLMAP's defaults) and mapped by
  ``pycolmap.incremental_mapping`` (its defaults: global bundle adjustment as it grows and at
  the end, refined focal length and radial distortion), COLMAP's random seed fixed
  (:data:`SEED`). The largest model's cameras and poses are the reference: a committed,
  compact file (:data:`REFERENCE_FILE`) with pycolmap's version and the options.
* **Labels**: a raw match is true when its Sampson distance to the pair's relative pose in that
  model is under the threshold (:func:`label_matches`), on pixels undistorted with the model's
  own camera (:func:`undistorted_pixels`). The Sampson distance is the one the estimators
  score with (``hmcc.ransac.sampson_distance``: ``|x2^T F x1| / sqrt(|F x1|_12^2 +
  |F^T x2|_12^2)``, pixels). A pair with an unregistered image has no label.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import sqlite3
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hmcc.ransac import sampson_distance

from .common import REPO

__all__ = [
    "LABEL_THRESHOLDS_PX",
    "MATCHING_SETS",
    "MAX_IMAGE_SIZE",
    "REFERENCE_FILE",
    "REFERENCE_THRESHOLD_PX",
    "SEED",
    "MatchingSet",
    "Reference",
    "build_reference",
    "fundamental_from_poses",
    "label_matches",
    "load_reference",
    "matched_database",
]

#: Longer image side for SIFT (the images are 2000 x 1125; keypoints are in the full frame).
MAX_IMAGE_SIZE = 1600
#: COLMAP's random seed (``pycolmap.set_random_seed``) for matching and mapping.
SEED = 0
#: A match is true under this Sampson distance (px) to the reference's relative pose.
REFERENCE_THRESHOLD_PX = 2.0
#: The labels' sensitivity: the same at these thresholds too.
LABEL_THRESHOLDS_PX = (1.0, 2.0, 4.0)
REFERENCE_FILE = REPO / "benchmarks" / "data" / "brighton_reference.json"


@dataclass(frozen=True)
class MatchingSet:
    """How the raw matches are made: COLMAP's ratio test (``max_ratio``) and cross-check."""

    name: str
    max_ratio: float
    cross_check: bool


#: COLMAP's defaults (``strict``), then the looser ratio tests: more true matches, many more
#: outliers. COLMAP's other matching options (``max_distance`` 0.7, ...) keep their defaults.
MATCHING_SETS = (
    MatchingSet("strict", 0.8, True),
    MatchingSet("ratio 0.9", 0.9, False),
    MatchingSet("ratio 0.95", 0.95, False),
)


def _pycolmap() -> Any:
    import pycolmap

    return pycolmap


def matched_database(
    images: Path, cache: Path, matching: MatchingSet, max_size: int = MAX_IMAGE_SIZE
) -> tuple[Path, float]:
    """The unverified database of ``images`` under ``matching`` (cached in ``cache``); the
    seconds it took to build, 0 if cached. The strict one is ``bench_colmap``'s raw database
    at ``max_size``; a relaxed one is a copy of it whose matches are made again. (Keypoints
    are in the images' full frame whatever ``max_size``.)"""
    from .bench_colmap import raw_database

    pycolmap = _pycolmap()
    pycolmap.set_random_seed(SEED)
    strict, build_s = raw_database(images, cache, max_size)
    if matching.max_ratio == 0.8 and matching.cross_check:
        return strict, build_s
    tag = f"ratio{matching.max_ratio:g}-{'cross' if matching.cross_check else 'nocross'}"
    path = strict.with_name(f"{strict.stem}-{tag}.db")
    if path.is_file():
        return path, build_s
    partial = path.with_suffix(".partial")
    shutil.copy(strict, partial)
    con = sqlite3.connect(partial)
    try:
        con.execute("DELETE FROM matches")
        con.execute("DELETE FROM two_view_geometries")
        con.commit()
    finally:
        con.close()
    t0 = time.perf_counter()
    options = pycolmap.FeatureMatchingOptions()
    options.skip_geometric_verification = True
    options.sift.max_ratio = matching.max_ratio
    options.sift.cross_check = matching.cross_check
    pycolmap.match_exhaustive(partial, matching_options=options, device=pycolmap.Device.cpu)
    partial.rename(path)
    return path, build_s + time.perf_counter() - t0


# --------------------------------------------------------------------------- the reference


@dataclass(frozen=True)
class Reference:
    """The bundle-adjusted model: per registered image name, its camera (COLMAP model name and
    parameters, COLMAP's pixels: the top-left pixel's centre at (0.5, 0.5)) and its pose
    ``x_cam = R X + t``; the images it did not register; how it was made (``meta``)."""

    cameras: Mapping[str, tuple[str, int, int, np.ndarray]]
    poses: Mapping[str, tuple[np.ndarray, np.ndarray]]
    unregistered: tuple[str, ...]
    meta: Mapping[str, Any]

    def registered(self, name: str) -> bool:
        return name in self.poses

    def fundamental(self, name1: str, name2: str) -> np.ndarray:
        """F of the pair in undistorted pixels (``x2^T F x1 = 0``; COLMAP's pixels)."""
        (r1, t1), (r2, t2) = self.poses[name1], self.poses[name2]
        return fundamental_from_poses(
            self.calibration(name1), r1, t1, self.calibration(name2), r2, t2
        )

    def calibration(self, name: str) -> np.ndarray:
        """(3, 3) K of the image's camera (its undistorted pixels)."""
        return _calibration(*self.cameras[name][:2], self.cameras[name][3])

    def undistorted(self, name: str, pixels: np.ndarray) -> np.ndarray:
        """(N, 2) COLMAP pixels of image ``name`` -> undistorted pixels (same K)."""
        model, width, height, params = self.cameras[name]
        return undistorted_pixels(model, width, height, params, pixels)

    def labels(
        self, name1: str, name2: str, px1: np.ndarray, px2: np.ndarray, threshold_px: float
    ) -> np.ndarray:
        """(N,) bool: the (N, 2) matched COLMAP pixels within ``threshold_px`` (Sampson)."""
        f = self.fundamental(name1, name2)
        return label_matches(
            f, self.undistorted(name1, px1), self.undistorted(name2, px2), threshold_px
        )

    def distances(self, name1: str, name2: str, px1: np.ndarray, px2: np.ndarray) -> np.ndarray:
        """(N,) Sampson distances (px) of the matched COLMAP pixels to the pair's pose."""
        f = self.fundamental(name1, name2)
        return sampson_distance(f, self.undistorted(name1, px1), self.undistorted(name2, px2))


def fundamental_from_poses(
    k1: np.ndarray, r1: np.ndarray, t1: np.ndarray, k2: np.ndarray, r2: np.ndarray, t2: np.ndarray
) -> np.ndarray:
    """F (``x2^T F x1 = 0``, pixels) of two cameras ``x_cam = R X + t`` with calibrations K."""
    r = r2 @ r1.T  # cam2_from_cam1
    t = t2 - r @ t1
    tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    f: np.ndarray = np.linalg.inv(k2).T @ tx @ r @ np.linalg.inv(k1)
    return f / np.linalg.norm(f)


def label_matches(f: np.ndarray, p1: np.ndarray, p2: np.ndarray, threshold_px: float) -> np.ndarray:
    """(N,) bool: (N, 2) undistorted pixel correspondences whose Sampson distance to F is under
    ``threshold_px`` (the reference's truth)."""
    return np.asarray(sampson_distance(f, p1, p2) < threshold_px)


def _calibration(model: str, width: int, params: np.ndarray) -> np.ndarray:
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        fx = fy = params[0]
        cx, cy = params[1], params[2]
    elif model in ("PINHOLE", "OPENCV"):
        fx, fy, cx, cy = params[:4]
    else:
        raise ValueError(f"camera model {model} is not supported here")
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def undistorted_pixels(
    model: str, width: int, height: int, params: np.ndarray, pixels: np.ndarray
) -> np.ndarray:
    """(N, 2) pixels of a COLMAP camera -> the pixels of its pinhole part (COLMAP's own
    ``cam_from_img``, then K)."""
    pycolmap = _pycolmap()
    camera = pycolmap.Camera(
        model=model, width=width, height=height, params=np.asarray(params, dtype=np.float64)
    )
    normalized = np.asarray(camera.cam_from_img(np.asarray(pixels, dtype=np.float64)))
    k = _calibration(model, width, params)
    return np.asarray(normalized[:, :2] * np.diag(k)[:2] + k[:2, 2])


def build_reference(
    raw: Path,
    images: Path,
    work: Path,
    title: str = "Brighton Beach",
    max_size: int = MAX_IMAGE_SIZE,
) -> dict[str, Any]:
    """Verify a copy of the strict ``raw`` database with COLMAP's defaults, map it and return
    the largest model as the reference file's document."""
    pycolmap = _pycolmap()
    work.mkdir(parents=True, exist_ok=True)
    db = work / "verified.db"
    shutil.copy(raw, db)
    pycolmap.set_random_seed(SEED)
    t0 = time.perf_counter()
    pycolmap.geometric_verification(db)
    options = pycolmap.IncrementalPipelineOptions()
    models = pycolmap.incremental_mapping(db, images, work / "sparse", options)
    seconds = time.perf_counter() - t0
    if not models:
        raise RuntimeError("incremental mapping made no model")
    best = max(models.values(), key=lambda m: m.num_reg_images())
    names = sorted(p.name for p in images.iterdir() if p.suffix.upper() in (".JPG", ".JPEG"))
    doc_images: dict[str, Any] = {}
    for image in best.images.values():
        if not image.has_pose:
            continue
        camera = best.cameras[image.camera_id]
        pose = image.cam_from_world()
        doc_images[image.name] = {
            "camera": {
                "model": camera.model.name,
                "width": int(camera.width),
                "height": int(camera.height),
                "params": [float(v) for v in camera.params],
            },
            "R": np.asarray(pose.rotation.matrix()).round(12).tolist(),
            "t": np.asarray(pose.translation).ravel().round(9).tolist(),
        }
    return {
        "what": (
            f"{title}, {len(names)} images: COLMAP's bundle-adjusted model (largest), cameras "
            "in COLMAP's pixels (top-left pixel centre at 0.5, 0.5), poses x_cam = R X + t"
        ),
        "pycolmap": pycolmap.__version__,
        "seed": SEED,
        "max_image_size": max_size,
        "features": "pycolmap.extract_features, CPU, CameraMode.SINGLE, defaults otherwise",
        "matching": "pycolmap.match_exhaustive, CPU, defaults (ratio 0.8, cross-check)",
        "verification": "pycolmap.geometric_verification, defaults",
        "mapping": "pycolmap.incremental_mapping, IncrementalPipelineOptions() defaults",
        "raw_database_sha1": _matches_digest(raw),
        "models": len(models),
        "registered": len(doc_images),
        "unregistered": [n for n in names if n not in doc_images],
        "points3d": best.num_points3D(),
        "reprojection_error_px": round(float(best.compute_mean_reprojection_error()), 4),
        "track_length": round(float(best.compute_mean_track_length()), 3),
        "build_s": round(seconds, 1),
        "images": doc_images,
    }


def _matches_digest(db: Path) -> str:
    """SHA-1 of a database's keypoints and matches (whether a rebuilt one is the same)."""
    digest = hashlib.sha1()
    con = sqlite3.connect(db)
    try:
        for row in con.execute("SELECT image_id, data FROM keypoints ORDER BY image_id"):
            digest.update(str(row[0]).encode() + (row[1] or b""))
        for row in con.execute("SELECT pair_id, data FROM matches ORDER BY pair_id"):
            digest.update(str(row[0]).encode() + (row[1] or b""))
    finally:
        con.close()
    return digest.hexdigest()[:16]


def load_reference(path: Path = REFERENCE_FILE) -> Reference:
    """The committed reference file."""
    doc = json.loads(path.read_text())
    cameras, poses = {}, {}
    for name, image in doc["images"].items():
        cam = image["camera"]
        params = np.asarray(cam["params"], dtype=np.float64)
        cameras[name] = (cam["model"], int(cam["width"]), int(cam["height"]), params)
        poses[name] = (np.asarray(image["R"], dtype=np.float64), np.asarray(image["t"]))
    meta = {k: v for k, v in doc.items() if k != "images"}
    return Reference(cameras, poses, tuple(doc["unregistered"]), meta)
