"""The methods by name. Adding a method: write its module (a function of the pair, the options
and the stage recorder, see :class:`hmcc.stages.Method`), add one line here and its name to
:data:`hmcc.method_names.METHOD_NAMES`."""

from __future__ import annotations

from .gc_filter import verify_gc_ransac
from .lean import verify_lean
from .method_names import DEFAULT_METHOD, METHOD_NAMES, POS_METHODS
from .motion_filter import verify_hmcc, verify_hmcc_ransac
from .plus import verify_plus
from .ransac import ESTIMATOR_METHODS
from .stages import Method

__all__ = ["DEFAULT_METHOD", "METHODS", "METHOD_NAMES", "POS_METHODS"]

METHODS: dict[str, Method] = {
    DEFAULT_METHOD: verify_plus,  # HMCC ranks, a model on the most consistent, all decided
    "hmcc-lean": verify_lean,  # motions propose, one robust score selects (a candidate)
    "hmcc-ransac": verify_hmcc_ransac,  # the paper: HMCC filter, then RANSAC
    "hmcc": verify_hmcc,  # the HMCC filter alone
    "gc-ransac": verify_gc_ransac,  # Lu et al. (2016) pairwise vote, then RANSAC
    **ESTIMATOR_METHODS,  # one estimator on all matches: ransac, lo-ransac, magsac++, ...
}
