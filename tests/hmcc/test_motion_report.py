"""``params.return_motions``: every match's motion on the plane and the stage that decided it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hmcc import VerifyOptions, verify
from hmcc.motion_report import INLIER
from hmcc.projection import project_to_plane
from hmcc.simulate import SimulationOptions, simulate_pair
from hmcc_schema import parse_pair

OPTIONS = VerifyOptions(return_motions=True)


@pytest.fixture(scope="module")
def pair():  # type: ignore[no-untyped-def]
    doc = simulate_pair(SimulationOptions(views=("V", "F"), n_inliers=150, outlier_ratio=0.6), 5)
    return parse_pair(doc).pair_data(0)


def test_off_by_default(pair) -> None:  # type: ignore[no-untyped-def]
    result = verify(pair, "hmcc-ransac")
    assert result.motions is None and "motions" not in result.to_dict()


@pytest.mark.parametrize("method", ["hmcc-ransac", "hmcc", "hmcc-plus", "lo-ransac"])
def test_decisions_match_the_inliers_and_the_stages(pair, method: str) -> None:  # type: ignore[no-untyped-def]
    """decision == "inlier" exactly for the result's inliers; for the HMCC methods the matches
    removed by a stage are those its input had and its output lacks."""
    result = verify(pair, method, OPTIONS)
    motions = result.to_dict()["motions"]
    decision = np.asarray(motions["decision"])
    m = len(pair.matches)
    assert len(decision) == len(motions["start"]) == len(motions["length_m"]) == m
    np.testing.assert_array_equal(np.flatnonzero(decision == INLIER), result.inliers)
    if method.startswith("hmcc") and method != "hmcc-plus":
        assert motions["stages"] == [s.name for s in result.stages]
        before = np.arange(m)
        for report in result.stages:
            kept = result.survivors[report.name]
            removed = np.setdiff1d(before, kept)
            assert len(removed) == report.input - report.kept
            assert (decision[removed] == report.name).all()
            before = kept


def test_motions_are_the_projections_on_the_stage_plane(pair) -> None:  # type: ignore[no-untyped-def]
    result = verify(pair, "hmcc-ransac", OPTIONS)
    motions = result.motions
    assert motions is not None
    z0 = result.stages[0].stats["z0_m"]
    assert motions["z0_m"] == z0
    px1, px2 = pair.matched_pixels()
    start, ok = project_to_plane(pair.camera1, pair.pose1, px1, z0)
    i = int(np.flatnonzero(ok)[0])
    np.testing.assert_allclose(motions["start"][i], start[i])
    vector = np.asarray(motions["end"][i]) - np.asarray(motions["start"][i])
    assert motions["length_m"][i] == pytest.approx(np.hypot(*vector))
    assert motions["direction_deg"][i] == pytest.approx(
        np.degrees(np.arctan2(vector[1], vector[0])) % 360.0
    )


def test_the_inliers_form_leaves_them_out(pair) -> None:  # type: ignore[no-untyped-def]
    options = dataclasses.replace(OPTIONS, result="inliers")
    assert "motions" not in verify(pair, "hmcc-ransac", options).to_dict()
