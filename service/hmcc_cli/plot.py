"""``hmcc plot``: one pair's motions and votes as a PNG, the paper's figures for any pair.

Panels (from a full result with ``motions``, see ``params.return_motions``):

(a) the motions on the plane, coloured by the stage that decided them (Figs. 7, 8, 10, 12);
(b) the global direction vote: the direction stage's histogram with its selected bins
    (Fig. 9); for methods without that stage (``hmcc-plus``), the directions of every motion
    and of the inliers;
(c) the direction-change vote: the direction_change stage's histogram with its selected bins
    (Fig. 11); without that stage, the motion lengths of every match and of the inliers;
(d), (e) every match's keypoint in image 1 and image 2, the final inliers highlighted;
(f) the inliers' motions alone (the reduced set, Fig. 12).

Needs matplotlib (the ``plot`` extra: ``scripts/bootstrap plot`` in the checkout); imported
only when a plot is drawn.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["DECISION_COLOURS", "draw_motions"]

#: Colour of each decision: the paper draws kept motions green and removed ones red; we tell
#: the stages apart.
DECISION_COLOURS: dict[str, str] = {
    "inlier": "#1a9850",
    "projection": "#999999",
    "direction": "#d73027",
    "direction_change": "#fc8d59",
    "length": "#fee08b",
    "ransac": "#4575b4",
    "gc": "#d73027",
    "consistency": "#d73027",
    "model": "#fc8d59",
    "refine": "#4575b4",
    "fallback": "#762a83",
}


def _points(rows: list[Any]) -> np.ndarray:
    return np.array([[np.nan, np.nan] if r is None else r for r in rows], dtype=float).reshape(
        -1, 2
    )


def _stage(result: dict[str, Any], name: str) -> dict[str, Any] | None:
    for stage in result.get("stages") or []:
        if stage["name"] == name:
            return dict(stage["stats"])
    return None


def _vote_panel(ax: Any, stats: dict[str, Any], bin_deg: float, title: str) -> None:
    """A stage's histogram, selected bins dark, the others light, the peak marked."""
    hist = np.asarray(stats["histogram"], dtype=float)
    selected = np.zeros(len(hist), dtype=bool)
    selected[np.asarray(stats.get("selected_bins", []), dtype=int)] = True
    left = np.arange(len(hist)) * bin_deg
    ax.bar(left[~selected], hist[~selected], width=bin_deg, align="edge", color="#bbbbbb")
    ax.bar(left[selected], hist[selected], width=bin_deg, align="edge", color="#1a9850")
    peak = int(stats["peak_bin"])
    ax.annotate("peak", (left[peak] + bin_deg / 2, hist[peak]), ha="center", va="bottom")
    ax.set_title(title, fontsize=9)
    ax.set_ylabel("votes")


def draw_motions(doc: dict[str, Any], result: dict[str, Any], path: Path) -> None:
    """Write the PNG of one pair: ``doc`` the public pair dict (keypoints, matches, cameras),
    ``result`` its full result with ``motions``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection

    motions = result["motions"]
    start, end = _points(motions["start"]), _points(motions["end"])
    decision = np.asarray(motions["decision"], dtype=object)
    inlier = decision == "inlier"
    fig, axes = plt.subplots(2, 3, figsize=(16, 10))
    (a, b, c), (d, e, f) = axes
    order = [*motions["stages"], "inlier"]
    for name in dict.fromkeys(order):
        chosen = (decision == name) & np.isfinite(start).all(axis=1)
        if not chosen.any():
            continue
        colour = DECISION_COLOURS.get(name, "#444444")
        segments = list(np.stack((start[chosen], end[chosen]), axis=1))
        label = f"{'kept (inlier)' if name == 'inlier' else 'removed by ' + name}: {chosen.sum()}"
        a.add_collection(LineCollection(segments, colors=colour, linewidths=0.8, label=label))
        a.scatter(*start[chosen].T, s=3, color=colour)
    a.set_aspect("equal", adjustable="datalim")
    a.legend(fontsize=7, loc="best")
    a.set_title(f"(a) motions on Z0 = {motions['z0_m']:.1f} m, by stage decision", fontsize=9)
    a.set_xlabel("east (m)")
    a.set_ylabel("north (m)")

    direction = np.asarray(
        [np.nan if v is None else v for v in motions["direction_deg"]], dtype=float
    )
    length = np.asarray([np.nan if v is None else v for v in motions["length_m"]], dtype=float)
    stats = _stage(result, "direction")
    params = result.get("params") or {}
    if stats is not None and "histogram" in stats:
        bin_deg = float(params.get("direction", {}).get("bin_deg", 10.0))
        _vote_panel(b, stats, bin_deg, "(b) global direction vote (selected bins green)")
        b.set_xlabel("direction (deg, counter-clockwise from east)")
    else:
        bins = np.arange(0.0, 361.0, 10.0)
        b.hist(direction[np.isfinite(direction)], bins=bins, color="#bbbbbb", label="all")
        b.hist(direction[inlier & np.isfinite(direction)], bins=bins, color="#1a9850")
        b.set_title("(b) motion directions: all (grey), inliers (green)", fontsize=9)
        b.set_xlabel("direction (deg)")
    stats = _stage(result, "direction_change")
    if stats is not None and "histogram" in stats:
        bin_deg = float(params.get("direction_change", {}).get("bin_deg", 3.0))
        _vote_panel(c, stats, bin_deg, "(c) local direction-change vote (selected bins green)")
        c.set_xlabel("direction change to the k nearest motions (deg)")
    else:
        ok = np.isfinite(length)
        bins = np.linspace(0.0, float(np.percentile(length[ok], 99)) if ok.any() else 1.0, 40)
        c.hist(length[ok], bins=bins, color="#bbbbbb")
        c.hist(length[ok & inlier], bins=bins, color="#1a9850")
        c.set_title("(c) motion lengths: all (grey), inliers (green)", fontsize=9)
        c.set_xlabel("length (m)")

    matches = np.asarray(doc["matches"], dtype=int).reshape(-1, 2)
    for ax, key, column, label in (
        (d, "keypoints1", 0, "(d) image 1"),
        (e, "keypoints2", 1, "(e) image 2"),
    ):
        keypoints = np.asarray(doc[key], dtype=float)[:, :2]
        xy = keypoints[matches[:, column]]
        ax.scatter(*xy[~inlier].T, s=4, color="#bbbbbb", label=f"other matches: {(~inlier).sum()}")
        ax.scatter(*xy[inlier].T, s=6, color="#1a9850", label=f"inliers: {inlier.sum()}")
        camera = doc["image1" if column == 0 else "image2"]["camera"]
        ax.set_xlim(0, camera["width"])
        ax.set_ylim(camera["height"], 0)
        ax.set_aspect("equal")
        ax.legend(fontsize=7, loc="upper right")
        ax.set_title(f"{label}: the matches' keypoints (pixels)", fontsize=9)
    keep = inlier & np.isfinite(start).all(axis=1)
    f.add_collection(
        LineCollection(
            list(np.stack((start[keep], end[keep]), axis=1)), colors="#1a9850", linewidths=0.8
        )
    )
    f.scatter(*start[keep].T, s=3, color="#d73027", label="start")
    f.scatter(*end[keep].T, s=3, color="#e6c200", label="end")
    f.set_aspect("equal", adjustable="datalim")
    f.set_xlabel("east (m)")
    f.legend(fontsize=7)
    f.set_title(f"(f) the {keep.sum()} inliers' motions (the reduced set)", fontsize=9)
    fig.suptitle(
        f"{result['method']}: {int(inlier.sum())} of {len(decision)} matches are inliers",
        fontsize=11,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
