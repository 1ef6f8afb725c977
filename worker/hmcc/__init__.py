"""hmcc: geometric verification of UAV feature matches with rough POS (HMCC-RANSAC).

The core: pure numpy/SciPy/OpenCV/numba on arrays, no I/O. Typical use::

    from hmcc import PairData, verify
    result = verify(pair)                      # hmcc-plus, the default method
    result.inliers, result.model_matrix, result.to_dict()

A JSON pair (the service's format) becomes a :class:`PairData` with ``hmcc_schema.parse_pair``.
"""

from __future__ import annotations

from importlib.metadata import version

from .camera import Camera
from .errors import InputError
from .methods import DEFAULT_METHOD, METHODS
from .options import VerifyOptions
from .pair import PairData
from .pose import Pose
from .verification import Verification, verify

__all__ = [
    "DEFAULT_METHOD",
    "METHODS",
    "Camera",
    "InputError",
    "PairData",
    "Pose",
    "Verification",
    "VerifyOptions",
    "__version__",
    "verify",
]

__version__ = version("hmcc-match")
