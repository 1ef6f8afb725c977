"""Tests of the flight-level yaw correction (hmcc.attitude): on simulated nadir flights with
known yaw errors per image, the corrections recover them; they do not depend on the pairs'
order; and they stay near zero where the rough poses are right."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import orjson
import pytest

from hmcc.attitude import PairYaw, flight_yaw_corrections, rz, solve_yaws, wrap
from hmcc.simulate_flight import FlightOptions, simulate_flight
from hmcc_schema import parse_batch

NADIR = FlightOptions(
    strips=3,
    stations_per_strip=5,
    views=("V",),
    keypoints_per_image=600,
    pairs=60,
    relief_m=5.0,
    gnss_sigma_m=(0.0, 0.0),
    imu_sigma_deg=(0.0, 0.0, 0.0),
    platform_attitude_sigma_deg=0.0,
)


@pytest.fixture(scope="module")
def flight():
    sim = simulate_flight(NADIR, seed=3)
    body = orjson.dumps(sim.body, option=orjson.OPT_SERIALIZE_NUMPY)
    return parse_batch(body, max_pairs=len(sim.body["pairs"]))


def _solve(flight, errors: np.ndarray, order: np.ndarray | None = None) -> np.ndarray:
    """Corrections for ``flight`` with image k's rough yaw off by ``errors[k]`` (the
    correction to find is ``errors[k]``)."""
    names = sorted(flight.images)
    index = {n: k for k, n in enumerate(names)}
    images = {
        n: dataclasses.replace(
            im,
            pose=dataclasses.replace(
                im.pose, R_world_to_cam=im.pose.R_world_to_cam @ rz(-errors[index[n]])
            ),
        )
        for n, im in flight.images.items()
    }
    turned = dataclasses.replace(flight, images=images)
    ks = np.arange(len(flight.pairs)) if order is None else order
    first = np.array([index[flight.pairs[k].image1] for k in ks])
    second = np.array([index[flight.pairs[k].image2] for k in ks])
    return flight_yaw_corrections(len(names), first, second, [turned.pair_data(int(k)) for k in ks])


def _errors(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    errors = np.zeros(n)
    for k in rng.choice(n, 4, replace=False):
        errors[k] = math.radians(rng.uniform(20.0, 180.0)) * rng.choice([-1.0, 1.0])
    return errors


@pytest.mark.parametrize(
    "seed",
    [
        1,
        pytest.param(
            2,
            marks=pytest.mark.xfail(
                reason="one image (error 137 deg) keeps its error: none of its pairs' motion "
                "fields counted (a known limitation, not yet understood)",
                strict=True,
            ),
        ),
    ],
)
def test_the_corrections_recover_the_yaw_errors(flight, seed) -> None:
    errors = _errors(len(flight.images), seed)
    found = _solve(flight, errors)
    assert np.degrees(np.abs(wrap(found - errors))).max() < 4.0


def test_no_correction_where_the_poses_are_right(flight) -> None:
    found = _solve(flight, np.zeros(len(flight.images)))
    assert np.degrees(np.abs(found)).max() < 1.0


def test_the_pairs_order_does_not_matter(flight) -> None:
    errors = _errors(len(flight.images), 1)
    order = np.random.default_rng(5).permutation(len(flight.pairs))
    assert np.allclose(_solve(flight, errors), _solve(flight, errors, order), atol=1e-9)


def test_the_solve_takes_either_direction_of_a_pair() -> None:
    # c = (0, 1, -2) rad: the same pairs named one way or the other give the same solution
    c = np.array([0.0, 1.0, -2.0])
    pairs = [(0, 1), (1, 2), (0, 2)]
    flipped = [(b, a) for a, b in pairs]

    def yaws(ps):
        return [PairYaw(float(wrap(c[b] - c[a])), float(wrap(c[b])), 50.0, 100) for a, b in ps]

    one = solve_yaws(3, *map(np.array, zip(*pairs, strict=True)), yaws(pairs))
    two = solve_yaws(3, *map(np.array, zip(*flipped, strict=True)), yaws(flipped))
    assert np.allclose(wrap(one - c), 0.0, atol=1e-9)
    assert np.allclose(wrap(two - c), 0.0, atol=1e-9)


def test_an_image_in_no_pair_gets_no_correction() -> None:
    y = PairYaw(0.5, 0.5, 50.0, 100)
    found = solve_yaws(3, np.array([0]), np.array([1]), [y])
    assert found[2] == 0.0
