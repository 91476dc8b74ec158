"""Low surfaces measured again at full resolution, on a synthetic full-resolution pair."""

import cv2
import numpy as np

from services.camera_sim.rig import RigSpec, layout_pairs
from services.depth.floor_geometry import FloorGeometry
from services.depth.low_band import LowBand
from services.depth.stereo import MatcherConfig, Rectifier
from tests.test_floor_model import _textured_pair

CALIB = layout_pairs(RigSpec(pair_count=1), (12.0, 10.0))[0]
"""An exact look-down pair: its rectification is the identity, its floor 46.2 px at full size."""


def _pair(disparity_px: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(left, right) of a texture whose left pixel u has ``disparity_px[u]``: the right image's
    pixel u − d shows it (d looked up where the surface is in the right image: the left map
    shifted by the floor's disparity, exact but for a pixel at each step)."""
    height, width = disparity_px.shape
    texture = cv2.GaussianBlur(
        rng.uniform(40, 220, (height, width)).astype(np.float32), (0, 0), 1.5
    )
    in_right = np.roll(disparity_px, -round(float(np.median(disparity_px))), axis=1)
    return _textured_pair(in_right, rng, texture)


def _band(matcher: MatcherConfig) -> LowBand:
    """The pair's low band at half resolution, its bounds from the half-resolution geometry."""
    rectifier = Rectifier.from_calibration(CALIB, 2)
    geometry = FloorGeometry.from_rectifier(rectifier, rectifier.pixel_rays_world())
    return LowBand(CALIB, 2, matcher, geometry)


def _half(image: np.ndarray) -> np.ndarray:
    height, width = image.shape
    return np.asarray(
        cv2.resize(image, (width // 2, height // 2), interpolation=cv2.INTER_AREA), np.uint8
    )


def test_a_low_deck_is_measured_again_and_the_rest_is_left_alone() -> None:
    """The half-resolution reading of a 14 cm deck is 0.2 px low, a third of it (in stripes) at
    3 cm, not even raised: what the matcher's windows straddling boards and floor gave on the
    renders. The full-resolution reading puts all of it back. A 1.2 m top (beyond the low band),
    the floor away from the deck and a speck too small to be a surface keep their readings."""
    rng = np.random.default_rng(5)
    width, height = CALIB.image_size
    fb_px_m = CALIB.left.focal_px * CALIB.baseline_m
    camera_m = float(CALIB.left.position_world[2])

    def disparity_px(height_m: float) -> float:
        return fb_px_m / (camera_m - height_m)

    truth_px = np.full((height, width), disparity_px(0.0), np.float32)
    truth_px[200:280, 300:420] = disparity_px(0.14)  # the deck
    truth_px[60:140, 400:520] = disparity_px(1.2)  # a tall top
    left, right = _pair(truth_px, rng)

    small_truth = (
        cv2.resize(truth_px, (width // 2, height // 2), interpolation=cv2.INTER_AREA) / 2
    ).astype(np.float32)
    coarse = small_truth.copy()
    coarse[100:140, 150:210] -= 0.2  # the deck, read low …
    stripes = (np.arange(coarse.shape[1]) // 3) % 3 == 0
    coarse[100:140, 150:210][:, stripes[150:210]] = disparity_px(0.03) / 2  # … a third at 3 cm
    coarse[118:122, 178:182] = disparity_px(1.0) / 2  # a post on the deck: in its box, not low
    coarse[20:30, 20:30] = disparity_px(0.2) / 2  # a speck of 100 px
    coarse[:10] = np.nan
    band = _band(MatcherConfig())
    refined = band.refine(left, right, _half(left), coarse, 0.0)

    assert band.regions == 1
    deck_error = (refined - small_truth)[103:137, 153:207]
    assert abs(float(np.median(deck_error))) < 0.05  # was 0.2 px low
    assert float(np.mean(np.abs(deck_error) < 0.1)) > 0.9
    np.testing.assert_array_equal(refined[118:122, 178:182], coarse[118:122, 178:182])
    untouched = np.ones(coarse.shape, np.bool_)
    untouched[96:144, 146:214] = False  # the deck's box, with its margin
    np.testing.assert_array_equal(refined[untouched], coarse[untouched])


def test_a_strip_at_the_images_edge_is_matched_with_a_large_block() -> None:
    """A raised strip one row high along the top edge: its box is matched over enough rows for
    the matcher's block (StereoBM refuses an image no taller than its block)."""
    rng = np.random.default_rng(6)
    width, height = CALIB.image_size
    floor_px = CALIB.left.focal_px * CALIB.baseline_m / float(CALIB.left.position_world[2])
    left, right = _pair(np.full((height, width), floor_px, np.float32), rng)
    coarse = np.full((height // 2, width // 2), floor_px / 2, np.float32)
    coarse[0, 40:240] = floor_px / 2 + 0.6  # 200 px along the edge, 15 cm up
    band = _band(MatcherConfig(algorithm="bm", block_size=11))
    refined = band.refine(left, right, _half(left), coarse, 0.0)
    assert band.regions == 1
    assert np.isfinite(refined).all()
