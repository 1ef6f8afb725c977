"""Verify one pair: ``verify(pair, method, options)`` runs a method of :data:`hmcc.methods.METHODS`
on the pair's arrays and returns a :class:`Verification` (no I/O)."""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass, field
from importlib.metadata import version
from typing import Any, Literal

import cv2
import numpy as np

from .errors import InputError
from .methods import DEFAULT_METHOD, METHODS
from .motion_report import motion_report
from .options import DEFAULT_OPTIONS, VerifyOptions
from .pair import PairData
from .stages import StageReport, Stages

__all__ = ["ResultForm", "Verification", "unverified", "verify"]

#: ``full``: every key below; ``inliers``: only method, inliers, model and ``timings_ms.total``.
ResultForm = Literal["full", "inliers"]

_VERSIONS = {"hmcc": version("hmcc-match"), "opencv": cv2.__version__, "numpy": np.__version__}


@dataclass
class Verification:
    """Result: ``inliers`` (K,) int64 ascending indices into the input matches.

    ``survivors`` maps each stage to the indices of the input matches it kept (not part of the
    JSON result; for analysis such as which stage loses true matches). ``motions`` is
    :func:`hmcc.motion_report.motion_report`'s when ``options.return_motions`` is set.
    ``matches`` (M, 2) int64 and ``matching`` (the matcher's figures) of a pair that asked
    for matching (:mod:`hmcc.pair_matching`): ``inliers`` index those matches.
    """

    method: str
    inliers: np.ndarray
    model_type: str | None
    model_matrix: np.ndarray | None
    stages: list[StageReport]
    statistics: dict[str, Any]
    options: VerifyOptions
    survivors: dict[str, np.ndarray] = field(default_factory=dict)
    motions: dict[str, Any] | None = None
    matches: np.ndarray | None = None
    matching: dict[str, Any] | None = None

    @property
    def params(self) -> dict[str, Any]:
        """The resolved parameters as echoed in the result."""
        return _echo(self.options) | {"method": self.method}

    @property
    def timings_ms(self) -> dict[str, float]:
        """Each stage's wall time and ``total``, their sum (ms)."""
        timings = {s.name: s.time_ms for s in self.stages}
        timings["total"] = float(sum(timings.values()))
        return timings

    def to_dict(self, form: ResultForm | None = None, inliers: bool = True) -> dict[str, Any]:
        """JSON-ready result in the public format, in the form ``options.result`` asks for
        unless ``form`` is given (see :data:`ResultForm`); without its ``inliers`` for a
        caller that takes them as the array (a list of thousands of numbers costs more than
        the rest of the result)."""
        form = form or self.options.result
        model = {
            "type": self.model_type,
            "matrix": None if self.model_matrix is None else self.model_matrix.tolist(),
        }
        head: dict[str, Any] = {"method": self.method}
        if self.matches is not None:
            head["matches"] = self.matches.tolist()
        if inliers:
            head["inliers"] = self.inliers.tolist()
        if form == "inliers":
            total = float(sum(s.time_ms for s in self.stages))
            short = head | {"model": model, "timings_ms": {"total": total}}
            if self.matching is not None:
                short["matching"] = {k: v for k, v in self.matching.items() if k != "params"}
            return short
        full = head | {
            "model": model,
            "stages": [
                {
                    "name": s.name,
                    "input": s.input,
                    "kept": s.kept,
                    "time_ms": s.time_ms,
                    "stats": s.stats,
                }
                for s in self.stages
            ],
            "timings_ms": self.timings_ms,
            "statistics": self.statistics,
            "params": self.params,
        }
        if self.motions is not None:
            full["motions"] = self.motions
        if self.matching is not None:
            full["matching"] = self.matching
        return full


@functools.lru_cache(maxsize=64)
def _echo(options: VerifyOptions) -> dict[str, Any]:
    """``asdict`` of options costs about as much as a small pair's verification stage; a flight
    verifies thousands of pairs with the same options."""
    return dataclasses.asdict(options)


def verify(
    pair: PairData, method: str = DEFAULT_METHOD, options: VerifyOptions | None = None
) -> Verification:
    """Verify the matches of one pair; raises :class:`InputError` for input it cannot use."""
    run = METHODS.get(method)
    if run is None:
        raise InputError("method", f"unknown method {method!r}; one of {list(METHODS)}")
    stages = Stages()
    found = run(pair, options or DEFAULT_OPTIONS, stages)
    m = len(pair.matches)
    inliers = np.sort(found.inliers).astype(np.int64)
    statistics = {
        "matches": m,
        **found.statistics,
        "inliers": len(inliers),
        "inlier_ratio": len(inliers) / m if m else 0.0,
        "versions": _VERSIONS,
    }
    motions = None
    if found.options.return_motions:
        motions = motion_report(pair, found.options, stages.reports, stages.survivors, inliers)
    return Verification(
        method,
        inliers,
        found.model_type,
        found.matrix,
        stages.reports,
        statistics,
        found.options,
        stages.survivors,
        motions,
    )


def unverified(method: str, options: VerifyOptions, matches: int, reason: str) -> Verification:
    """The result of ``matches`` matches the method could not verify (too few for its model,
    ``reason``): no inliers, no model, no stages."""
    statistics = {
        "matches": matches,
        "inliers": 0,
        "inlier_ratio": 0.0,
        "unverified": reason,
        "versions": _VERSIONS,
    }
    return Verification(method, np.zeros(0, np.int64), None, None, [], statistics, options)
