"""COLMAP databases for the tests: built by hand from simulated pairs (exact truth), and the
bytes of a database to check that a refused run left it untouched."""

from __future__ import annotations

import hashlib
import sqlite3
from pathlib import Path
from typing import Any

import numpy as np
import orjson
import pycolmap

from hmcc.simulate import SimulationOptions, simulate_pair


def sim_pair(seed: int = 1, **kw: Any) -> dict[str, Any]:
    return simulate_pair(SimulationOptions(n_inliers=300, outlier_ratio=0.5, **kw), seed=seed)


def db_from_pairs(
    path: Path,
    pairs: list[dict[str, Any]],
    *,
    prior_focal: bool = False,
    matches: bool = True,
) -> list[int]:
    """A COLMAP database of the simulated ``pairs`` (images ``p{k}a.jpg`` and ``p{k}b.jpg``
    of pair k): PINHOLE cameras, keypoints and matches in COLMAP's pixels (ours + 0.5).
    Returns the image ids in order a, b of each pair."""
    db = pycolmap.Database.open(str(path))
    ids = []
    try:
        for k, pair in enumerate(pairs):
            pair_ids = []
            for side in (1, 2):
                c = pair[f"image{side}"]["camera"]
                camera = pycolmap.Camera(
                    model="PINHOLE",
                    width=c["width"],
                    height=c["height"],
                    params=[c["fx"], c["fy"], c["cx"] + 0.5, c["cy"] + 0.5],
                )
                camera.has_prior_focal_length = prior_focal
                camera_id = db.write_camera(camera)
                name = f"p{k}{'ab'[side - 1]}.jpg"
                image_id = db.write_image(pycolmap.Image(name=name, camera_id=camera_id))
                kps = np.asarray(pair[f"keypoints{side}"], dtype=np.float64)[:, :2] + 0.5
                db.write_keypoints(image_id, kps.astype(np.float32))
                pair_ids.append(image_id)
            if matches:
                db.write_matches(*pair_ids, np.asarray(pair["matches"], dtype=np.uint32))
            ids.extend(pair_ids)
    finally:
        db.close()
    return ids


def pose_file(path: Path, pairs: list[dict[str, Any]], skip: set[str] = frozenset()) -> Path:  # type: ignore[assignment]
    """A JSON pose file (name -> the pair's API pose) of the images of :func:`db_from_pairs`."""
    doc = {
        f"p{k}{'ab'[side - 1]}.jpg": pair[f"image{side}"]["pose"]
        for k, pair in enumerate(pairs)
        for side in (1, 2)
    }
    path.write_bytes(orjson.dumps({k: v for k, v in doc.items() if k not in skip}))
    return path


def rows(path: Path) -> dict[tuple[int, int], tuple[int, int, bool, bool]]:
    """(image_id1, image_id2) -> the raw two_view_geometries row: (config, inlier rows, F
    stored, E stored)."""
    con = sqlite3.connect(path)
    try:
        found = con.execute(
            "SELECT pair_id, config, rows, F IS NOT NULL, E IS NOT NULL FROM two_view_geometries"
        ).fetchall()
    finally:
        con.close()
    return {
        tuple(pycolmap.pair_id_to_image_pair(p)): (c, n, bool(f), bool(e))  # type: ignore[misc]
        for p, c, n, f, e in found
    }


def geometry(path: Path, image_id1: int, image_id2: int) -> pycolmap.TwoViewGeometry:
    db = pycolmap.Database.open(str(path))
    try:
        return db.read_two_view_geometry(image_id1, image_id2)
    finally:
        db.close()


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()
