"""The disparity chain (services/depth/stereo.py) and the real-image bench's scoring, with real
OpenCV on synthetic pairs whose disparity is known exactly."""

import dataclasses
from pathlib import Path

import cv2
import numpy as np
import pytest

from bench.stereo_real import known, non_occluded, read_disparity, score_disparity, search_band
from services.camera_sim.rig import RigSpec, layout_pairs
from services.depth.stereo import (
    FULL_WIDTH_INSIDE_PX,
    OPTIONAL_STAGES,
    MatcherConfig,
    Rectifier,
    compute_disparity,
    equiangular_fraction,
    guided_weighted_median,
    invalidate_depth_edges,
    neighbourhood_mean,
    scale_intrinsics,
    stage_variants,
    stereo_rectify,
)

MIN_D, NUM_D = 8, 32


def textured_pair(disparity_px: float, contrast: float) -> tuple[np.ndarray, np.ndarray]:
    """A fronto-parallel textured plane seen with exactly ``disparity_px`` (band-limited texture,
    shifted with cubic interpolation)."""
    rng = np.random.default_rng(3)
    height, width, pad = 240, 320, 32
    texture = cv2.GaussianBlur(
        rng.normal(0, 1, (height, width + 2 * pad)).astype(np.float32), (0, 0), 1.0
    )
    texture = texture / texture.std() * contrast + 128
    shift = np.array([[1, 0, disparity_px], [0, 1, 0]], np.float32)
    right = cv2.warpAffine(
        texture, shift, texture.shape[::-1], flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP
    )
    crop = (slice(None), slice(pad, pad + width))
    return (
        np.clip(texture[crop], 0, 255).astype(np.uint8),
        np.clip(right[crop], 0, 255).astype(np.uint8),
    )


FRACTIONS = [20.1, 20.3, 20.5, 20.7]  # not multiples of SGBM's 1/16 px


@pytest.mark.parametrize("contrast", [8.0, 40.0])
def test_compute_disparity_on_a_fronto_parallel_pair(contrast: float) -> None:
    inner = (slice(20, -20), slice(20, -20))  # the left margin included: the chain matches it
    errors, sgbm_errors = [], []
    for true_disparity in FRACTIONS:
        left, right = textured_pair(true_disparity, contrast)
        disparity = compute_disparity(left, right, MIN_D, NUM_D, MatcherConfig())
        assert disparity.dtype == np.float32
        assert np.isfinite(disparity[inner]).mean() > 0.97
        errors.append(float(np.nanmedian(np.abs(disparity[inner] - true_disparity))))
        sgbm = compute_disparity(left, right, MIN_D, NUM_D, stage_variants(MatcherConfig())["sgbm"])
        sgbm_errors.append(float(np.nanmedian(np.abs(sgbm[inner] - true_disparity))))
    assert max(errors) <= 0.06
    # SGBM's own fraction is pulled toward whole pixels: up to 0.11–0.13 px off here.
    assert max(errors) < max(sgbm_errors) / 1.8


def test_full_width_matches_the_left_margin() -> None:
    true_disparity = 20.3
    left, right = textured_pair(true_disparity, 20.0)
    plain = compute_disparity(left, right, MIN_D, NUM_D, MatcherConfig(full_width=False))
    full = compute_disparity(left, right, MIN_D, NUM_D, MatcherConfig())
    rows = slice(20, -20)
    # OpenCV leaves minDisparity + numDisparities columns without a match.
    assert np.isnan(plain[rows, : MIN_D + NUM_D - 1]).all()
    # Full width: every column whose match lies FULL_WIDTH_INSIDE_PX inside the right image.
    first = int(np.ceil(true_disparity)) + FULL_WIDTH_INSIDE_PX + 1
    margin = full[rows, first : MIN_D + NUM_D]
    assert np.isfinite(margin).mean() > 0.97
    assert np.nanmedian(np.abs(margin - true_disparity)) <= 0.06
    assert np.isnan(full[rows, : int(true_disparity) + FULL_WIDTH_INSIDE_PX - 1]).all()


def test_equiangular_fraction_undoes_the_parabola_through_a_v() -> None:
    # A V-shaped cost with its minimum at w + δ: a parabola through its samples at w-1, w, w+1 has
    # its vertex at w + δ / (2 − 2|δ|); that is what SGBM reports, in 1/16 px.
    for offset_px in (-0.45, -0.3, -0.1, 0.0, 0.1, 0.25, 0.4):
        reported = 30 + offset_px / (2 - 2 * abs(offset_px))
        raw_16 = np.array([[round(reported * 16)]], np.int16)
        recovered = float(equiangular_fraction(raw_16)[0, 0])
        assert recovered == pytest.approx(30 + offset_px, abs=0.04)  # within SGBM's 1/16 step
    assert equiangular_fraction(np.array([[16 * 30]], np.int16))[0, 0] == 30.0


def test_neighbourhood_mean_averages_a_plane_and_keeps_an_edge() -> None:
    rng = np.random.default_rng(0)
    disparity = np.full((40, 40), 20.0, np.float32)
    disparity[:, 20:] = 30.0
    noisy = (disparity + rng.normal(0, 0.1, disparity.shape)).astype(np.float32)
    noisy[5, 5] = np.nan
    smoothed = neighbourhood_mean(noisy, 5, 1.0)
    assert np.isnan(smoothed[5, 5])  # holes stay holes
    plane = (slice(4, -4), slice(4, 16))
    assert np.nanstd(smoothed[plane] - 20) < np.nanstd(noisy[plane] - 20) / 3
    # Within two pixels of the step the window spans 10 px: those pixels keep their own value.
    near = (slice(None), slice(18, 22))
    np.testing.assert_array_equal(smoothed[near], noisy[near])


def test_edge_filter_drops_both_sides_of_a_depth_step() -> None:
    disparity = np.full((10, 10), 20.0, np.float32)
    disparity[:, 5:] = 25.0
    filtered = invalidate_depth_edges(disparity, 1.0)
    assert np.isnan(filtered[:, 4:6]).all()
    assert np.isfinite(filtered[:, :4]).all() and np.isfinite(filtered[:, 6:]).all()
    assert invalidate_depth_edges(disparity, 0.0) is disparity  # 0: off


def test_stage_variants_toggle_one_stage_each() -> None:
    configured = MatcherConfig()
    variants = stage_variants(configured)
    assert variants["configured"] == configured
    assert variants["sgbm"] == dataclasses.replace(
        configured, full_width=False, guided_median_px=0, edge_filter_px=0.0, subpixel=False
    )
    for stage in OPTIONAL_STAGES:
        toggled = variants[f"-{stage}"]
        assert getattr(toggled, stage) != getattr(configured, stage)
        assert dataclasses.replace(toggled, **{stage: getattr(configured, stage)}) == configured


# The real-image bench's scoring (bench/stereo_real.py).


def test_score_disparity_on_known_errors() -> None:
    gt = np.full((10, 10), 10.0, np.float32)
    estimate = gt.copy()
    flat = estimate.reshape(-1)  # 100 scored pixels
    flat[:10] = np.nan  # 10 without a disparity
    flat[10:20] += 3.0  # 10 off by 3 px
    flat[20:30] -= 1.5  # 10 off by 1.5 px
    flat[30:50] += 0.75  # 20 off by 0.75 px
    flat[50:100] += 0.25  # 50 off by 0.25 px
    scores = score_disparity(estimate, gt, np.ones(gt.shape, bool))
    assert scores.valid == pytest.approx(0.9)
    assert scores.bad_05px == pytest.approx(40 / 90)
    assert scores.bad_1px == pytest.approx(20 / 90)
    assert scores.bad_2px == pytest.approx(10 / 90)
    assert scores.median_err_px == pytest.approx(0.25)
    # Only the scored pixels count.
    scored = np.zeros(gt.shape, bool)
    scored.reshape(-1)[50:] = True
    assert score_disparity(estimate, gt, scored).bad_05px == 0.0


def test_unknown_and_occluded_ground_truth_is_not_scored() -> None:
    gt = np.full((20, 60), 4.0, np.float32)
    gt[5:15, 30:40] = 12.0  # a near square, 8 px more disparity than the background
    gt[0, 50] = np.inf  # Middlebury's unknown
    gt[1, 50] = 0.0  # KITTI's unknown
    gt[2, 50] = np.nan
    visible = non_occluded(gt)
    assert not known(gt)[:3, 50].any() and not visible[:3, 50].any()
    assert not visible[:, :4].any()  # their match lies left of the right image
    # The 8 background pixels left of the square are hidden behind it in the right view.
    assert not visible[5:15, 22:30].any()
    assert visible[5:15, 30:40].all() and visible[5:15, 10:21].all()
    assert visible[:5, 22:30].all()


def test_search_band_covers_the_ground_truth() -> None:
    gt = np.array([[7.2, 59.9, np.inf, 0.0]], np.float32)
    assert search_band(gt) == (6, 64)


def test_ground_truth_files(tmp_path: Path) -> None:
    gt = np.arange(12, dtype=np.float32).reshape(3, 4) + 1.5
    gt[0, 0] = np.inf
    pfm = tmp_path / "disp0.pfm"
    # PFM stores rows bottom to top; a negative scale means little-endian.
    pfm.write_bytes(b"Pf\n4 3\n-1.0\n" + gt[::-1].astype("<f4").tobytes())
    np.testing.assert_array_equal(read_disparity(pfm, 1.0), gt)
    png = tmp_path / "disp.png"
    cv2.imwrite(str(png), (np.nan_to_num(gt, posinf=0) * 256).astype(np.uint16))  # KITTI-style
    from_png = read_disparity(png, 1 / 256)
    assert from_png[0, 0] == 0.0 and not known(from_png)[0, 0]
    np.testing.assert_allclose(from_png[1:], gt[1:])
    npz = tmp_path / "disp.npz"
    np.savez(npz, disparity=gt)
    np.testing.assert_array_equal(read_disparity(npz, 2.0), gt * 2)


def test_the_guided_median_puts_a_fattened_edge_back_on_the_image_edge() -> None:
    """A bright top (30 px) over a darker floor (22 px) whose disparity the matcher dragged 3 px
    over the floor on every side: the spilled pixels take the floor's disparity, the top and the
    floor keep their own sub-pixel values, and a floor pixel of the top's grey is left alone only
    where its grey says top (the median weighs neighbours by grey likeness)."""
    rng = np.random.default_rng(5)
    gray = np.full((60, 80), 90.0) + rng.normal(0.0, 1.0, (60, 80))
    truth = np.full((60, 80), 22.13, np.float32) + rng.normal(0.0, 0.05, (60, 80)).astype(
        np.float32
    )
    top = (slice(20, 40), slice(30, 50))
    gray[top] = 170.0
    truth[top] = 30.37
    fattened = truth.copy()
    fattened[17:43, 27:53] = 30.37  # 3 px of spill on every side
    fattened[fattened > 30] += rng.normal(0.0, 0.05, (26, 26)).astype(np.float32).ravel()
    refined = guided_weighted_median(fattened, np.clip(gray, 0, 255).astype(np.uint8), 7)
    spill = np.zeros((60, 80), np.bool_)
    spill[17:43, 27:53] = True
    spill[top] = False
    assert np.abs(refined[spill] - 22.13).max() < 0.3  # back on the floor
    assert np.array_equal(refined[top], fattened[top])  # the top untouched, sub-pixel and all
    far = np.ones((60, 80), np.bool_)
    far[10:50, 20:60] = False
    assert np.array_equal(refined[far], fattened[far])  # away from the edge: nothing looked at
    assert np.isnan(
        guided_weighted_median(
            np.full((8, 8), np.nan, np.float32), gray[:8, :8].astype(np.uint8), 7
        )
    ).all()


def test_a_row_offset_moves_the_right_images_rows_and_nothing_else() -> None:
    """``Rectifier.with_row_offset`` samples the right image where the calibration's maps put row
    v + offset (checked against OpenCV's own float maps remapped there, a textured image, so the
    maps' x moves along too), leaves the left image alone, and at a zero offset is the
    calibration's rectification."""
    calibration = layout_pairs(RigSpec(), (12.0, 10.0))[0]
    rectifier = Rectifier.from_calibration(calibration, 2)
    width, height = calibration.image_size
    rng = np.random.default_rng(5)
    texture = cv2.GaussianBlur(rng.uniform(0, 255, (height, width)), (0, 0), 2.0).astype(np.uint8)
    size = rectifier.size[::-1]
    calibrated = rectifier.rectify(texture, texture)
    unmoved = rectifier.with_row_offset(np.zeros(size, np.float32)).rectify(texture, texture)
    assert np.array_equal(unmoved[0], calibrated[0])
    assert np.abs(unmoved[1].astype(int) - calibrated[1]).max() <= 1  # fixed-point maps' rounding
    offset = np.full(size, 2.5, np.float32)
    moved = rectifier.with_row_offset(offset).rectify(texture, texture)
    assert np.array_equal(moved[0], calibrated[0])
    k2 = scale_intrinsics(calibration.right.K_array, 0.5)
    k1 = scale_intrinsics(calibration.left.K_array, 0.5)
    _, r2, _, p2, _ = stereo_rectify(calibration, k1, k2, rectifier.size)
    map_x, map_y = cv2.initUndistortRectifyMap(
        k2, calibration.right.dist_array, r2, p2, rectifier.size, cv2.CV_32FC1
    )
    v, u = np.mgrid[0 : size[0], 0 : size[1]].astype(np.float32)
    at_x, at_y = (cv2.remap(m, u, v + offset, cv2.INTER_LINEAR) for m in (map_x, map_y))
    small = cv2.resize(texture, rectifier.size, interpolation=cv2.INTER_AREA)
    expected = cv2.remap(small, at_x, at_y, cv2.INTER_LINEAR)
    inner = (slice(20, -20), slice(20, -20))
    assert np.abs(moved[1][inner].astype(int) - expected[inner]).max() <= 2
    assert np.abs(calibrated[1][inner].astype(int) - expected[inner]).mean() > 5  # it did move
    with pytest.raises(ValueError, match="row offset"):
        rectifier.with_row_offset(np.zeros((10, 10), np.float32))
