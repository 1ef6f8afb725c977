"""The methods' names, without the methods: what a parser or a command line checks a name
against, importable without numba, SciPy or OpenCV (:data:`hmcc.methods.METHODS` maps the same
names, in the same order, to the methods themselves)."""

from __future__ import annotations

from typing import get_args

from .stage_options import EstimatorName

__all__ = ["DEFAULT_METHOD", "F_ONLY_METHODS", "METHOD_NAMES", "POS_METHODS", "model_refusal"]

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

#: The methods that fit a fundamental matrix only: with another ``params.ransac.model`` a flight
#: is refused when it is made (:func:`model_refusal`), before any pair is verified.
F_ONLY_METHODS = frozenset({DEFAULT_METHOD, "hmcc-lean"})


def model_refusal(method: str, model: str) -> str | None:
    """Why ``method`` does not fit ``model`` (``params.ransac.model``'s reason), or None."""
    if method in F_ONLY_METHODS and model != "fundamental":
        return f"{method} fits a fundamental matrix; name another method for {model!r}"
    return None
