import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from common.sensor_model import (
    FloatArray,
    SensorModelParams,
    cell_occupancy_probability,
    depth_from_disparity,
    depth_sigma,
    in_model_range,
    logodds,
    normal_cdf,
    obstacle_likelihood,
    probability,
)

PARAMS = SensorModelParams()


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_normal_cdf_table_matches_erf(dtype: type) -> None:
    x: FloatArray = np.concatenate([np.linspace(-8, 8, 20001), [-1e9, 1e9, -6.0, 6.0]]).astype(
        dtype
    )
    exact = np.array([0.5 * (1 + math.erf(float(v) / math.sqrt(2))) for v in x])
    assert np.abs(normal_cdf(x) - exact).max() < 1e-6


def test_depth_from_disparity_and_invalid_disparity() -> None:
    disparity = np.array([46.188, 0.0, -3.0], dtype=np.float32)
    depth = depth_from_disparity(disparity, 554.256, 0.5)
    assert depth[0] == pytest.approx(6.0, abs=1e-3)
    assert np.isnan(depth[1]) and np.isnan(depth[2])


def test_depth_sigma_grows_as_depth_squared() -> None:
    params = SensorModelParams(calibration_sigma_m=0.0)
    z = np.array([1.0, 2.0, 4.0, 8.0])
    sigma = depth_sigma(z, 554.256, 0.5, params)
    np.testing.assert_allclose(sigma / sigma[0], z**2)
    # DESIGN.md: ≈ 3 cm at the floor, 6 m down, Δd = 0.25 px.
    assert depth_sigma(np.array([6.0]), 554.256, 0.5, params)[0] == pytest.approx(0.0325, abs=1e-3)
    assert depth_sigma(np.array([6.0]), 554.256, 0.5, PARAMS)[0] == pytest.approx(0.0425, abs=1e-3)


@given(st.lists(st.floats(-0.5, 2.3), min_size=2, max_size=50), st.floats(0.005, 0.2))
def test_likelihood_is_monotone_in_height_up_to_the_band_top(
    heights: list[float], sigma: float
) -> None:
    h = np.sort(np.asarray(heights, dtype=np.float32))
    p = obstacle_likelihood(h, np.full_like(h, sigma), PARAMS)
    assert np.all(np.diff(p) >= -1e-6)
    assert np.all((p >= 0) & (p <= 1))


@given(st.integers(0, 500), st.integers(1, 500))
def test_cell_probability_stays_within_p_miss_and_p_hit(obstacle: int, pixels: int) -> None:
    obstacle = min(obstacle, pixels)
    p = cell_occupancy_probability(np.array([float(obstacle)]), np.array([float(pixels)]), PARAMS)
    assert PARAMS.p_miss <= p[0] <= PARAMS.p_hit


def test_floor_is_free_and_box_top_is_occupied() -> None:
    sigma = np.full(2, 0.03, dtype=np.float32)
    p = obstacle_likelihood(np.array([0.0, 0.8], dtype=np.float32), sigma, PARAMS)
    assert p[0] < 0.01 and p[1] > 0.99
    cells = cell_occupancy_probability(np.array([0.0, 20.0]), np.array([20.0, 20.0]), PARAMS)
    assert cells.tolist() == pytest.approx([PARAMS.p_miss, PARAMS.p_hit])


def test_a_cell_an_edge_only_clips_is_evidence_of_free_and_its_rim_of_nothing() -> None:
    # Share of band pixels 0 … 1 over 20 pixels: neutral at 0.6, where a rim cell whose centre
    # an edge passes through reads (half the cell, and the fattening and side faces beside it).
    shares = np.arange(21, dtype=np.float64)
    p = cell_occupancy_probability(shares, np.full(21, 20.0), PARAMS)
    assert np.all(np.diff(p) >= 0)
    assert p[12] == pytest.approx(0.5)
    assert np.all(p[13:] > 0.5) and p[17] == pytest.approx(PARAMS.p_hit)
    # An edge clipping under a quarter of the cell: free. From a quarter up to 0.6 (an object's
    # rim, half of it or less, or whose top the side faces partly hide): no evidence, or the rim
    # adds up to free, or the fattening beside an object to occupied.
    assert np.all(p[:5] == pytest.approx(PARAMS.p_miss))
    assert np.all(p[5:13] == pytest.approx(0.5))


def test_free_evidence_never_reaches_above_the_neutral_share() -> None:
    """A lower ``edge_fraction`` (a setting that was valid before ``free_share_max``) still
    starts up; the free side then ends where the occupied side begins."""
    params = SensorModelParams(edge_fraction=0.2, evidence_ramp=0.1)
    p = cell_occupancy_probability(np.arange(21, dtype=np.float64), np.full(21, 20.0), params)
    assert np.all(p[:2] == pytest.approx(params.p_miss)) and np.all(p[2:4] < 0.5)
    assert p[4] == pytest.approx(0.5) and np.all(p[5:] > 0.5)


def test_aggregation_does_not_grow_with_pixel_count() -> None:
    few = cell_occupancy_probability(np.array([5.0]), np.array([5.0]), PARAMS)
    many = cell_occupancy_probability(np.array([500.0]), np.array([500.0]), PARAMS)
    assert few == pytest.approx(many)


def test_surfaces_above_the_band_give_no_evidence() -> None:
    h = np.array([-0.05, 1.0, 2.05, 3.0], dtype=np.float32)
    assert in_model_range(h, np.full_like(h, 0.03), PARAMS).tolist() == [True, True, True, False]


def test_logodds_round_trip() -> None:
    p = np.array([0.12, 0.5, 0.97])
    np.testing.assert_allclose(probability(logodds(p)), p)


def test_bad_parameters_are_rejected() -> None:
    with pytest.raises(ValueError, match="p_hit"):  # its bounds say p_miss < 0.5 < p_hit
        SensorModelParams(p_hit=0.4)
    with pytest.raises(ValueError, match="band"):
        SensorModelParams(obstacle_min_m=2.5)
