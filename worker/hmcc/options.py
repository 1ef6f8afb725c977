"""Every parameter of every stage, defaults in one place: :class:`VerifyOptions`.

Each stage's options live beside the stage (paper values as defaults, bounds declared on the
fields, see :mod:`hmcc.bounds`); this object gathers them, with the one seed every random stage
draws from. It is what a request's ``params`` holds and what a result echoes.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated, Literal

from annotated_types import Interval

from .bounds import PYDANTIC_CONFIG, check_fields
from .stage_options import (
    DirectionChangeOptions,
    DirectionOptions,
    GCOptions,
    GroundOptions,
    LeanOptions,
    LengthOptions,
    PlusOptions,
    RansacOptions,
)

__all__ = ["DEFAULT_OPTIONS", "VerifyOptions"]


@dataclass(frozen=True)
class VerifyOptions:
    """Every parameter of every stage (the paper's values; ``plus`` is ``hmcc-plus``'s own,
    ``lean`` ``hmcc-lean``'s)."""

    __pydantic_config__ = PYDANTIC_CONFIG

    seed: Annotated[int, Interval(ge=0, lt=2**31)] = 0
    ground: GroundOptions = field(default_factory=GroundOptions)
    direction: DirectionOptions = field(default_factory=DirectionOptions)
    direction_change: DirectionChangeOptions = field(default_factory=DirectionChangeOptions)
    length: LengthOptions = field(default_factory=LengthOptions)
    ransac: RansacOptions = field(default_factory=RansacOptions)
    gc: GCOptions = field(default_factory=GCOptions)
    plus: PlusOptions = field(default_factory=PlusOptions)
    lean: LeanOptions = field(default_factory=LeanOptions)
    #: What a result holds: ``full`` (stages, statistics, parameters) or only ``inliers`` (with
    #: the model and the total time), much smaller for a flight of thousands of pairs.
    result: Literal["full", "inliers"] = "full"
    #: Add ``motions`` to a full result: every match's motion on the plane and the stage that
    #: decided it (:func:`hmcc.motion_report.motion_report`), for drawing the paper's figures.
    return_motions: bool = False

    def __post_init__(self) -> None:
        check_fields(self)


DEFAULT_OPTIONS = VerifyOptions()
