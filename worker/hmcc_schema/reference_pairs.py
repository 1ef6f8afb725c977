"""Reading the reference pair files of ``shared/fixtures`` (brighton-beach / snowpeak layout).

Those files carry per-image ``K``, ``C_enu`` and ``R_world_to_cam`` instead of the public
format's ``camera`` and ``pose``; :func:`reference_to_pair` rewrites one into the public pair
format (a plain dict, no I/O), with ``Z0`` as the ground height (the plane goes below it)
and the reference inliers as ``ground_truth``.
"""

from __future__ import annotations

from typing import Any

from hmcc import InputError

__all__ = ["is_reference_pair", "reference_to_pair"]


def is_reference_pair(doc: dict[str, Any]) -> bool:
    """True for a reference pair file (its images have ``K`` and ``R_world_to_cam``)."""
    image = doc.get("image1")
    return isinstance(image, dict) and "K" in image and "R_world_to_cam" in image


def _image(record: dict[str, Any]) -> dict[str, Any]:
    k = record["K"]
    x, y, z = record["C_enu"]
    return {
        "camera": {
            "width": record["width"],
            "height": record["height"],
            "fx": k[0][0],
            "fy": k[1][1],
            "cx": k[0][2],
            "cy": k[1][2],
        },
        "pose": {
            "position": {"x": x, "y": y, "z": z},
            "attitude": {"matrix": record["R_world_to_cam"]},
        },
    }


def reference_to_pair(doc: dict[str, Any], plane_z: float | str | None = None) -> dict[str, Any]:
    """Public pair dict from a reference pair file: the file's ``Z0`` is the ground height (the
    plane goes below it, as the paper does); ``plane_z`` sets the plane itself instead.

    Raises :class:`hmcc.errors.InputError` naming the first missing field.
    """
    try:
        return _convert(doc, plane_z)
    except KeyError as e:
        raise InputError(str(e.args[0]), "missing from the reference pair file") from None
    except (IndexError, TypeError) as e:
        raise InputError("reference pair", f"malformed: {e}") from None


def _convert(doc: dict[str, Any], plane_z: float | str | None) -> dict[str, Any]:
    return {
        "image1": _image(doc["image1"]),
        "image2": _image(doc["image2"]),
        "keypoints1": doc["keypoints1"],
        "keypoints2": doc["keypoints2"],
        "matches": doc["matches"],
        "plane": {"ground_z": doc["Z0"]} if plane_z is None else {"z": plane_z},
        "ground_truth": {
            "inliers": sorted(doc["reference_inliers"]),
            "source": "automatic reference (MAGSAC++ F at 1 px), see the fixture README",
            "pair": f"{doc['image1']['id']}-{doc['image2']['id']}",
        },
    }
