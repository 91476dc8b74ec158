"""The fixed-camera floor model of one stereo pair (DESIGN.md, "The fixed-camera floor model").

The cameras never move and the floor is the plane z = 0 of the calibration, so after rectification
the floor's disparity is a known affine function of the pixel. Two cues follow, per pair and frame,
on the rectified images at the processing resolution:

- **Floor test** (plane consistency): the right image is remapped at the floor's disparity, so that
  a floor pixel of the left image meets its own floor point in the right. Zero-mean normalised
  cross-correlation over a small window says *agree* (textured, matching, no residual shift),
  *contradict* (textured and not matching, or matching only shifted: something above the floor) or
  nothing (too little texture); one Lucas–Kanade step measures the residual shift, i.e. a surface's
  height above the floor, to a fraction of a pixel.
- **Background**: a per-pixel appearance model of the empty floor for each camera (the right one on
  the floor-warped grid, so pixel p of both models looks at the same floor point): mean and spread
  after a gain field per camera (:func:`gain_fields`: auto-exposure and gain scale every floor
  pixel alike; a circuit of luminaires switched off over part of the hall, by a factor that varies
  smoothly over the image).

Evidence rules (what :meth:`FloorModel.update` returns as the disparity the tile is built from):

0. Near the floor (residual shift under a pixel, textured) the floor test measures where the
   matcher has nothing: a 14 cm pallet is half a pixel at the processing resolution, below what
   the matcher's search resolves reliably. It never overrules the matcher: its window straddles a
   pallet's boards and the floor between them and "agrees" on a shift between the two (on
   ``--seed 1`` a pallet's middle boards read floor).
1. Fattening: an object disparity on an untextured pixel is the matcher's window dragging a nearby
   edge onto smooth floor; where both cameras match their floor backgrounds and the floor test does
   not contradict, it becomes a floor observation.
2. A pixel without a disparity is a floor observation only where both cameras' pixels (the left
   pixel and its floor-homography partner in the right) match their backgrounds and the floor test
   does not contradict (or, never modelled, by rule 11).
3. The floor test alone never makes a floor observation where stereo has nothing: a uniform box top
   also "agrees" under the floor warp (it has no texture to disagree with).
4. A pixel whose appearance departs from the background and has no disparity gives no evidence
   (unknown); it is occupied only where stereo or the floor test measures it in the obstacle band.
   A reading at the floor's height there is no floor evidence either where the matcher carried it
   in (no texture along x) or where the image no longer shows the background's texture: the lower
   rim of a dark body reads at the floor's height and its points fall inside its footprint (a
   person's cells 45 % free on the default scene), while a shadow keeps the floor's texture.
   On a plain floor, a pixel the model does not hold has no background to vouch for a floor
   reading: there the matcher's floor reading is evidence only where the floor test agrees (the
   dark near face of a plain box standing since start-up, and its top beside it, take the floor's
   disparity from around; offline, ``--floor plain --plain-objects``: static false-free 0.42 →
   0.07 %). So are the plain floor's own pixels until the model holds them: the first learning
   frames map less of it.
5. Shadows lie on the floor: on texture stereo still measures the floor (rule 0 where the matcher
   has nothing), on a plain floor a shadow is a departure (rule 4: unknown), never an obstacle.
6. Along the baseline, the matcher fills an untextured run of a row from the measurements that bound
   it: its value there is kept only where every measurement bounding the run within reach agrees
   with it (a plain top between its two edges). A dark vertical face between a top and the floor, a
   lane line along the baseline or the floor beside a box edge along x take whatever their
   surroundings carry: measured-looking heights that put a ring of false obstacles along every
   edge parallel to the baseline; they give no evidence. But a floor reading beside such an edge
   (a wall's foot), whose window holds the edge while its own row has texture along x, is kept
   where the nearest measurements up and down its column agree with it and none along its row
   disagrees (6b: the floor along the walls along x, two cells wide, stayed unknown without it).
   On a plain floor, a raised filling kept on the word of one measurement is no evidence where
   that measurement is a textured surface's (several in a row along x) and the pixel has the
   floor's grey around it (6c): a textured top does not turn plain at its edge, so the run
   beyond it is the plain floor the matcher carried the top's disparity over, which nothing
   bounds on the far side (a plain top, measured at its edges only, keeps its filling).
7. A run with no disparity at all between two measurements at one height in the obstacle band
   (the plain top of a box or a mover: SGBM's uniqueness test leaves most of it empty) is that
   surface, unless the background says floor there.
8. A region still without evidence where the image departs from the floor's background
   (something stands there) and whose edges hold measurements in the band is a surface at their
   upper quartile's height: a plain top whose one measured edge cannot bridge it (the other lies
   beside the occlusion). Measurements above the band (the matcher's picks at the top of its
   search) do not count. Like 6 and 7, it only ever adds obstacles or takes evidence away, never
   clears a cell. Not in a frame that re-learns: there the whole image departs. Nor, on a
   textured floor, where the left image shows its floor's grey with texture along x: there the
   right camera cannot see the floor past a top's image-left edge (the left-occluded band),
   which the left one shows.
   What 7 and 8 infer stands on the footprint it hides: where the image shows floor (observed,
   or measured low, over a pixel and its neighbours) straight below the inferred point, that
   point is a face below a top's edge, not the top. It takes the highest of a few lower heights
   whose floor below is not seen, or none (a mover's side face, filled at its top's height, stood
   1.3 m out over the open floor before it).
9. Floor seen through a gap narrower than 12 cm between surfaces in the band (a pallet's deck
   between its boards) belongs to them: no robot passes there, and a cell whose centre falls in
   the slot is the pallet's.
10. Where the image still departs from the background (or lies on a run of rule 12) and no rule
    made evidence, the floor is *hidden* now (:attr:`FloorModel.hidden`): something stands in
    the pixel's ray (a plain mover, a person whose top is out of view), or a shadow darkens a
    plain floor. Its floor cell is no longer known to be free: the tile says so and the map
    forgets a free belief there (unknown, never occupied). Not in a frame that re-learns, where
    the whole image departs.
11. Paint along the baseline (a lane line along x) has no texture along x for either stereo or
    the floor test, and its edges stop the model's growth, so it is never modelled: a pixel of it
    with no evidence and texture along the baseline only, in a gap of at most PAINT_GAP_M between
    floor rows that match their background above and below it, is floor (not where an inferred
    point of 7 or 8 fell).
12. Something put down after the model learnt the floor under it: on a textured floor, along
    the plain run outward of a plain top's measured edge (a strip measured at obstacle height
    on modelled pixels, running across the ray or up to 60 degrees off it: STRIP_TILTS_DEG)
    that ends within TOP_REACH_M at texture or the image's edge, the background vouches for
    nothing: no floor observation (1, 2, 11), no floor reading kept on its word alone (6), and
    a modelled pixel there neither learns nor counts as a stale background. Nor is the
    matcher's filling there evidence: on the top it is the top's height, but the run goes on
    past the top's far edge (a plain top of the floor's grey meeting smooth floor has no edge
    to stop it), and there the filling is fattening that rule 1 no longer takes away (kept and
    vetted by rule 6, it stood as false obstacles up to 0.6 m beyond a crate put down; kept
    unvetted, 0.8 m). Where nothing is left the floor is hidden (10). A plain top of the
    floor's grey matches the background wherever the floor under it is smooth, and rule 1 took
    the filling for fattening (offline, ``--seed 2``'s light crate put down on concrete, one
    pair fused alone: 21–24 of its 112 inner cells served free in every frame; with the rule
    0–6). An object standing since start-up never had its edges modelled, so the floor beyond
    its top keeps its evidence.

The matcher's offset on the floor (and through its coarse fit the disparity residual) is fitted
before the first frame's evidence as well as every few frames: until the first fit, two frames
later, a poorly calibrated pair's floor read up to 0.3 m high.

Learning (never from pixels where something stands), every ``learn_every`` frames:

- *Seeds* are pixels the floor test agrees on, or that stereo measures at the floor's disparity on
  texture (with most of their window there too).
- The model grows from seeds over *smooth* pixels (no intensity edge, no contradiction): a smooth
  connected region holding enough seeds is floor, so a plain floor is learned from the few floor
  edges stereo can measure (object bases, wall bases, markings). An object standing since start-up
  is bounded by its outline and never joins: it stays unmodelled, so it is never a floor
  observation. Growth stops a few pixels short of an edge (its blur passes ``edge_gray``), so the
  grown floor then creeps outward, away from the nadir, up to the edge's middle (at most
  EDGE_CREEP_PX): outward, a floor region ends at what rises from it (a wall's foot, a box's
  base), the face beyond the edge's middle (without it, a plain floor along a wall's foot along
  the baseline was never learned).
- *Line of sight*: a pixel is never learned where its ray to the floor passes through the column
  under an obstacle point measured in this frame (a box's side face between its base and its top
  edge: learned as floor, it would put free cells inside the box).
- *Plain tops*: on a textured floor, nor where a plain run leads outward from a measured obstacle
  point and ends, within TOP_REACH_M, at texture or the image's edge (a lone textured pixel, sensor
  noise, does not end it): the top beyond an edge, which has nothing to measure and may meet a
  floor of its grey with hardly an edge (a light crate on concrete). On a plain floor nothing ends
  such a run: there the plain pixels within TOP_REACH_M outward of a plain top's measured edge
  are kept from the model, open run or not. Such an edge is a strip measured in the band, thin
  along the ray (the matcher measures its window's width of a plain top) and running on across
  it; a textured top is measured across, so neither its far edge nor its corners start a run.
  The edge is not found in every frame, so each learning frame that finds it also takes a
  confirmation back from the run (long-learnt floor, confirmed hundreds of times, keeps its model
  when a mover passes).
- A pixel is modelled once confirmed in ``confirm_frames`` learning frames that agree: one whose
  image departs from what it was confirmed as before it is modelled starts again from the image,
  its count at one. Its first confirmation may have seen something since gone: at the floor's
  height, a forklift's forks standing there at start-up (seeds, grown into as floor), or a passing
  forklift's floor-grey top grown into at a learning frame. Modelled on it, the floor that came
  back departed for good: hidden, and filled as an obstacle whenever an edge came near (rule 8;
  offline, ``--floor plain --seed 1 --pairs 6``: a 150–380-cell false obstacle where the forklift
  started, through the run). (A re-learning frame, below, starts every confirmed pixel from its
  image and keeps its count.) Later it is updated (running mean and variance) only while it is
  confirmed and still matches.
- When most modelled pixels depart at once after gain normalisation (a lighting change the gain
  field does not take off), the model re-learns from that frame: confirmed pixels restart from it,
  the rest is forgotten; in that frame rule 8 fills no departed region.
- A modelled pixel whose grey still matches its background but whose texture does not, in
  ``stale_learning_frames`` learning frames in a row, each time where the matcher reads the floor
  and nothing stands on it or before it (line of sight, plain tops, any reading in or above the
  band), starts again from the image: its background was learnt from something since gone (a
  floor-grey forklift top grown into while the model started, among floor learnt a frame
  before). A departure in grey never counts: a dark body standing still, whose plain sides the
  matcher carries the floor's disparity onto, would be learnt as floor. Nor does a count that
  ran on over frames out of the row: the floor-grey side of something standing with its top out
  of view meets the conditions now and then.
- The floor's disparity from the calibration is off by a fraction of a pixel when the calibration
  is (a poor one by a pixel at the image's edges): an affine offset in the pixel is fitted to the
  pixels measured near the floor, started (and started again whenever a quarter of the image
  finds the floor elsewhere, unless those blocks all lie above the current floor and are half the
  blocks or fewer, or each still shows it: there something stands on it) by a coarse fit through
  the floor's offset in blocks of the image.
  The rows are off too (the calibration's relative pitch and roll): an affine row offset is
  fitted alike, and the depth pipeline rectifies the next frames with it
  (:attr:`FloorModel.row_offset_px`, to 1/32 px), so the matcher as well as this model sees
  aligned rows.

Pure numpy/OpenCV, no I/O: the depth pipeline owns one per pair.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import numpy.typing as npt

from common.arrays import F32, U8, Mask
from common.compiled import compiled
from services.depth.floor_background import (
    GAIN_MIN_SAMPLES,
    GAIN_SAMPLE_STEP,
    UNIT_GAIN,
    gain_fields,
    gain_normalised,
    texture_checks,
)
from services.depth.floor_config import FloorModelConfig
from services.depth.floor_geometry import FloorGeometry
from services.depth.floor_offset import (
    MIN_FIT_PIXELS,
    coarse_floor_offset,
    restarts_from_blocks,
    robust_affine_fit,
)
from services.depth.floor_rows import column_support, row_support
from services.depth.image_windows import blur, probed, window_max_at
from services.depth.line_of_sight import LineOfSight
from services.depth.plane_consistency import X_ENERGY_MIN, FloorTest, floor_shift_2d, floor_test

FLOOR_WINDOW_SHARE = 0.75
"""A stereo seed needs this share of its window measured at the floor's disparity."""
RESIDUAL_FIT_PX = 0.5
"""The residual is fitted to pixels the floor test measures within this of the floor."""
SEED_PROBE_PX = 3.0
"""A smooth pixel is touched by a seed this far outward of it (away from the nadir)."""
EDGE_CREEP_PX = 3
"""Steps (pixels) the learned floor creeps outward toward the edge that stopped its growth
(:meth:`FloorModel._up_to_edges`)."""
LINE_ACROSS_PX = 3.0
"""Beyond an inward seed, the floor this much further on is compared with the pixel."""
TOP_REACH_M = 1.5
"""A plain run beyond an obstacle's edge that ends within this many metres of floor at the
camera's foot (a top at height h looks C/(C − h) times larger: 1.2 m at 1.2 m up, the widest top
of the simulated site) is the top it bounds; one that does not is floor (on a textured floor: on a
plain one, see :meth:`FloorModel._plain_tops`)."""
THIN_TOP_PX = 10.0
"""A strip measured in the obstacle band thinner than twice this along the ray (from the nadir)
is a plain top's edge: the matcher measures its window's width of the top and nothing beyond.
Inward, from this to twice this, no top measured across at its height either (its surface half
and whole this further in): a textured top's far edge beyond a gap in its measurement (a
shelf's speckled top) is no strip."""
MIN_STRIP_PX = 20
"""Fewer pixels than this of such a strip are a corner of something, not a top's edge."""
STRIP_TILTS_DEG = (0.0, -30.0, 30.0, -60.0, 60.0)
"""The directions, from across the ray, a top's edge may run in (the first: across it, the
plain floor's test): a box's edge runs across the ray only where the box faces the camera's foot
(one put down square to the image, up and to the side of the nadir, has its near edge at 40–50
degrees to the ray). The thin test bounds it: a strip 2–4 px wide within about 15 degrees of the
ray is none; a compact blob 16–18 px across where the ray runs along an image axis passes (its
runs cost unknown floor, not free)."""
SAME_SURFACE_M = 0.1
"""A measurement that close below another's height, or higher, belongs to the same surface."""
TEXTURED_FLOOR_SHARE = 0.5
"""A floor this much of which the floor test finds textured is textured: there a plain run is no
floor (measured: concrete and speckle 0.87–1.0 of the modelled pixels, a plain floor 0.04–0.06)."""
ROW_REACH_PX = 40
"""How far along a row (processing pixels) a measurement vouches for the matcher's filling."""
ROW_TOLERANCE_M = 0.1
"""A filled value agrees with a measurement bounding its run within this height."""
EDGE_REACH_PX = 6
"""How far along a column a measurement vouches for a floor reading beside an edge along the
baseline (:meth:`FloorModel._beside_edges`): the floor test's 5-px window and its blur reach about
4 px from an edge, and rows 4–7 of a view beside a wall's foot read unmatchable; not tuned."""
TEXTURED_ANCHOR_PX = 8
"""Measurements in a row along the baseline from which they are a textured surface's, not one
edge's (the matcher measures a plain top's edge over a few pixels): rule 6c. Offline, the plain
scenes: 8 gained IoU +0.007 to +0.028, 16 −0.001 to +0.011."""
FLOOR_GREY_WINDOW_PX = 41
"""Window (processing pixels, about 0.9 m of floor) over which the modelled floor's background
gives the floor's grey beside pixels the model does not hold (rule 6c)."""
FLOOR_GREY_MIN_SHARE = 0.05
"""Share of that window the model must hold for its grey to count."""
REGION_EDGE_PX = 5
"""A measurement within (this − 1) / 2 px of a departed region lies on its edge (rule 8)."""
REGION_MIN_RAISED = 10
GAP_CLOSED_M = 0.12
"""Floor seen through a gap narrower than this between surfaces in the band is theirs (rule 9)."""
GAP_KERNEL_MAX_PX = 31
"""The closing's kernel at most (a calibration of absurd focal length is refused later, by the
disparity band it implies; it must not ask for a kernel of terabytes first)."""
REGION_TOP_QUANTILE = 0.75
STANDING_STEPS = 4
"""Heights an inferred surface tries, evenly from its own down to the band's foot, for one that
stands where the floor below it is not seen (a face below a top's edge)."""
PAINT_GAP_M = 0.16
"""Rule 11: a gap up to this tall between floor rows the background confirms, across paint along
the baseline, is the paint's (lane lines are 5–10 cm wide; the model's growth stops a pixel or
two before each of their edges)."""

BLANK_GRAY = (20.0, 245.0, 2.0)
"""A frame shows nothing when 99 % of its grey levels (at every 4th pixel) lie under the first
(dark, covered), 99 % over the second (blinded), or all within the third of each other (a
constant image: a camera that sends the same value). Not merely "uniform": a plain floor in view
alone spans only the sensor's noise and its light's falloff, a few grey levels."""


def blank(image: U8) -> bool:
    """Whether a camera's image shows nothing (BLANK_GRAY). Such a frame is neither measured nor
    learned from: one black frame made the whole view depart from its background, the model
    learned the floor again from nothing, and said *no_floor* for 10 s, as for a calibration not
    this pair's."""
    dark, blinded, constant = BLANK_GRAY
    # The percentiles from the grey levels' histogram: np.percentile's sort cost 0.16 ms a frame.
    below = np.cumsum(np.bincount(image[::4, ::4].ravel(), minlength=256))
    low, high = np.searchsorted(below, (0.01 * below[-1], 0.99 * below[-1]))
    return bool(high <= dark or low >= blinded or high - low < constant)


@compiled
def foot_px(
    row: int, col: int, height_m: float, terms: tuple[F32, float, float, float, float]
) -> tuple[int, int]:
    """Where the floor straight below the point at ``height_m`` on the pixel's ray shows: on the
    line from the pixel to the nadir, where vertical lines vanish. Its image is z·p + h·μ·n over
    z + h·μ (z the point's depth, μ the depth a metre down adds), to the nearest pixel."""
    ray_down, camera_height_m, depth_per_m_down, nadir_row, nadir_col = terms
    depth = (camera_height_m - height_m) / ray_down[row, col]
    weight = height_m * depth_per_m_down / (depth + height_m * depth_per_m_down)
    return (
        int(np.rint(row + weight * (nadir_row - row))),
        int(np.rint(col + weight * (nadir_col - col))),
    )


@compiled
def _stand(
    measured: F32,
    inferred: Mask,
    floor_seen: Mask,
    terms: tuple[F32, float, float, float, float],
    focal_baseline_px_m: float,
    lowest_m: float,
    fallen: Mask,
) -> None:
    """FloorModel._keep_standing's loop: per inferred pixel, the first of STANDING_STEPS heights
    from its own down whose foot is not ``floor_seen`` (a sequential scan: the numpy passes over
    the pixels and steps cost 1 ms a frame)."""
    ray_down, camera_height_m = terms[0], terms[1]
    rows, cols = measured.shape
    for row in range(rows):
        for col in range(cols):
            disparity = measured[row, col]
            if not inferred[row, col] or not disparity > 0.0:  # (NaN or none: no surface)
                continue
            top_m = camera_height_m - focal_baseline_px_m / disparity * ray_down[row, col]
            chosen_m = np.nan
            for step in range(STANDING_STEPS):
                height_m = top_m + (lowest_m - top_m) * step / (STANDING_STEPS - 1)
                foot_row, foot_col = foot_px(row, col, height_m, terms)
                inside = 0 <= foot_row < rows and 0 <= foot_col < cols
                if not (inside and floor_seen[foot_row, foot_col]):
                    chosen_m = height_m
                    break
            if chosen_m == top_m:
                continue
            if not np.isnan(chosen_m):
                measured[row, col] = (
                    focal_baseline_px_m * ray_down[row, col] / (camera_height_m - chosen_m)
                )
            else:
                measured[row, col] = np.nan
                fallen[row, col] = True


def floor_everywhere_around(floor: Mask) -> Mask:
    """Pixels whose 3 × 3 neighbourhood is all ``floor`` (outside the image counts as floor)."""
    eroded: Mask = cv2.erode(floor.view(np.uint8), np.ones((3, 3), np.uint8)).view(np.bool_)
    return eroded


@compiled
def _march_outward(
    start: Mask,
    passable: Mask,
    nadir_px: tuple[float, float],
    reach_px: int,
    grace_px: int,
    runs: U8,
) -> None:
    """From each ``start`` pixel, one pixel at a time straight away from the nadir: the pixels
    passed over, passable ones (any for the first ``grace_px``, and a lone other one), up to two
    others in a row or ``reach_px``. In the image, not on polar bins: near the nadir a bin spans
    a wide angle, and a start there would fan out over the floor beside its top."""
    rows, cols = start.shape
    cx, cy = nadir_px
    for v0 in range(rows):
        for u0 in range(cols):
            if not start[v0, u0]:
                continue
            du, dv = u0 - cx, v0 - cy
            norm = math.sqrt(du * du + dv * dv)
            if norm < 1.0:
                continue
            du, dv = du / norm, dv / norm
            misses = 0
            for k in range(1, reach_px + 1):
                u, v = round(u0 + k * du), round(v0 + k * dv)
                if u < 0 or v < 0 or u >= cols or v >= rows:
                    break
                if passable[v, u] or k <= grace_px:
                    misses = 0
                else:
                    misses += 1
                    if misses == 2:
                        break
                runs[v, u] = 1


@compiled
def _thin_across(
    obstacle: Mask,
    height_m: F32,
    near: Mask,
    thin_probes: npt.NDArray[np.int64],
    further_probes: npt.NDArray[np.int64],
    across_probes: npt.NDArray[np.int64],
    strip: Mask,
) -> None:
    """Flat arrays, per ``obstacle`` pixel: whether no obstacle pixel at either ``thin_probes``
    (along the ray: inward and outward, THIN_TOP_PX) stands within SAME_SURFACE_M below it or
    higher, nor at ``further_probes`` (further inward) one of its surface (within SAME_SURFACE_M)
    with its surface again at its own probes half and whole THIN_TOP_PX inward (the last row of
    ``further_probes``, and ``thin_probes``' first): a top measured across, whose far edge this
    is beyond a gap in its measurement. A plain box before it in a row, its edges measured and
    its top not, is not one; a printed box's top there is, and ends a plain box's near edge, as
    the inward probe always did closer in. And, in one direction of ``across_probes``
    (direction, either way, pixel), both pixels are ``near`` an obstacle pixel
    (FloorModel._top_edges). Only at the obstacle's pixels, a few in a hundred."""
    same = np.float32(SAME_SURFACE_M)
    for pixel in range(obstacle.size):
        if not obstacle[pixel]:
            continue
        thin = True
        for probe in range(thin_probes.shape[0]):
            at = thin_probes[probe, pixel]
            if at >= 0 and obstacle[at] and height_m[at] > height_m[pixel] - same:
                thin = False
        for probe in range(further_probes.shape[0] - 1):
            at = further_probes[probe, pixel]
            if at < 0 or not obstacle[at]:
                continue
            across = abs(height_m[at] - height_m[pixel]) < same
            for inner in (further_probes[-1, at], thin_probes[0, at]):
                across = across and inner >= 0 and obstacle[inner]
                across = across and abs(height_m[inner] - height_m[pixel]) < same
            thin = thin and not across
        runs_on = False
        for direction in range(across_probes.shape[0]):
            both = True
            for way in range(2):
                at = across_probes[direction, way, pixel]
                if at < 0 or not near[at]:
                    both = False
            runs_on = runs_on or both
        strip[pixel] = thin and runs_on


@compiled
def _paint_gaps(floor: Mask, candidates: Mask, gap_px: F32, paint: Mask) -> None:
    """Per column: the ``candidates`` in a gap between two ``floor`` pixels whose rows lie at most
    ``gap_px`` (at the gap's first row) apart."""
    rows, cols = floor.shape
    for col in range(cols):
        last = -1
        for row in range(rows):
            if not floor[row, col]:
                continue
            if last >= 0 and row - last - 1 <= gap_px[last + 1, col]:
                for inner in range(last + 1, row):
                    paint[inner, col] = candidates[inner, col]
            last = row


class FloorModel:
    """Floor test, background per camera, and the evidence rules of the module docstring."""

    def __init__(
        self,
        geometry: FloorGeometry,
        obstacle_band_m: tuple[float, float],
        config: FloorModelConfig | None = None,
    ) -> None:
        self.config = config or FloorModelConfig()
        self.geometry = geometry
        self.obstacle_min_m, self.obstacle_max_m = obstacle_band_m
        height, width = geometry.floor_disparity_px.shape
        self.shape = (height, width)
        v, u = np.mgrid[0:height, 0:width].astype(np.float32)
        self._u, self._v = u, v
        # Affine floor-disparity offset a + b·u' + c·v' (u', v' in [-1, 1]); fitted at run time.
        self._basis = np.stack([np.ones_like(u), u / width * 2 - 1, v / height * 2 - 1])
        self.residual_coef = np.zeros((2, 3), np.float64)
        """Affine calibration residual on the floor: disparity (row 0) and row offset (row 1)."""
        self.aligned_row_coef = np.zeros(3, np.float64)
        """The row offset (affine, as ``residual_coef[1]``) the images this model is given were
        rectified with: set by whoever rectifies them (the depth pipeline), zero otherwise."""
        self.matcher_offset_coef = np.zeros(3, np.float64)
        self.matcher_offset_px = np.zeros((height, width), np.float32)
        """What the matcher measures on the floor beyond the calibration's floor disparity
        (affine, like the residual): taken off every disparity it measures."""
        self.line_of_sight = LineOfSight(self.shape, geometry.nadir_px)
        self.mean = np.zeros((2, height, width), np.float32)
        self.var = np.zeros((2, height, width), np.float32)
        self.tolerance = np.zeros((2, height, width), np.float32)
        """max(match_sigmas·σ, match_min_gray, match_relative·mean), kept with the model."""
        self._modelled = np.zeros((height, width), np.bool_)
        self.hidden = np.zeros((height, width), np.bool_)
        """Rule 10, of the last frame: pixels whose floor is hidden by something standing there."""
        self.inferred = np.zeros((height, width), np.bool_)
        """Of the last frame: pixels whose height rules 7 and 8 carried in from around (no measurement
        of their own): the tile drops them where the frame measures the floor in their cell."""
        self.plain_floor = False
        """The floor seen is plain (TEXTURED_FLOOR_SHARE): rule 4's pixels the model does not hold.
        Decided in each learning frame that sees enough floor, after that frame's evidence: False
        until then."""
        self.confirmed = np.zeros((height, width), np.uint8)
        self._stale = np.zeros((height, width), np.uint8)
        """Learning frames in a row each modelled pixel departed in texture alone
        (``stale_learning_frames``)."""
        self.restarted = 0
        """Pixels started again from the image because their model had gone stale."""
        self.disagreed = 0
        """Pixels started again before they were modelled: their confirmations disagreed."""
        self._offset_compared = False
        """The coarse fit has been compared with the matcher's offset (until then it is no
        estimate: :func:`restarts_from_blocks`)."""
        self.frames = 0
        self.relearned = 0
        self.blank = False
        """The last frame showed nothing (:func:`blank`) …"""
        self.blank_frames = 0
        """… and how many did."""
        self._window = np.ones((self.config.window_px, self.config.window_px), np.uint8)
        nx, ny = geometry.nadir_px
        radius = np.maximum(np.hypot(u - nx, v - ny), 1e-3)
        out_x, out_y = (u - nx) / radius, (v - ny) / radius

        def probe(step_px: float, across_px: float = 0.0) -> npt.NDArray[np.int64]:
            """Per pixel, the index (row-major) of the pixel ``step_px`` outward of it and
            ``across_px`` across the ray, as cv2.remap's nearest neighbour picks it (found by
            remapping the indices themselves); -1 beyond the image."""
            map_xy, map_fraction = cv2.convertMaps(
                u + step_px * out_x - across_px * out_y,
                v + step_px * out_y + across_px * out_x,
                cv2.CV_16SC2,
            )
            indices = np.arange(height * width, dtype=np.float64).reshape(height, width)
            picked = cv2.remap(
                indices,
                map_xy,
                map_fraction,
                cv2.INTER_NEAREST,
                borderMode=cv2.BORDER_CONSTANT,
                borderValue=-1,
            )
            return np.asarray(picked, np.int64)

        self._outward_probe = probe(SEED_PROBE_PX)
        self._step_out_probe, self._step_in_probe = probe(1.0), probe(-1.0)
        self._inward_probe = probe(-SEED_PROBE_PX)
        self._thin_probes = np.stack([probe(-THIN_TOP_PX).ravel(), probe(THIN_TOP_PX).ravel()])
        self._further_probes = np.stack(
            [probe(-THIN_TOP_PX * (1.0 + step / 4)).ravel() for step in range(1, 5)]
            + [probe(-THIN_TOP_PX / 2).ravel()]
        )
        """Along the ray, inward: 1.25–2 times THIN_TOP_PX in quarters, and half of it last
        (:func:`_thin_across`)."""
        self._across_probes = np.stack(
            [
                np.stack(
                    [
                        probe(
                            float(sign * THIN_TOP_PX * np.sin(tilt)),
                            float(sign * THIN_TOP_PX * np.cos(tilt)),
                        )
                        for sign in (-1.0, 1.0)
                    ]
                ).reshape(2, -1)
                for tilt in np.radians(STRIP_TILTS_DEG)
            ]
        )
        """Per direction a strip may run in, the pixels THIN_TOP_PX either way along it."""
        self._beyond_probe = probe(-SEED_PROBE_PX - LINE_ACROSS_PX)
        self._top_reach_px = TOP_REACH_M * geometry.floor_px_per_m
        """TOP_REACH_M in pixels of the floor."""
        self._gain = (UNIT_GAIN, UNIT_GAIN)
        self._set_floor(self.geometry.floor_disparity_px)
        focal_px = geometry.floor_px_per_m * geometry.camera_height_m
        self._paint_gap_px = (
            PAINT_GAP_M * geometry.floor_disparity_px * (focal_px / geometry.focal_baseline_px_m)
        ).astype(np.float32)
        """Rule 11's longest gap between floor rows at each pixel: PAINT_GAP_M at the floor's
        depth there (f/z; foreshortening off the nadir makes it up to a fifth wider in metres)."""
        gap_px = min(GAP_CLOSED_M * geometry.floor_px_per_m, GAP_KERNEL_MAX_PX)
        self._gap_kernel = np.ones((2 * math.ceil(gap_px / 2) + 1,) * 2, np.uint8)
        # Compile the kernels (or load them from numba's cache) now, not in the first frame.
        row_support(np.zeros((1, 1), np.float32), np.zeros((1, 1), np.bool_), 1, ROW_TOLERANCE_M)
        no_runs = np.zeros((1, 1), np.uint8)
        column_support(
            np.zeros((1, 1), np.float32),
            np.zeros((1, 1), np.float32),
            no_runs.view(np.bool_),
            no_runs.view(np.bool_),
            1,
            X_ENERGY_MIN,
            1,
            ROW_TOLERANCE_M,
            no_runs.view(np.bool_).copy(),
        )
        _march_outward(no_runs.view(np.bool_), no_runs.view(np.bool_), (0.0, 0.0), 1, 1, no_runs)
        tiny, none = np.zeros((8, 8), np.float32), np.zeros((8, 8), np.bool_)
        floor_test(tiny, tiny, none, self.config)
        texture_checks(np.zeros((2, 8, 8), np.float32), [tiny, tiny], [none, none], none)
        probed(tiny, np.zeros(tiny.shape, np.int64), np.float32(0.0))
        probed(none, np.zeros(tiny.shape, np.int64), np.False_)
        window_max_at(tiny, 1, none)
        window_max_at(np.zeros((8, 8), np.int32), 1, none)
        self._keep_standing(np.full((8, 8), np.nan, np.float32), none, none)

    # -- geometry -------------------------------------------------------------------------------

    def _set_floor(self, floor_px: F32) -> None:
        self.floor_now = floor_px.astype(np.float32)
        """The floor's disparity with the fitted calibration residual."""
        self._warp_maps = ((self._u - self.floor_now).astype(np.float32), self._v)

    def _fit_residual(self, left: F32, warped: F32, test: FloorTest) -> None:
        """Fit the calibration's residual on the floor: an affine disparity offset and an affine
        row offset (the vertical misalignment a rectification from a slightly wrong calibration
        leaves), by a robust least-squares fit of the floor test's 2-D shift where it agrees."""
        step = 2
        with np.errstate(invalid="ignore"):
            near = np.abs(test.shift_px[::step, ::step]) < RESIDUAL_FIT_PX
        if int(near.sum()) < MIN_FIT_PIXELS:
            return
        shift_x, shift_y = floor_shift_2d(left[::step, ::step], warped[::step, ::step], self.config)
        near &= np.isfinite(shift_x) & np.isfinite(shift_y)
        if int(near.sum()) < MIN_FIT_PIXELS:
            return
        basis = self._basis[:, ::step, ::step][:, near].T
        rate = self.config.offset_rate
        # x: measured against the current warp, the shift adds to the fitted offset (disparity =
        # floor + shift). y: measured against the rows the images came aligned by
        # (``aligned_row_coef``), which lag the fit: the offset is those minus the shift, and
        # the fit moves toward it (moving by the shift alone overshot while they lagged).
        self.residual_coef[0] += rate * robust_affine_fit(basis, shift_x[near])
        row_coef = self.aligned_row_coef - robust_affine_fit(basis, shift_y[near])
        self.residual_coef[1] += rate * (row_coef - self.residual_coef[1])
        self._apply_residual()

    def _affine_px(self, coef: npt.NDArray[np.float64]) -> F32:
        """a + b·u' + c·v' at every pixel."""
        return np.tensordot(coef.astype(np.float32), self._basis, axes=1).astype(np.float32)

    def _apply_residual(self) -> None:
        """The floor's disparity from the fitted calibration residual, and the warp at it."""
        self._set_floor(self.geometry.floor_disparity_px + self._affine_px(self.residual_coef[0]))

    @property
    def row_offset_px(self) -> F32:
        """The fitted row offset at every pixel: the right image's row v shows what the
        calibration puts at row v + offset. Whoever rectifies the images aligns them by it
        (:meth:`DepthPipeline._align_rows`) and says so in :attr:`aligned_row_coef`."""
        return self._affine_px(self.residual_coef[1])

    def _fit_matcher_offset(self, disparity: F32, test: FloorTest) -> None:
        """Fit the matcher's offset on the floor: its disparity minus the calibration's floor
        disparity where it measures the floor (on texture along x, within ``floor_tolerance_px``
        of the floor the floor test has fitted). Fitted on the matcher's own disparities rather
        than taken from the floor test's fit: the two measure the same residual through different
        biases (about 0.1 px apart on the renders). Not on the pixels where the floor test agrees:
        on concrete they are few, and a pallet's strongly textured deck (half a pixel up, its
        windows mixed with the floor between its boards) was a quarter of them, pulling the
        offset up by 0.3 px around it and the deck under the obstacle band."""
        step = 2
        matched = disparity[::step, ::step]
        with np.errstate(invalid="ignore"):
            on_floor = test.matchable[::step, ::step] & (
                np.abs(matched - self.floor_now[::step, ::step]) <= self.config.floor_tolerance_px
            )
        beyond = matched - self.geometry.floor_disparity_px[::step, ::step]
        coarse = coarse_floor_offset(
            beyond, test.matchable[::step, ::step], self._basis[:, ::step, ::step]
        )
        started = self._offset_compared
        self._offset_compared |= coarse is not None
        if coarse is not None and restarts_from_blocks(
            coarse,
            self.matcher_offset_coef,
            self.matcher_offset_px[::step, ::step],
            beyond,
            test.matchable[::step, ::step],
            self.config.floor_tolerance_px,
            started,
        ):
            # The fine fit's start is wrong where the floor is: begin again from the blocks.
            self._set_matcher_offset(coarse.coef)
            self.residual_coef[0] = coarse.coef
            self._apply_residual()
            return
        if int(on_floor.sum()) < MIN_FIT_PIXELS:
            return
        beyond -= self.matcher_offset_px[::step, ::step]
        basis = self._basis[:, ::step, ::step][:, on_floor].T
        self._set_matcher_offset(
            self.matcher_offset_coef
            + self.config.offset_rate * robust_affine_fit(basis, beyond[on_floor])
        )

    def _set_matcher_offset(self, coef: npt.NDArray[np.float64]) -> None:
        self.matcher_offset_coef = coef.astype(np.float64)
        self.matcher_offset_px = self._affine_px(self.matcher_offset_coef)

    # -- state ----------------------------------------------------------------------------------

    @property
    def modelled(self) -> Mask:
        """Pixels whose background is known (both cameras)."""
        return self._modelled

    def modelled_share(self) -> float:
        return float(np.count_nonzero(self._modelled)) / float(self._modelled.size)

    def state(self) -> str:
        """``ready``, ``learning``, ``no_floor`` (long past learning with nearly nothing learned,
        the floor test finds no floor where the calibration puts it), or ``blank`` (the last
        frame showed nothing)."""
        if self.blank:
            return "blank"
        share, cfg = self.modelled_share(), self.config
        if share >= cfg.ready_share:
            return "ready"
        if self.frames >= cfg.no_floor_frames and share < cfg.no_floor_share:
            return "no_floor"
        return "learning"

    def floor_agreement(self, left_rect: U8, right_rect: U8) -> tuple[float, float]:
        """(share of the view where both images have texture, share of those where they agree at
        the floor's disparity) for one rectified pair, learning nothing. The floor test agrees
        only where it is sure: on the default scene's concrete 2–5 % of the textured view, on a
        plain floor 5–27 %, on speckle 5–75 %; with left and right swapped (the floor then
        matches at minus its disparity) 0.03–1.2 % (24 views, three floors, two seeds)."""
        sigma = self.config.blur_sigma_px
        _, inside, test = self._tested(blur(left_rect, sigma), blur(right_rect, sigma))
        textured = test.textured & inside
        count = int(np.count_nonzero(textured))
        if count == 0:
            return 0.0, 0.0
        return count / textured.size, float(np.count_nonzero(test.agree & textured)) / count

    # -- one frame --------------------------------------------------------------------------

    def update(self, left_rect: U8, right_rect: U8, disparity: F32) -> F32:
        """The disparity the tile is built from: this frame under the evidence rules (NaN where
        there is no evidence). Learns from the frame as well."""
        cfg = self.config
        self.blank = blank(left_rect) or blank(right_rect)
        if self.blank:  # nothing measured, nothing learned
            self.blank_frames += 1
            self.inferred = np.zeros(self.shape, np.bool_)
            self.hidden = np.zeros(self.shape, np.bool_)
            return np.full(self.shape, np.nan, np.float32)
        left = blur(left_rect, cfg.blur_sigma_px)
        right = blur(right_rect, cfg.blur_sigma_px)
        warped, inside, test = self._tested(left, right)
        if self.frames == 0:
            # The matcher's offset (through its coarse fit, the residual) before the first
            # evidence: a pair's first frames took the whole floor up to 0.3 m on a poorly
            # calibrated seed (4 m wide "objects" the tracker kept for seconds) until the first
            # fit, two frames later.
            self._fit_matcher_offset(disparity, test)
            warped, inside, test = self._tested(left, right)
        floor_now = self.floor_now

        valid = np.isfinite(disparity)
        with np.errstate(invalid="ignore"):
            near_floor = floor_now + test.shift_px
            # Rule 0: near the floor, on strong texture, the floor test measures where the matcher
            # has nothing.
            refined = np.isfinite(near_floor) & ~valid
            at_floor = valid & (
                np.abs(disparity - self.matcher_offset_px - self.geometry.floor_disparity_px)
                <= cfg.floor_tolerance_px
            )
        # The calibration's residual offsets every disparity, not only the floor's (a yaw between
        # the cameras shifts the whole right image; 0.4 px is 10 cm at the floor): each
        # measurement is taken back to the calibration's geometry, the floor test's by the fitted
        # floor, the matcher's by its own offset on the floor.
        measured = np.where(
            refined,
            near_floor - (floor_now - self.geometry.floor_disparity_px),
            disparity - self.matcher_offset_px,
        ).astype(np.float32)

        both_match, departed, covered, grey_alike, left_alike = self._match(left, warped, inside)
        height_now = self.geometry.height_m(measured)
        # Rule 12: where something was put down, the background vouches for nothing.
        put_down = self._put_down_tops(test, height_now)
        matches = both_match & ~test.contradict & ~put_down
        # The matcher's interpolation (a disparity without texture along x) is a weak measurement:
        # an obstacle there, where both cameras see the floor's background, is the matcher's
        # window dragging a nearby edge over smooth floor (rule 1, fattening).
        interpolated = valid & ~test.matchable
        measured[put_down & interpolated] = np.nan  # rule 12
        observed = matches & ((interpolated & ~at_floor) | (~valid & ~refined))
        anchors = np.isfinite(height_now) & ~interpolated
        support = row_support(
            height_now,
            anchors,
            ROW_REACH_PX,
            ROW_TOLERANCE_M,
            runs=self.plain_floor,  # rule 6c
        )
        # No texture (a plain box top), or texture only across the baseline (board gaps, grain
        # along x: a pallet's deck), lets the matcher carry the floor's disparity in from around:
        # that "floor" is believed only where the background says floor too.
        with np.errstate(invalid="ignore"):
            low = height_now < self.obstacle_min_m
        carried = interpolated & low & ~matches & (test.along_baseline | ~test.textured)
        # Rule 6; with no measurement within reach, only the background vouches (for the floor).
        vouched = np.where(support.anchored, support.consistent, matches & low)
        if support.one_sided_run is not None:  # on a plain floor: rule 6c
            vouched &= ~self._fattened_one_sided(
                left, interpolated, height_now, support.one_sided_run
            )
        # Rule 6b, never against its row: where the row's measurements disagree rule 6 stands
        # (a dark face beside a top's edge along x takes the floor's disparity as well).
        disagreed = support.anchored & ~support.consistent
        dropped = (carried | (interpolated & ~vouched)) & ~disagreed
        held = self._beside_edges(test, height_now, anchors, dropped & low & ~matches)
        carried &= ~held
        vouched |= held
        measured[carried | (interpolated & ~vouched & ~observed)] = np.nan
        bridged = ~np.isfinite(measured) & ~observed & self._in_band(support.bridge_m)
        measured[bridged] = self.geometry.disparity_px(support.bridge_m[bridged], bridged)  # 7
        # Rule 4: where the image departs from the floor's background, the matcher's filling at
        # the floor (a plain top takes the floor's disparity in from around) is no floor evidence,
        # nor a floor reading where the floor's texture is gone (a dark body's lower rim).
        departs = self._modelled & inside & ~both_match
        measured[departs & (interpolated | covered) & low] = np.nan
        if self.plain_floor:
            measured[~self._modelled & ~test.agree & low] = np.nan
        # Floor the image shows: observed, or measured low, over a pixel and its 8 neighbours (a
        # lone floor reading may be a plain body's grey matching the floor's background).
        floor_seen = floor_everywhere_around(observed | (np.isfinite(measured) & low))
        relearn = departed > cfg.relearn_share
        # Rule 8, not where the whole image departs: there a departed region tells no object (a
        # plain top there goes unfilled, unknown, for the frame).
        filled = (
            np.zeros_like(departs)
            if relearn
            else self._fill_departed_regions(
                measured,
                ~np.isfinite(measured) & ~observed & departs & ~self._left_floor(test, left_alike),
            )
        )
        fallen = self._keep_standing(measured, bridged | filled, floor_seen)
        observed |= self._paint(matches, test, inside & ~np.isfinite(measured) & ~fallen)  # 11
        # Floor observations sit at height 0 (measurements are corrected to the calibration's floor).
        out = np.where(observed, self.geometry.floor_disparity_px, measured).astype(np.float32)
        self._close_gaps(out)  # rule 9
        self.inferred = (bridged | filled) & ~fallen & ~observed

        # Rule 10 (not in a frame that re-learns: there the whole image departs).
        hidden = departs | put_down
        self.hidden = np.zeros_like(departs) if relearn else hidden & ~np.isfinite(out)
        if relearn or self.frames % cfg.learn_every == 0:
            # A put-down top's run matches nothing (rule 12) but is no stale background either.
            stale_grey = grey_alike & ~put_down
            self._learn(
                left, warped, inside, test, measured, at_floor, matches, stale_grey, relearn
            )
        if self.frames % cfg.offset_every == cfg.offset_every // 2:  # not in a learning frame
            self._fit_residual(left, warped, test)
            self._fit_matcher_offset(disparity, test)
        self.frames += 1
        return out

    def _fattened_one_sided(
        self, left: F32, interpolated: Mask, height_m: F32, one_sided_run: npt.NDArray[np.int64]
    ) -> Mask:
        """Rule 6c: the raised fillings of a plain floor that rule 6 keeps on the word of one
        measurement, where that measurement is a textured surface's (TEXTURED_ANCHOR_PX
        measurements in a row along it) and the pixel has the floor's grey around it
        (:meth:`_floor_grey_alike`). The matcher carries a textured top's disparity from its
        edge over the plain floor beyond, which nothing bounds on the far side, and a textured
        top does not turn plain at its edge; a plain top is measured at its edges only, a few
        pixels each, and keeps its filling (a plain top of the floor's grey, learned as floor,
        holds its cells on it: docs/accuracy-journal.md, "One-sided rows on a plain floor")."""
        with np.errstate(invalid="ignore"):
            raised = interpolated & (height_m >= self.obstacle_min_m)
        one_sided = raised & (one_sided_run >= TEXTURED_ANCHOR_PX)
        if not one_sided.any():
            return one_sided
        return one_sided & self._floor_grey_alike(left)

    def _floor_grey_alike(self, left: F32) -> Mask:
        """Pixels whose grey (gain-normalised) lies within ``match_min_gray`` of the modelled
        floor's background around them (its mean over FLOOR_GREY_WINDOW_PX): the floor's grey,
        where the model does not hold the pixel itself (it keeps the floor beyond a plain top's
        edge from the model)."""
        window = (FLOOR_GREY_WINDOW_PX, FLOOR_GREY_WINDOW_PX)
        modelled = self._modelled.astype(np.float32)
        weight = cv2.blur(modelled, window)
        with np.errstate(invalid="ignore", divide="ignore"):
            floor_grey = cv2.blur(self.mean[0] * modelled, window) / weight
            grey = gain_normalised(left, self._gain[0])
            alike: Mask = (weight >= FLOOR_GREY_MIN_SHARE) & (
                np.abs(grey - floor_grey) <= self.config.match_min_gray
            )
        return alike

    def _beside_edges(
        self, test: FloorTest, height_m: F32, anchors: Mask, candidates: Mask
    ) -> Mask:
        """Rule 6b: the ``candidates`` (floor readings the matcher filled in, that rule 6 or the
        carried-floor rule drop and no measurement along their row disagrees with) that have
        texture along x in their own row and that the measurements nearest up and down their
        column within EDGE_REACH_PX agree with (:func:`column_support`). Beside an edge along the
        baseline, such as a wall's foot, the floor test's window holds the edge, whose texture
        runs across the baseline only, so the window reads as grain along x and the reading was
        dropped (the floor along the walls along x stayed unknown, two cells wide), yet the
        pixel's own row has texture along x for the matcher (a pallet's boards along x give
        their rows little)."""
        held = np.zeros(self.shape, np.bool_)
        column_support(
            test.left_x_gray,
            height_m,
            anchors,
            candidates,
            self.config.window_px // 2,
            X_ENERGY_MIN,
            EDGE_REACH_PX,
            ROW_TOLERANCE_M,
            held,
        )
        return held

    def _tested(self, left: F32, right: F32) -> tuple[F32, Mask, FloorTest]:
        """The right image warped onto the left by the floor (−1 outside its view), where it is
        inside, and the floor test of the two."""
        map_xy, map_fraction = self._warp_maps
        warped = np.asarray(
            cv2.remap(
                right,
                map_xy,
                map_fraction,
                cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_CONSTANT,
                borderValue=-1.0,
            ),
            dtype=np.float32,
        )
        inside = warped >= 0.0
        return warped, inside, floor_test(left, warped, inside, self.config)

    def _gains(self, left: F32, warped: F32, modelled: Mask) -> tuple[F32, F32]:
        """The gain field of each camera against its background (:func:`gain_fields`) over the
        modelled pixels: exposure, gain and the lighting scale the floor smoothly over the image.
        Before enough pixels are modelled, over every pixel with a background: the means of the
        first learning frames, learnt while auto-exposure may still converge, are then on one
        scale. (With a gain of 1 there, a pixel first learnt in a brighter frame kept a brighter
        mean; once modelled, it departed for good, and rule 8 filled it as an obstacle.)"""
        step = GAIN_SAMPLE_STEP
        sample = modelled[::step, ::step]
        if int(sample.sum()) < GAIN_MIN_SAMPLES:
            sample = (self.confirmed[::step, ::step] > 0) & (warped[::step, ::step] >= 0.0)
        ratios = [
            (image[::step, ::step] / np.maximum(self.mean[side, ::step, ::step], 1.0)).astype(
                np.float32, copy=False
            )
            for side, image in ((0, left), (1, warped))
        ]
        fields = gain_fields(ratios, sample, step, left.shape)
        return fields[0], fields[1]

    def _match(self, left: F32, warped: F32, inside: Mask) -> tuple[Mask, float, Mask, Mask, Mask]:
        """Whether both cameras match their backgrounds at each pixel after gain normalisation
        (their grey and texture: :func:`texture_checks`); the share of modelled pixels that
        departs (for the re-learn decision); where the left background's texture is gone;
        whether both match in grey alone; and whether the left one does."""
        modelled = self._modelled & inside
        self._gain = self._gains(left, warped, modelled)
        normalised = [
            gain_normalised(image, gain)
            for image, gain in zip((left, warped), self._gain, strict=True)
        ]
        alike = [
            modelled & (np.abs(normalised[side] - self.mean[side]) <= self.tolerance[side])
            for side in (0, 1)
        ]
        both = alike[0] & alike[1]
        kept, gone = (
            self._upsampled(sampled)
            for sampled in texture_checks(self.mean, normalised, alike, modelled)
        )
        count = int(np.count_nonzero(modelled))
        departed = 0.0 if count < MIN_FIT_PIXELS else 1.0 - float(np.count_nonzero(both)) / count
        return both & kept, departed, gone, both, alike[0]

    def _left_floor(self, test: FloorTest, left_alike: Mask) -> Mask:
        """Rule 8's exception: pixels where the left image shows its floor's grey with texture
        along x, on a textured floor (a plain floor's background has no texture to show). Among
        rule 8's holes (the right camera's floor-homography partner departs) that is the floor
        beside a top's image-left edge which the right camera cannot see past the top, the
        left-occluded band: baseline · top / camera height wide (9 cm beside the forklift under
        6 m cameras 0.5 m apart), where the disparity chain leaves most pixels unmeasured
        (beside a depth edge); filled at the top's height, it stood the movers' views 10–30 cm
        long on that side (docs/accuracy-journal.md, "The floor the right camera cannot see")."""
        if self.plain_floor:
            return np.zeros(self.shape, np.bool_)
        seen: Mask = test.matchable & left_alike
        return seen

    def _in_band(self, height_m: F32) -> Mask:
        """Heights in the obstacle band (NaN: not). Above it is no surface to fill or bridge with:
        the matcher's picks at the top of its search read there (2.9 m beside a forklift's dark
        front face)."""
        with np.errstate(invalid="ignore"):
            return (height_m >= self.obstacle_min_m) & (height_m <= self.obstacle_max_m)

    def _close_gaps(self, evidence: F32) -> None:
        """Rule 9, in place: floor evidence in a gap narrower than GAP_CLOSED_M between surfaces
        in the obstacle band (a morphological closing of the band's pixels) takes the highest of
        them: a pallet's deck shows the floor between its boards, and a cell whose centre falls
        in such a slot is the pallet's (nav2's rasterisation, and no robot passes there)."""
        height = self.geometry.height_m(evidence)
        band = self._in_band(height)
        closed = cv2.morphologyEx(band.view(np.uint8), cv2.MORPH_CLOSE, self._gap_kernel) > 0
        gap = closed & ~band & np.isfinite(height)
        if gap.any():
            band_height = np.where(band, height, np.float32(-np.inf))
            top = window_max_at(band_height, len(self._gap_kernel) // 2, gap)
            evidence[gap] = self.geometry.disparity_px(top, gap)

    def _paint(self, matches: Mask, test: FloorTest, empty: Mask) -> Mask:
        """Rule 11: pixels of ``empty`` (no evidence) never modelled whose texture runs along the
        baseline, in a column's gap of at most PAINT_GAP_M between floor matching its background:
        a painted line along x, the one floor feature stereo cannot measure at all (its edges
        have no texture along x, the growth stops at them). On the default scene 414 of its 1917
        unknown floor cells lay on such lines (18 % of their cells, 3.7 % elsewhere). A box's edge
        along x has its top, never modelled, on one side; a mover over a line departs from the
        background on both."""
        paint: Mask = np.zeros(self.shape, np.bool_)
        candidates = empty & ~self._modelled & test.along_baseline
        _paint_gaps(matches, candidates, self._paint_gap_px, paint)
        return paint

    def _fill_departed_regions(self, measured: F32, holes: Mask) -> Mask:
        """Rule 8, in place: each connected region of ``holes`` (no evidence, and the image departs
        from the floor's background there) whose edges hold at least REGION_MIN_RAISED
        measurements in the obstacle band takes their upper quartile's height. A plain top (a box, a mover)
        is measured only along part of its outline (one side lies beside the occlusion stereo
        cannot see, the others often match the floor's grey), so its edges show the floor too:
        asking for more raised than floor measurements there missed the movers of other scenes
        (bench/map_accuracy.py --seed 1 --pairs 6: forklift 0 % found, 85 % without the test).
        Returns the pixels it filled."""
        nothing = np.zeros_like(holes)
        count, labels = cv2.connectedComponents(holes.view(np.uint8), connectivity=8)
        if count <= 1:
            return nothing
        near = cv2.dilate(holes.view(np.uint8), np.ones((REGION_EDGE_PX,) * 2, np.uint8)) > 0
        height = self.geometry.height_m(measured[near], near)
        measured_near = np.isfinite(height)
        edge = near.copy()
        edge[near] = measured_near
        # The region beside each edge pixel (the highest label where two meet).
        region = window_max_at(np.asarray(labels, np.int32), REGION_EDGE_PX // 2, edge)
        edge_height = height[measured_near]
        raised = self._in_band(edge_height)
        raised_count = np.bincount(region[raised], minlength=count)
        fill = raised_count >= REGION_MIN_RAISED
        fill[0] = False  # label 0: not a hole
        if not fill.any():
            return nothing
        # The region's height: the upper quartile of its raised edge, whose lower part is the
        # faces below the top's outline.
        order = np.lexsort((edge_height[raised], region[raised]))
        sorted_height = edge_height[raised][order]
        starts = np.concatenate(([0], np.cumsum(raised_count)[:-1]))
        upper = starts + (raised_count * REGION_TOP_QUANTILE).astype(np.int64)
        region_height = np.full(count, np.nan, np.float32)
        region_height[fill] = sorted_height[upper[fill]]
        target = holes.copy()
        target[holes] = fill[labels[holes]]  # labels elsewhere are 0, never filled
        measured[target] = self.geometry.disparity_px(region_height[labels[target]], target)
        return target

    def _keep_standing(self, measured: F32, inferred: Mask, floor_seen: Mask) -> Mask:
        """In place: an inferred surface (rules 7 and 8: a height carried over a hole from its
        edges) stands where the image does not show the floor straight below it. Anything in the
        band stands on the footprint it hides; a face below a top's edge, taken at the top's
        height, would stand out over the floor before it, which the camera sees (a mover's side
        face put its top 1.3 m out over open floor). Such a pixel takes the highest of
        STANDING_STEPS heights, from its own down to the band's foot, whose floor below is not
        seen (on the face, next to it), or none: returns the pixels left with none."""
        fallen = np.zeros_like(inferred)
        _stand(
            measured,
            inferred,
            floor_seen,
            self.geometry.foot_terms,
            self.geometry.focal_baseline_px_m,
            self.obstacle_min_m,
            fallen,
        )
        return fallen

    def _upsampled(self, sampled: Mask) -> Mask:
        """A mask of the sampled grid back at every pixel."""
        height, width = self.shape
        full: Mask = (
            cv2.resize(sampled.view(np.uint8), (width, height), interpolation=cv2.INTER_NEAREST) > 0
        )
        return full

    def _seeds(self, test: FloorTest, at_floor: Mask, inside: Mask) -> Mask:
        # A disparity on an untextured pixel is the matcher's interpolation, not a measurement; and
        # one pixel at the floor's disparity is noise unless most of its window is there too.
        k = (self.config.window_px, self.config.window_px)
        floor_share = cv2.blur(at_floor.astype(np.float32), k)
        stereo_floor = test.x_textured & (floor_share >= FLOOR_WINDOW_SHARE) & ~test.contradict
        seeds: Mask = (test.agree | stereo_floor) & inside
        return seeds

    def _grown(self, left: F32, seeds: Mask, contradict: Mask) -> Mask:
        """Smooth connected regions touched by enough seeds (the plain floor around floor edges),
        crept outward up to the edges that stopped them (:meth:`_up_to_edges`)."""
        cfg = self.config
        gx = cv2.Sobel(left, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
        gy = cv2.Sobel(left, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
        gradient = np.abs(gx) + np.abs(gy)
        smooth = (gradient < cfg.edge_gray) & ~contradict
        count, labels = cv2.connectedComponents(smooth.astype(np.uint8), connectivity=4)
        if count <= 1:
            return np.zeros(self.shape, np.bool_)
        sizes = np.bincount(labels.ravel(), minlength=count)
        # Seeds sit on floor-level edges, next to the smooth floor rather than inside it. An edge
        # at floor level vouches only for its side toward the nadir: there lies the floor, while on
        # the other side of a box's base rises its face (a marking has floor on both sides).
        touching = probed(seeds, self._outward_probe, np.False_)
        # A line at floor level (a marking) vouches for both sides: inward of it as well, where
        # the floor beyond it looks the same as here (a box's base has its face beyond).
        seed_inward = probed(seeds, self._inward_probe, np.False_)
        across = probed(left, self._beyond_probe, np.float32(0.0))
        touching |= seed_inward & (np.abs(across - left) < 2 * cfg.texture_gray)
        seeded = np.bincount(labels[touching & smooth], minlength=count)
        enough = (seeded >= cfg.min_seeds) & (seeded >= cfg.seed_share * sizes)
        enough[0] = False  # label 0: the pixels that are not smooth
        return self._up_to_edges(enough[labels], gradient, contradict)

    def _up_to_edges(self, grown: Mask, gradient: F32, contradict: Mask) -> Mask:
        """``grown`` crept outward (away from the nadir) up to the edge that stopped its growth:
        at most EDGE_CREEP_PX steps, over pixels whose gradient still rises outward (short of the
        edge's middle, its strongest gradient). Growth stops where the blurred edge's gradient
        passes ``edge_gray``, a few pixels short of the edge, and outward is where a floor region
        ends at something rising from it (a box's base, a wall's foot: the floor lies on the
        nadir's side of them, the face beyond; a face crept onto under a top's edge is taken off
        by the line of sight). Without it the plain floor along the walls along the baseline, a
        cell or two wide, was never learned, so never seen free (offline, ``--floor plain``:
        unknown 4.99 → 3.53 % of the seen floor, IoU +0.017; docs/accuracy-journal.md, "The
        floor at a wall's foot")."""
        reach = grown.copy()
        rising = (probed(gradient, self._step_out_probe, np.float32(0.0)) > gradient) & ~contradict
        for _ in range(EDGE_CREEP_PX):
            step = rising & ~reach & probed(reach, self._step_in_probe, np.False_)
            if not step.any():
                break
            reach |= step
        return reach

    def _plain_floor_seen(self, test: FloorTest, inside: Mask) -> bool | None:
        """Whether the floor is plain (less than TEXTURED_FLOOR_SHARE of it textured for the floor
        test), over what is modelled, or all that is seen before that; None: too little floor seen
        to tell."""
        floor = self.modelled & inside
        if np.count_nonzero(floor) < MIN_FIT_PIXELS:
            floor = inside
        count = np.count_nonzero(floor)
        if count < MIN_FIT_PIXELS:
            return None
        return bool(np.count_nonzero(test.textured & floor) < TEXTURED_FLOOR_SHARE * count)

    def _blocked(
        self, test: FloorTest, height: F32, inside: Mask, plain: bool | None
    ) -> tuple[Mask, Mask]:
        """Pixels no learning frame may take for floor: under the columns of this frame's measured
        obstacle points (line of sight), and on a textured floor the plain runs outward of them
        that end within reach (a plain top: its edge was measured, the top beyond has nothing to
        measure, and where it meets a floor of its grey with hardly an edge the model grew over
        it; offline, ``--seed 2``: a light crate on concrete, 50 of its cells free). On a plain
        floor, the plain runs outward of a plain top's edge (:meth:`_plain_tops`), which are
        returned apart as well: they lose a confirmation. ``height``: the frame's evidence in
        metres; ``plain``: :meth:`_plain_floor_seen` (None: the line of sight only)."""
        with np.errstate(invalid="ignore"):
            obstacle = test.textured & (height >= self.obstacle_min_m)
        radius = self.line_of_sight.pixel_radius_px
        feet = np.where(
            obstacle, radius * (1.0 - height / np.float32(self.geometry.camera_height_m)), np.inf
        ).astype(np.float32)
        blocked = self.line_of_sight.blocked(feet)
        if plain is None:
            return blocked, np.zeros_like(blocked)
        if not plain:
            tops = self.line_of_sight.top_runs(
                obstacle, ~test.textured, self._top_reach_px, self.config.window_px
            )
            return blocked | tops, np.zeros_like(tops)
        tops = self._plain_tops(obstacle, height, ~test.textured)
        return blocked | tops, tops

    def _put_down_tops(self, test: FloorTest, height_m: F32) -> Mask:
        """Rule 12, on a textured floor: the plain runs outward of a plain top's edge measured on
        modelled floor (something put down after the model learnt the floor there) that end
        within reach at texture or the image's edge, on the top and on smooth floor beyond it
        alike (a fifth of the mask of a crate put down lies beyond it: its floor is hidden). An
        object standing since start-up never had its edges modelled, so the floor beyond its
        top keeps its evidence. Offline, six textured scenes of 20 s: runs from any measured
        point (as the learning's) left 0.9–1.7 points more of the floor unknown, runs from
        modelled pixels 0.6–1.2 (most of the rest came from patches of the matcher's noise over
        open floor; both measured with rules 1 and 2 alone giving way); from strips, a top's
        edge, IoU moves by −0.0008 to +0.0014 and the unknown share by −0.19 to +0.02 points;
        strips tilted up to 60 degrees off across as well, by −0.0011 to +0.0030 and +0.00 to
        +0.05 points against that. ``height_m``: this frame's measurements."""
        if self.plain_floor:
            return np.zeros(self.shape, np.bool_)
        with np.errstate(invalid="ignore"):
            obstacle = test.textured & self._modelled & (height_m >= self.obstacle_min_m)
        edges = self._top_edges(obstacle, height_m, tilted=True)
        if not edges.any():
            return edges
        return self.line_of_sight.top_runs(
            edges, ~test.textured, self._top_reach_px, self.config.window_px
        )

    def _top_edges(self, obstacle: Mask, height_m: F32, tilted: bool) -> Mask:
        """The pixels of ``obstacle`` (measured at obstacle height) on a plain top's measured
        edge: a strip thin along the ray (the matcher measures its window's width of a plain
        top; a textured top is measured across, so most of it is no strip) that runs on across
        it, or, ``tilted``, in one of STRIP_TILTS_DEG, 20 pixels or more of it (not an object's
        corner, a person's shoulder, nor a patch of the matcher's noise). Tilted edges serve
        rule 12 alone, whose runs must end at texture: on a plain floor nothing ends a run, and
        with them the plain scenes' unknown share rose 1.6–2.6 points (offline, 20 s)."""
        near = cv2.dilate(obstacle.view(np.uint8), self._window) > 0
        strip = np.zeros_like(obstacle)
        _thin_across(
            obstacle.ravel(),
            height_m.ravel(),
            near.ravel(),
            self._thin_probes,
            self._further_probes,
            self._across_probes if tilted else self._across_probes[:1],
            strip.ravel(),
        )
        if not strip.any():
            return strip
        # Areas by bincount: OpenCV's statistics cost 0.45 ms a call here, the labels 0.05.
        count, labels = cv2.connectedComponents(strip.view(np.uint8))
        strip &= (np.bincount(labels.ravel(), minlength=count) >= MIN_STRIP_PX)[labels]
        return strip

    def _plain_tops(self, obstacle: Mask, height: F32, plain: Mask) -> Mask:
        """On a plain floor: the plain pixels outward of a plain top's measured edge, within
        reach, open run or not (a top of the floor's grey meets the floor with no edge at all;
        live, ``--floor plain --plain-objects``: a 1.3 m box's top 39 % free, 12 % with this
        rule and the contested footprints of fusion). The edge is a
        strip measured in the band and thin along the ray; a textured top is measured across
        and bounds no run, nor does its far edge. The floor beyond a plain top within the reach
        is kept from the model too while its edge is found (nothing tells the two apart): that
        is the rule's cost in unknown floor."""
        runs = np.zeros(self.shape, np.uint8)
        _march_outward(
            self._top_edges(obstacle, height, tilted=False),
            plain & ~obstacle,
            self.geometry.nadir_px,
            round(self._top_reach_px),
            self.config.window_px,
            runs,
        )
        # Rays from neighbouring starts part outward: close the gaps between them.
        closed: Mask = cv2.dilate(runs, np.ones((3, 3), np.uint8)) > 0
        return closed

    def _learn(
        self,
        left: F32,
        warped: F32,
        inside: Mask,
        test: FloorTest,
        measured: F32,
        at_floor: Mask,
        matches: Mask,
        grey_alike: Mask,
        relearn: bool,
    ) -> None:
        cfg = self.config
        seeds = self._seeds(test, at_floor, inside)
        confirmed = (seeds | self._grown(left, seeds, test.contradict)) & inside
        plain = self._plain_floor_seen(test, inside)
        if plain is not None:
            self.plain_floor = plain
        height = self.geometry.height_m(measured)
        blocked, tops = self._blocked(test, height, inside, plain)
        confirmed &= ~blocked
        modelled = self.modelled & inside
        if relearn:
            # Most of the floor changed at once, not as the gain field has it: start again here.
            self.relearned += 1
            self.confirmed[~confirmed] = 0
            self._stale[:] = 0
            fresh = confirmed
            gains = (UNIT_GAIN, UNIT_GAIN)
        else:
            fresh = confirmed & (self.confirmed == 0)
            gains = self._gain
            # A stale background (module docstring, Learning): the matcher reads the floor where
            # nothing stands, the grey matches, the texture does not.
            with np.errstate(invalid="ignore"):
                standing = height >= self.obstacle_min_m
            stale = modelled & grey_alike & ~matches & at_floor & ~blocked & ~standing
            self._stale[~stale] = 0
            self._stale[stale] += 1
            restart = self._stale >= cfg.stale_learning_frames
            if restart.any():
                self.restarted += int(np.count_nonzero(restart))
                self._stale[restart] = 0
                fresh |= restart
        normalised = [
            gain_normalised(image, gain) for image, gain in zip((left, warped), gains, strict=True)
        ]
        if not relearn:
            # Confirmations that disagree (module docstring, Learning): start again from the image.
            pending = confirmed & ~fresh & ~self._modelled
            for side in (0, 1):
                moved = pending & (
                    np.abs(normalised[side] - self.mean[side]) > self.tolerance[side]
                )
                self.confirmed[moved] = 0
                self.disagreed += int(np.count_nonzero(moved & ~fresh))
                fresh |= moved
        # Modelled pixels learn only while they still match: a pixel under something never does.
        learning = confirmed & ~fresh & (matches | ~modelled)
        rate = learning.astype(np.float32) * np.float32(cfg.learn_rate)
        var_start = np.float32(cfg.match_min_gray**2 / cfg.match_sigmas**2)
        for side in (0, 1):
            mean, var = self.mean[side], self.var[side]
            delta = normalised[side] - mean
            mean += rate * delta
            var += rate * (delta * delta - var)
            np.copyto(mean, normalised[side], where=fresh)
            np.copyto(var, var_start, where=fresh)
            np.maximum(
                np.maximum(np.sqrt(var) * np.float32(cfg.match_sigmas), cfg.match_min_gray),
                mean * np.float32(cfg.match_relative),
                out=self.tolerance[side],
            )
        self.confirmed += (confirmed & (self.confirmed < 255)).view(np.uint8)
        # A plain top's run is withdrawn a confirmation too: its edge is not found in every frame,
        # and the frames between would confirm the top (long-learnt floor under a passing mover's
        # run keeps its hundreds).
        self.confirmed -= (tops & (self.confirmed > 0)).view(np.uint8)
        self._modelled = self.confirmed >= cfg.confirm_frames
