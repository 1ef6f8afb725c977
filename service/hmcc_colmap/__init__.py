"""hmcc_colmap: verify every matched pair of a COLMAP database (COLMAP >= 4 schema) and write
the verified two-view geometries back, so ``colmap mapper``, ``pycolmap.incremental_mapping``
or GLOMAP continue from the same file (``hmcc colmap``).

* :mod:`~hmcc_colmap.database`: the database in our conventions (cameras, keypoints with the
  pixel centre at (0, 0), matches) and the geometries written back;
* :mod:`~hmcc_colmap.poses`: the rough poses, from the images' EXIF GPS and DJI XMP or from a
  pose file (ODM geo.txt, CSV, JSON), positions from COLMAP's pose_priors;
* :mod:`~hmcc_colmap.verify`: :class:`ColmapRun`, one run chunk by chunk, here on the compute
  pool or through a running service, with its report.

pycolmap (the ``colmap`` extra) is imported by this package only.
"""

from __future__ import annotations

from .errors import ColmapInputError
from .verify import POS_METHODS, ColmapRun, RunOptions

__all__ = ["POS_METHODS", "ColmapInputError", "ColmapRun", "RunOptions"]
