"""What a method is: a function of a pair and the options that records timed stages and returns
its inliers and model (:class:`MethodResult`); :func:`hmcc.verification.verify` looks methods up
in :data:`hmcc.methods.METHODS`."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

if TYPE_CHECKING:
    from .options import VerifyOptions
    from .pair import PairData

__all__ = ["Method", "MethodResult", "Stage", "StageReport", "Stages"]


@dataclass(frozen=True)
class StageReport:
    """One stage: matches in, matches kept, wall time (ms) and the stage's statistics."""

    name: str
    input: int
    kept: int
    time_ms: float
    stats: dict[str, Any]


class Stages:
    """Times stages and records what went in and what was kept::

    with stages.stage("direction", n_in) as st:
        keep, stats = vote_directions(...)
        st.done(keep, stats)
    stages.survivors["direction"] = indices kept (into the input matches)
    """

    def __init__(self) -> None:
        self.reports: list[StageReport] = []
        self.survivors: dict[str, np.ndarray] = {}

    def stage(self, name: str, n_in: int) -> Stage:
        return Stage(self.reports, name, n_in)


class Stage:
    """One timed stage (a plain context manager: ``contextlib``'s costs a few us per use)."""

    def __init__(self, reports: list[StageReport], name: str, n_in: int) -> None:
        self.reports, self.name, self.n_in = reports, name, n_in
        self.keep: np.ndarray = np.zeros(0, dtype=bool)
        self.stats: dict[str, Any] = {}

    def __enter__(self) -> Stage:
        self.t0 = time.perf_counter()
        return self

    def __exit__(self, *exc: object) -> None:
        ms = (time.perf_counter() - self.t0) * 1e3
        kept = int(np.count_nonzero(self.keep))
        self.reports.append(StageReport(self.name, self.n_in, kept, ms, self.stats))

    def done(self, keep: np.ndarray, stats: dict[str, Any]) -> np.ndarray:
        """Record the (n_in,) keep mask and the statistics; returns ``keep``."""
        self.keep, self.stats = keep, stats
        return keep


@dataclass
class MethodResult:
    """What a method found: ``inliers`` (K,) int indices into the input matches (any order),
    the model (``model_type`` None and ``matrix`` None for a filter without a model), the
    method's statistics, and the options it actually used (echoed in the result)."""

    inliers: np.ndarray
    model_type: str | None
    matrix: np.ndarray | None
    statistics: dict[str, Any]
    options: VerifyOptions


class Method(Protocol):
    """A verification method: raises :class:`hmcc.errors.InputError` for input it cannot use."""

    def __call__(self, pair: PairData, options: VerifyOptions, stages: Stages) -> MethodResult: ...
