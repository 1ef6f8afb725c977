"""The methods by name. Adding a method: write its module (a function of the pair, the options
and the stage recorder, see :class:`hmcc.stages.Method`) and add one line here."""

from __future__ import annotations

from .gc_filter import verify_gc_ransac
from .lean import verify_lean
from .motion_filter import verify_hmcc, verify_hmcc_ransac
from .plus import verify_plus
from .ransac import ESTIMATOR_METHODS
from .stages import Method

__all__ = ["DEFAULT_METHOD", "METHODS", "POS_METHODS"]

DEFAULT_METHOD = "hmcc-plus"

METHODS: dict[str, Method] = {
    DEFAULT_METHOD: verify_plus,  # HMCC ranks, a model on the most consistent, all decided
    "hmcc-lean": verify_lean,  # motions propose, one robust score selects (a candidate)
    "hmcc-ransac": verify_hmcc_ransac,  # the paper: HMCC filter, then RANSAC
    "hmcc": verify_hmcc,  # the HMCC filter alone
    "gc-ransac": verify_gc_ransac,  # Lu et al. (2016) pairwise vote, then RANSAC
    **ESTIMATOR_METHODS,  # one estimator on all matches: ransac, lo-ransac, magsac++, ...
}

#: The methods that use the rough poses (the others ignore them): a new HMCC method goes here
#: too, so that callers that read poses (``hmcc colmap``) give it them.
POS_METHODS = frozenset({DEFAULT_METHOD, "hmcc-lean", "hmcc-ransac", "hmcc"})
