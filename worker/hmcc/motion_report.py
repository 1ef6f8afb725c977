"""What each stage decided about each match, with its motion on the plane: the data of the
paper's Figs. 7, 8, 10 and 12 (motions coloured by stage decision), returned in a result when
``params.return_motions`` is set, so that front ends (and ``hmcc plot``) can draw them.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from .errors import InputError
from .pair import PairData
from .projection import project_pair, project_to_plane
from .stages import StageReport

if TYPE_CHECKING:
    from .options import VerifyOptions

__all__ = ["INLIER", "motion_report"]

#: The decision of a match that is among the method's final inliers.
INLIER = "inlier"


def motion_report(
    pair: PairData,
    options: VerifyOptions,
    stages: list[StageReport],
    survivors: dict[str, np.ndarray],
    inliers: np.ndarray,
) -> dict[str, Any]:
    """JSON-ready motions of every match and the stage that decided it.

    * ``z0_m``: the plane (the projection stage's; for methods without one, the plane the
      pair's ``plane`` gives, as the HMCC methods would choose it);
    * ``start``, ``end``: (M,) ``[x, y]`` in metres on the plane (world frame), or null where a
      ray misses the plane; ``direction_deg`` (counter-clockwise from east, [0, 360)) and
      ``length_m`` likewise;
    * ``stages``: the stages that keep a subset of the matches, in order;
    * ``decision``: (M,) ``"inlier"`` for a final inlier, else the first stage (of ``stages``)
      that did not keep the match. In ``hmcc-plus`` the refine stage decides every match
      again, so a match outside the consistency stage's candidates can still be an inlier.

    When the plane cannot be found (a method without projection on a pair whose automatic
    plane fails), ``error`` says why and there are no motions.
    """
    px1, px2 = pair.matched_pixels()
    m = len(px1)
    report: dict[str, Any] = {}
    z0: float | None
    projection = next((s for s in stages if s.name == "projection"), None)
    try:
        if projection is not None:
            z0 = float(projection.stats["z0_m"])
            start, ok1 = project_to_plane(pair.camera1, pair.pose1, px1, z0)
            end, ok2 = project_to_plane(pair.camera2, pair.pose2, px2, z0)
            valid = ok1 & ok2
        else:
            motions, valid, stats = project_pair(pair, px1, px2, options.ground)
            z0 = float(stats["z0_m"])
            start = np.full((m, 2), np.nan)
            end = np.full((m, 2), np.nan)
            start[valid], end[valid] = motions.start, motions.end
    except InputError as e:
        report["error"] = f"{e.field}: {e.reason}"
        start = end = np.full((m, 2), np.nan)
        valid = np.zeros(m, dtype=bool)
        z0 = None
    vector = end - start
    direction = np.mod(np.degrees(np.arctan2(vector[:, 1], vector[:, 0])), 360.0)
    length = np.hypot(vector[:, 0], vector[:, 1])
    order = [name for name in survivors if survivors[name] is not None]
    decision = np.full(m, "", dtype=object)
    undecided = np.ones(m, dtype=bool)
    for name in order:
        kept = np.zeros(m, dtype=bool)
        kept[survivors[name]] = True
        removed = undecided & ~kept
        decision[removed] = name
        undecided &= kept
    final = np.zeros(m, dtype=bool)
    final[inliers] = True
    decision[final] = INLIER
    decision[undecided & ~final] = order[-1] if order else "method"

    def rows(values: np.ndarray) -> list[Any]:
        return [None if not ok else v for ok, v in zip(valid, values.tolist(), strict=True)]

    report.update(
        {
            "z0_m": z0,
            "stages": order,
            "start": rows(start),
            "end": rows(end),
            "direction_deg": rows(direction),
            "length_m": rows(length),
            "decision": decision.tolist(),
        }
    )
    return report
