"""The methods' names, without the methods: what a parser or a command line checks a name
against, importable without numba, SciPy or OpenCV (:data:`hmcc.methods.METHODS` maps the same
names, in the same order, to the methods themselves)."""

from __future__ import annotations

from typing import get_args

from .stage_options import EstimatorName

__all__ = ["DEFAULT_METHOD", "METHOD_NAMES", "POS_METHODS"]

DEFAULT_METHOD = "hmcc-plus"

#: Every method's name, as :data:`hmcc.methods.METHODS` orders them: the HMCC methods, the
#: pairwise vote, then one estimator on all matches.
METHOD_NAMES: tuple[str, ...] = (
    DEFAULT_METHOD,
    "hmcc-lean",
    "hmcc-ransac",
    "hmcc",
    "gc-ransac",
    *get_args(EstimatorName),
)

#: The methods that use the rough poses (the others ignore them): a new HMCC method goes here
#: too, so that callers that read poses (``hmcc colmap``) give it them.
POS_METHODS = frozenset({DEFAULT_METHOD, "hmcc-lean", "hmcc-ransac", "hmcc"})
