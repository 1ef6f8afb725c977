"""hmcc: geometric verification of UAV feature matches with rough POS (HMCC-RANSAC).

The core: pure numpy/SciPy/OpenCV/numba on arrays, no I/O. Typical use::

    from hmcc import PairData, verify
    result = verify(pair)                      # hmcc-plus, the default method
    result.inliers, result.model_matrix, result.to_dict()

A JSON pair (the service's format) becomes a :class:`PairData` with ``hmcc_schema.parse_pair``.
"""

from __future__ import annotations

from importlib.metadata import version
from typing import TYPE_CHECKING, Any

from .camera import Camera
from .errors import InputError
from .method_names import DEFAULT_METHOD
from .options import VerifyOptions
from .pair import PairData
from .pose import Pose

if TYPE_CHECKING:
    from .methods import METHODS
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

#: Imported on first use (PEP 562): the methods bring numba, SciPy and OpenCV, which a process
#: that only parses and hands out pairs (``hmcc flight``'s parent) does not need.
_LAZY = {"METHODS": "methods", "Verification": "verification", "verify": "verification"}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
