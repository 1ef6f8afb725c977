"""hmcc_colmap: verify every matched pair of a COLMAP database (COLMAP >= 4 schema) and write
the verified two-view geometries back, so ``colmap mapper``, ``pycolmap.incremental_mapping``
or GLOMAP continue from the same file (``hmcc colmap``).

* :mod:`~hmcc_colmap.database`: the database in our conventions (cameras, keypoints with the
  pixel centre at (0, 0), matches) and the geometries written back;
* :mod:`~hmcc_colmap.guided_match`: :class:`~hmcc_colmap.guided_match.GuidedMatchRun`
  (``hmcc match``), the features matched guided by the rough POS and the matches written;
* :mod:`~hmcc_colmap.poses`: the rough poses, from the images' EXIF GPS and XMP or from a
  pose file (ODM geo.txt, CSV, JSON), positions from COLMAP's pose_priors;
* :mod:`~hmcc_colmap.tags`: the vendors' XMP attitude tags, one reader per tag family;
* :mod:`~hmcc_colmap.twoview`: a verified pair's relative pose, computed in the compute
  pool's child beside the verification;
* :mod:`~hmcc_colmap.verify`: :class:`ColmapRun`, one run chunk by chunk, here on the compute
  pool or through a running service, with its report;
* :mod:`~hmcc_colmap.pairs`: the pairs worth matching, by footprint overlap (``hmcc pairs``),
  with :mod:`~hmcc_colmap.capture` (EXIF camera, capture time, height above take-off) and
  :mod:`~hmcc_colmap.track` (an attitude estimated from the flight track for GPS-only images).

pycolmap (the ``colmap`` extra) is imported by this package only, and only with
:mod:`~hmcc_colmap.database` (this module's names below load it when first used): the pool's
children import :mod:`~hmcc_colmap.twoview` without it.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from .errors import ColmapInputError

if TYPE_CHECKING:
    from .verify import POS_METHODS, ColmapRun, RunOptions

__all__ = ["POS_METHODS", "ColmapInputError", "ColmapRun", "RunOptions"]


def __getattr__(name: str) -> Any:
    if name in ("POS_METHODS", "ColmapRun", "RunOptions"):
        return getattr(importlib.import_module(".verify", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
