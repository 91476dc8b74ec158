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
   clears a cell. Not in a frame that re-learns: there the whole image departs.
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

import itertools
import math
from dataclasses import dataclass
from typing import Any, NamedTuple, TypeVar

import cv2
import numpy as np
import numpy.typing as npt

from common.compiled import compiled
from services.depth.stereo import Rectifier

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]
U8 = npt.NDArray[np.uint8]
Mask = npt.NDArray[np.bool_]
ScalarT = TypeVar("ScalarT", np.uint8, np.float32)

FLOOR_WINDOW_SHARE = 0.75
"""A stereo seed needs this share of its window measured at the floor's disparity."""
RESIDUAL_FIT_PX = 0.5
"""The residual is fitted to pixels the floor test measures within this of the floor."""
RESIDUAL_SCALE_PX = 0.1
"""Scale of the robust weights in the calibration-residual fit."""
RESIDUAL_RIDGE = 0.1
"""Slopes need the pixels spread over the image (variance of u', v' over this) to count fully."""
MAX_RESIDUAL_PX = 1.0
"""A good calibration's residual is a fraction of this; a fit beyond it is not believed."""
MIN_FIT_PIXELS = 200
"""Fewer pixels than this fit no residual, and a share of fewer modelled pixels decides nothing."""
SEED_PROBE_PX = 3.0
"""A smooth pixel is touched by a seed this far outward of it (away from the nadir)."""
EDGE_CREEP_PX = 3
"""Steps (pixels) the learned floor creeps outward toward the edge that stopped its growth
(:meth:`FloorModel._up_to_edges`)."""
X_ENERGY_MIN = 0.1
"""Variance of the x-gradient (gray levels² per pixel²) below which no window is x-textured (nor
a pixel's own row, over the window's width: rule 6b) …"""
X_ENERGY_SHARE = 0.06
"""… nor below this share of the y-gradient's (texture along the baseline: the aperture problem)."""
GAIN_SAMPLE_STEP = 6
"""Gains are taken from every this-many-th pixel in each direction (the gain field against the
background; the floor test's one gain between the cameras)."""
GAIN_BLOCKS = 4
"""The gain field starts from the median ratio in each of this many × this many blocks …"""
GAIN_BLOCK_MIN = 12
"""… holding at least this many sampled pixels …"""
GAIN_AGREE = 0.05
"""… and is one gain, their overall median, while every block's lies within this share of it;
else a quadratic surface, fitted to the blocks less those it misses by more than this share (an
object covers them; one at a time, the worst first) …"""
GAIN_BLOCKS_KEPT = 8
"""… keeping at least this many …"""
GAIN_OUTLIER = 0.1
"""… then to the sampled pixels within this share of that fit (a mover: not the light) …"""
GAIN_EXTRAPOLATION = 1.25
"""… and held within this factor of the kept blocks' medians (beyond their centres the surface
extrapolates)."""
GAIN_MIN_SAMPLES = 6 * GAIN_BLOCK_MIN
"""With fewer modelled samples than this the gain is fitted over every pixel with a background;
with fewer of those, it is 1."""
GAIN_RATIO_MAX = 64.0
"""A ratio to the background beyond this is taken as this, for the blocks' medians only."""
QUADRATIC_TERMS = 6
UNIT_GAIN = np.ones((1, 1), np.float32)
"""One gain of 1, as a field that broadcasts (read-only: shared)."""
UNIT_GAIN.setflags(write=False)
LINE_ACROSS_PX = 3.0
"""Beyond an inward seed, the floor this much further on is compared with the pixel."""
LINE_OF_SIGHT_MARGIN_PX = 1.5
"""An obstacle's foot within this of a pixel does not block it (the floor at an object's base)."""
LINE_OF_SIGHT_BIN_PX = 2.0
"""Polar bins of the line-of-sight test, in radius and in arc at the image's rim."""
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


@dataclass(frozen=True)
class FloorModelConfig:
    enabled: bool = True
    window_px: int = 5
    """Side of the floor test's correlation window (processing pixels; odd: centred on its pixel)."""
    blur_sigma_px: float = 1.0
    """Gaussian blur before every comparison: sensor noise and JPEG blocks matter less."""
    texture_gray: float = 1.0
    """Local standard deviation (gray levels) both windows need for the floor test to speak."""
    agree_zncc: float = 0.7
    contradict_zncc: float = 0.3
    measure_zncc: float = 0.5
    """Below this correlation the floor test measures no shift …"""
    measure_energy: float = 4.0
    """… nor below this x-gradient variance (gray levels² per pixel²): on weaker texture its
    shift is noisier than the matcher's disparity (on concrete, |residual| p95 0.17 px above 8,
    0.36–0.64 px below 2, the matcher's 0.24–0.32 px)."""
    max_shift_px: float = 1.0
    """The shift is a linearisation: trusted up to this far from the floor's disparity."""
    floor_shift_px: float = 0.2
    """Residual shift (processing pixels) within which the floor test agrees (≈ 5 cm)."""
    raised_shift_px: float = 0.35
    """Residual shift beyond which it contradicts (≈ 9 cm; the obstacle band starts at 10)."""
    floor_tolerance_px: float = 0.25
    """Stereo measures the floor where its disparity is within this of the floor's."""
    edge_gray: float = 1.0
    """Gradient (gray levels per pixel, blurred image) that stops the model's growth."""
    min_seeds: int = 40
    """A smooth region is learned as floor only with at least this many pixels touched by seeds …"""
    seed_share: float = 0.002
    """… and at least this share of its pixels."""
    match_sigmas: float = 4.0
    match_min_gray: float = 6.0
    match_relative: float = 0.05
    """A pixel matches its background within max(match_sigmas·σ, match_min_gray, match_relative·mean)."""
    learn_rate: float = 0.05
    learn_every: int = 4
    """Learn (grow, line of sight, update) every this many frames; the floor changes slowly."""
    confirm_frames: int = 2
    ready_share: float = 0.3
    """The model reports *ready* once this share of the image is modelled."""
    relearn_share: float = 0.5
    """Re-learn when more than this share of the modelled pixels departs at once."""
    stale_learning_frames: int = 3
    """Learning frames in a row a modelled pixel departs in texture alone, where the matcher reads
    the floor and nothing stands, before it starts again from the image (module docstring,
    Learning); 1–255."""
    offset_every: int = 4
    offset_rate: float = 0.5

    def __post_init__(self) -> None:
        for name in ("stale_learning_frames", "confirm_frames"):  # uint8 counts per pixel
            if not 1 <= getattr(self, name) <= 255:
                raise ValueError(f"{name} {getattr(self, name)} is not in 1–255")


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


@dataclass(frozen=True)
class RowSupport:
    """What the measurements bounding each pixel along its row say of it (evidence rules 6, 7)."""

    anchored: Mask
    """A measurement lies within reach on at least one side."""
    consistent: Mask
    """Every measurement within reach on either side agrees with the pixel's height."""
    bridge_m: F32
    """Where measurements within reach on both sides agree with each other: the height between
    them, interpolated along the row; NaN elsewhere."""
    one_sided_run: npt.NDArray[np.int64] | None
    """Where a measurement lies within reach on one side only: how many measurements in a row
    the nearest one belongs to (a textured top's many, a plain top's edge a few: rule 6c); 0
    elsewhere. None unless asked for (it costs 0.4 ms a frame)."""


def row_support(
    height_m: F32, anchors: Mask, reach_px: int, tolerance_m: float, runs: bool = False
) -> RowSupport:
    """The nearest anchor (measured pixel) left and right of every pixel in its row, and how their
    heights relate to the pixel's and to each other (and with ``runs``, the one-sided run)."""
    anchored = np.empty(height_m.shape, np.bool_)
    consistent = np.empty(height_m.shape, np.bool_)
    bridge = np.empty(height_m.shape, np.float32)
    one_sided_run = np.empty(height_m.shape if runs else (0, 0), np.int64)
    _scan_rows(
        height_m, anchors, reach_px, tolerance_m, anchored, consistent, bridge, one_sided_run
    )
    return RowSupport(anchored, consistent, bridge, one_sided_run if runs else None)


@compiled
def _scan_rows(
    height_m: F32,
    anchors: Mask,
    reach_px: int,
    tolerance_m: float,
    anchored: Mask,
    consistent: Mask,
    bridge: F32,
    one_sided_run: npt.NDArray[np.int64],
) -> None:
    """Per row, two passes, the nearest anchor to the left then to the right (a sequential scan:
    a dozen whole-frame numpy passes cost 3 ms, this 0.2 ms); first the anchors' run lengths,
    where ``one_sided_run`` is not empty."""
    rows, cols = height_m.shape
    tolerance = np.float32(tolerance_m)
    left_col = np.empty(cols, np.int64)
    left_height = np.empty(cols, np.float32)
    run = np.empty(cols, np.int64)
    runs = one_sided_run.shape[0] > 0
    for row in range(rows):
        col = 0
        while runs and col < cols:
            start = col
            while col < cols and anchors[row, col]:
                col += 1
            run[start:col] = col - start
            if col == start:
                run[col] = 0
                col += 1
        last, last_height = -reach_px - 1, np.float32(np.nan)
        for col in range(cols):
            if anchors[row, col]:
                last, last_height = col, height_m[row, col]
            left_col[col], left_height[col] = last, last_height
        nearest, nearest_height = cols + reach_px + 1, np.float32(np.nan)
        for col in range(cols - 1, -1, -1):
            if anchors[row, col]:
                nearest, nearest_height = col, height_m[row, col]
            height, start, start_height = height_m[row, col], left_col[col], left_height[col]
            near_left, near_right = col - start <= reach_px, nearest - col <= reach_px
            anchored[row, col] = near_left or near_right
            if runs:
                one_sided = near_left != near_right
                nearest_run = run[start] if near_left else run[min(nearest, cols - 1)]
                one_sided_run[row, col] = nearest_run if one_sided else 0
            agrees = True  # NaN never agrees
            if near_left and not abs(height - start_height) <= tolerance:
                agrees = False
            if near_right and not abs(height - nearest_height) <= tolerance:
                agrees = False
            consistent[row, col] = agrees
            if near_left and near_right and abs(start_height - nearest_height) <= tolerance:
                along = np.float32(col - start) / np.float32(max(nearest - start, 1))
                bridge[row, col] = start_height + (nearest_height - start_height) * along
            else:
                bridge[row, col] = np.float32(np.nan)


@compiled
def _column_support(
    gradient_x: F32,
    height_m: F32,
    anchors: Mask,
    candidates: Mask,
    half_px: int,
    reach_px: int,
    tolerance_m: float,
    held: Mask,
) -> None:
    """Rule 6b at the ``candidates``: texture along x in the pixel's own row (the x-gradient's
    variance over ``2·half_px + 1`` columns above X_ENERGY_MIN), and a measurement (``anchors``)
    within ``reach_px`` up or down its column, every such nearest one agreeing with its height
    (as :func:`_scan_rows` along a row; NaN never agrees). At the candidates alone: over the
    whole image (the row's variance by blurs, the row scan on the transpose) the rule cost 0.87
    ms a frame, so 0.14 ms."""
    height, width = height_m.shape
    tolerance = np.float32(tolerance_m)
    for row in range(height):
        for col in range(width):
            if candidates[row, col]:
                held[row, col] = _row_textured(gradient_x, row, col, half_px) and _column_agrees(
                    height_m, anchors, row, col, reach_px, tolerance
                )


@compiled
def _row_textured(gradient_x: F32, row: int, col: int, half_px: int) -> bool:
    """The x-gradient's variance over the pixel's row, ``half_px`` either side (fewer at the
    image's edges), is above X_ENERGY_MIN."""
    first, last = max(col - half_px, 0), min(col + half_px, gradient_x.shape[1] - 1)
    total, squares = np.float32(0.0), np.float32(0.0)
    for c in range(first, last + 1):
        g = gradient_x[row, c]
        total += g
        squares += g * g
    count = np.float32(last - first + 1)
    mean = total / count
    return bool(squares / count - mean * mean > np.float32(X_ENERGY_MIN))


@compiled
def _column_agrees(
    height_m: F32, anchors: Mask, row: int, col: int, reach_px: int, tolerance_m: np.float32
) -> bool:
    """An anchor lies within ``reach_px`` up or down the pixel's column, and the nearest on each
    side agrees with its height within ``tolerance_m`` (NaN never agrees)."""
    value, anchored = height_m[row, col], False
    for step in (-1, 1):
        r = row + step
        while 0 <= r < height_m.shape[0] and abs(r - row) <= reach_px:
            if anchors[r, col]:
                anchored = True
                if not abs(value - height_m[r, col]) <= tolerance_m:
                    return False
                break
            r += step
    return anchored


@compiled
def _foot(
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
                foot_row, foot_col = _foot(row, col, height_m, terms)
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


@dataclass(frozen=True)
class FloorGeometry:
    """What the floor model needs of a pair's rectified geometry."""

    floor_disparity_px: F32
    """Disparity of the plane z = 0 at every rectified pixel."""
    ray_down: F32
    """−ray_z of every pixel's ray (scaled so that depth z multiplies it): height = C_z − z·ray_down."""
    camera_height_m: float
    focal_baseline_px_m: float
    """f·b: depth z = f·b / d."""
    nadir_px: tuple[float, float]
    """Where vertical lines vanish in the rectified left image (the point below the camera)."""
    floor_px_per_m: float
    """Pixels a metre of floor spans below the camera (focal length over camera height)."""
    depth_per_m_down: float
    """Depth (along the optical axis) a point gains per metre it moves straight down: 0 for rays
    that are all vertical (the point below shows at the same pixel)."""

    @staticmethod
    def from_rectifier(rectifier: Rectifier, rays_world: F32) -> FloorGeometry:
        down = np.maximum(-rays_world[2].astype(np.float64), 1e-9)
        height_m = float(rectifier.C_world[2])
        focal_baseline = rectifier.focal_px * rectifier.baseline_m
        below = rectifier.R_world_rect.T @ np.array([0.0, 0.0, -1.0])
        if below[2] <= 1e-6:
            raise ValueError("the camera does not look down: no floor model")
        nadir = (
            rectifier.cx_px + rectifier.focal_px * below[0] / below[2],
            rectifier.cy_px + rectifier.focal_px * below[1] / below[2],
        )
        return FloorGeometry(
            floor_disparity_px=(focal_baseline * down / height_m).astype(np.float32),
            ray_down=down.astype(np.float32),
            camera_height_m=height_m,
            focal_baseline_px_m=focal_baseline,
            nadir_px=(float(nadir[0]), float(nadir[1])),
            floor_px_per_m=rectifier.focal_px / height_m,
            depth_per_m_down=float(below[2]),
        )

    @property
    def foot_terms(self) -> tuple[F32, float, float, float, float]:
        """What :func:`_foot` needs of the geometry: ray_down, the camera's height, the depth a
        metre down adds, the nadir's row and column."""
        return (
            self.ray_down,
            self.camera_height_m,
            self.depth_per_m_down,
            self.nadir_px[1],
            self.nadir_px[0],
        )

    def height_m(self, disparity_px: F32, at: Mask | None = None) -> F32:
        """The height of the surface at ``disparity_px`` at every pixel, or with ``at`` at those
        pixels only (``disparity_px`` holds their values, in order): the same figures, without the
        passes over the rest of the image."""
        ray_down = self.ray_down if at is None else self.ray_down[at]
        with np.errstate(divide="ignore", invalid="ignore"):
            depth = np.float32(self.focal_baseline_px_m) / disparity_px
        height: F32 = (np.float32(self.camera_height_m) - depth * ray_down).astype(np.float32)
        return height

    def disparity_px(self, height_m: F32, at: Mask | None = None) -> F32:
        """The disparity of a surface at ``height_m`` at every pixel (inverse of :meth:`height_m`),
        or with ``at`` at those pixels only (``height_m`` holds their values, in order)."""
        ray_down = self.ray_down if at is None else self.ray_down[at]
        with np.errstate(divide="ignore", invalid="ignore"):
            disparity: F32 = (
                np.float32(self.focal_baseline_px_m)
                * ray_down
                / (np.float32(self.camera_height_m) - height_m)
            ).astype(np.float32)
        return disparity


@dataclass(frozen=True)
class FloorTest:
    """Left against the floor-warped right, per pixel (see :func:`floor_test`)."""

    textured: Mask
    """Enough texture in both windows for the test to speak."""
    x_textured: Mask
    """Enough texture *along x* for any horizontal-baseline match: elsewhere (a uniform surface,
    or grain and gaps along the baseline) a disparity is the matcher's interpolation."""
    along_baseline: Mask
    """Texture, but hardly any of it along x (grain, board gaps along the baseline)."""
    matchable: Mask
    """Texture, and texture along x, in the *left* image's window alone: there the matcher's
    disparity is a measurement, at whatever height; elsewhere (a uniform surface, sensor noise,
    texture only across the baseline) the matcher carried it in from around. (``x_textured``
    needs the floor-warped right image to agree, which a raised surface's does not.)"""
    shift_px: F32
    """Disparity minus the floor's, measured to a fraction of a pixel; NaN where not measured."""
    agree: Mask
    contradict: Mask
    left_x_gray: F32
    """The left image's x-gradient (gray levels per pixel), one of the test's planes: rule 6b
    reads a pixel's own row of it."""


class FloorTestThresholds(NamedTuple):
    """The floor test's thresholds in float32, as numpy compares a float32 image with a number."""

    texture_var: np.float32
    agree_zncc: np.float32
    contradict_zncc: np.float32
    measure_zncc: np.float32
    measure_energy: np.float32
    max_shift_px: np.float32
    floor_shift_px: np.float32
    raised_shift_px: np.float32

    @staticmethod
    def of(config: FloorModelConfig) -> FloorTestThresholds:
        return FloorTestThresholds(
            *(
                np.float32(value)
                for value in (
                    config.texture_gray**2,
                    config.agree_zncc,
                    config.contradict_zncc,
                    config.measure_zncc,
                    config.measure_energy,
                    config.max_shift_px,
                    config.floor_shift_px,
                    config.raised_shift_px,
                )
            )
        )


@compiled
def _floor_decisions(
    means: F32,
    inside: Mask,
    limits: FloorTestThresholds,
    textured: Mask,
    x_textured: Mask,
    along_baseline: Mask,
    matchable: Mask,
    shift_px: F32,
    agree: Mask,
    contradict: Mask,
) -> None:
    """The floor test's verdicts at each pixel from its window means (``FLOOR_TEST_TERMS``'
    order), in float32 as the numpy expressions they replace: a few dozen whole-image passes
    cost more than the window sums."""
    x_energy_min, x_energy_share = np.float32(X_ENERGY_MIN), np.float32(X_ENERGY_SHARE)
    tiny, nan = np.float32(1e-6), np.float32(np.nan)
    rows, cols = inside.shape
    for row in range(rows):
        for col in range(cols):  # & and | rather than and, or: fewer branches
            mean_l, mean_r, mean_g = means[0, row, col], means[1, row, col], means[2, row, col]
            mean_across, mean_lx, mean_ly = (
                means[3, row, col],
                means[4, row, col],
                means[5, row, col],
            )
            var_l = means[6, row, col] - mean_l * mean_l
            var_r = means[7, row, col] - mean_r * mean_r
            covariance = means[8, row, col] - mean_l * mean_r
            energy = means[9, row, col] - mean_g * mean_g
            along = means[10, row, col] - (mean_r - mean_l) * mean_g
            energy_across = means[11, row, col] - mean_across * mean_across
            left_energy_x = means[12, row, col] - mean_lx * mean_lx
            left_energy_y = means[13, row, col] - mean_ly * mean_ly
            left_textured = var_l > limits.texture_var
            is_textured = left_textured & (var_r > limits.texture_var) & inside[row, col]
            zncc = covariance / np.sqrt(max(var_l * var_r, tiny))
            shift = along / max(energy, tiny)
            size = abs(shift)
            # Texture along x, against an absolute floor and against the texture across it: grain
            # or board gaps along the baseline have gradients, but none along x to match on.
            is_along = is_textured & (energy < energy_across * x_energy_share)
            is_x_textured = is_textured & (energy > x_energy_min) & (not is_along)
            strong = is_x_textured & (energy >= limits.measure_energy)
            measured = strong & (zncc >= limits.measure_zncc) & (size < limits.max_shift_px)
            # A shift too large for the linearisation to measure is still no floor.
            strong &= size >= limits.max_shift_px
            textured[row, col] = is_textured
            x_textured[row, col] = is_x_textured
            along_baseline[row, col] = is_along
            matchable[row, col] = (
                left_textured
                & (left_energy_x > x_energy_min)
                & (left_energy_x >= left_energy_y * x_energy_share)
            )
            shift_px[row, col] = shift if measured else nan
            agree[row, col] = (
                measured & (zncc >= limits.agree_zncc) & (size <= limits.floor_shift_px)
            )
            contradict[row, col] = is_textured & (
                (zncc < limits.contradict_zncc)
                | strong
                | (measured & (size >= limits.raised_shift_px))
            )


NO_PLANE = -1
"""A term of :func:`window_means` that is one plane, not a product of two."""


def window_means(planes: F32, terms: npt.NDArray[np.int64], window_px: int) -> F32:
    """The mean over a ``window_px`` square about every pixel of each term, a row of ``terms``:
    ``planes[i]``, or the float32 product ``planes[i] * planes[j]``, (i, j) or (i, NO_PLANE). Equal
    to ``cv2.blur`` of each term to the bit (sums in float64 in its order, borders reflected
    without the edge pixel), in one pass without the products' images: a dozen blurs and their
    products as numpy passes were the floor test's main cost."""
    if window_px % 2 != 1:
        raise ValueError(f"window_means needs an odd window, not {window_px}")
    means = np.empty((len(terms), *planes.shape[1:]), np.float32)
    _window_means(np.ascontiguousarray(planes, np.float32), terms, window_px // 2, means)
    return means


@compiled
def _reflected(index: int, length: int) -> int:
    """``index`` reflected into [0, length) without repeating the edge (cv2.BORDER_REFLECT_101)."""
    if length == 1:
        return 0
    while index < 0 or index >= length:
        index = -index if index < 0 else 2 * length - 2 - index
    return index


@compiled
def _window_means(planes: F32, terms: npt.NDArray[np.int64], half_px: int, means: F32) -> None:
    """cv2.blur's box filter for float32, term by term: each row's sums along x (left to right),
    then a running sum of the last rows' sums down each column, scaled once."""
    _, rows, cols = planes.shape
    size = 2 * half_px + 1
    scale = 1.0 / (size * size)
    padded = np.empty(cols + 2 * half_px, np.float64)
    row_sums = np.empty((size, cols), np.float64)  # the last ``size`` rows' sums, a ring
    column = np.empty(cols, np.float64)
    for term in range(terms.shape[0]):
        first, product = planes[terms[term, 0]], terms[term, 1] != NO_PLANE
        second = planes[max(terms[term, 1], 0)]
        column[:] = 0.0
        for step in range(rows + 2 * half_px):  # the window's rows from its top, reflected
            row = _reflected(step - half_px, rows)
            # Loops over rows' views (not 2-D indexing): so they vectorise.
            values, first_row, second_row = (
                padded[half_px : half_px + cols],
                first[row],
                second[row],
            )
            if product:
                for col in range(cols):
                    values[col] = first_row[col] * second_row[col]
            else:
                for col in range(cols):
                    values[col] = first_row[col]
            for k in range(half_px):
                padded[half_px - 1 - k] = padded[half_px + _reflected(-1 - k, cols)]
                padded[half_px + cols + k] = padded[half_px + _reflected(cols + k, cols)]
            sums = row_sums[step % size]
            if size == 5:  # the windows this module uses: unrolled, the loop vectorises
                for col in range(cols):
                    sums[col] = (
                        padded[col]
                        + padded[col + 1]
                        + padded[col + 2]
                        + padded[col + 3]
                        + padded[col + 4]
                    )
            else:
                sums[:] = padded[:cols]
                for k in range(1, size):
                    shifted = padded[k : k + cols]
                    for col in range(cols):
                        sums[col] += shifted[col]
            if step < size - 1:
                for col in range(cols):
                    column[col] += sums[col]
                continue
            out, oldest = means[term, step - size + 1], row_sums[(step + 1) % size]
            for col in range(cols):
                total = column[col] + sums[col]
                out[col] = np.float32(total * scale)
                column[col] = total - oldest[col]


def _gradient(image: F32, dx: int, dy: int, out: F32 | None = None) -> F32:
    """Sobel derivative along x (dx) or y (dy), in gray levels per pixel of a smoothed image
    (into ``out`` if given)."""
    gradient: F32 = np.asarray(
        cv2.Sobel(image, cv2.CV_32F, dx, dy, dst=out, ksize=3, scale=1.0 / 16.0), np.float32
    )
    return gradient


FLOOR_TEST_PLANES = ("left", "warped", "gradient", "across", "left_x", "left_y", "error")
"""The floor test's planes: both images (the right one floor-warped, at the left one's gain), the
x- and y-gradients of their sum and of the left image, and the right minus the left."""
_LEFT, _WARPED, _GRADIENT, _ACROSS, _LEFT_X, _LEFT_Y, _ERROR = range(len(FLOOR_TEST_PLANES))
# The terms whose window means it takes (:func:`_floor_decisions` reads them in this order).
FLOOR_TEST_TERMS = np.array(
    [
        (_LEFT, NO_PLANE),
        (_WARPED, NO_PLANE),
        (_GRADIENT, NO_PLANE),
        (_ACROSS, NO_PLANE),
        (_LEFT_X, NO_PLANE),
        (_LEFT_Y, NO_PLANE),
        (_LEFT, _LEFT),
        (_WARPED, _WARPED),
        (_LEFT, _WARPED),
        (_GRADIENT, _GRADIENT),
        (_ERROR, _GRADIENT),
        (_ACROSS, _ACROSS),
        (_LEFT_X, _LEFT_X),
        (_LEFT_Y, _LEFT_Y),
    ],
    np.int64,
)


def floor_test(left: F32, warped: F32, inside: Mask, config: FloorModelConfig) -> FloorTest:
    """Zero-mean normalised cross-correlation of ``left`` and ``warped`` (the right image remapped
    at the floor's disparity) over a small window, and the residual shift between them.

    The shift is one Lucas–Kanade step along x: where the surface has disparity d = d_floor + δ,
    left(u) = warped(u − δ) ≈ warped(u) − δ·∂warped/∂u, so δ = ⟨(warped − left)·g⟩ / ⟨g²⟩ over the
    window with g the x-gradient, means removed, after one global gain between the cameras.
    """
    step = GAIN_SAMPLE_STEP
    left_sample, right_sample = left[::step, ::step], warped[::step, ::step]
    seen = right_sample >= 0
    ratio = float(left_sample[seen].mean()) / max(float(right_sample[seen].mean()), 1.0)
    planes = np.empty((len(FLOOR_TEST_PLANES), *left.shape), np.float32)
    np.copyto(planes[_LEFT], left)
    warped = np.multiply(warped, np.float32(ratio), out=planes[_WARPED])
    both = left + warped
    _gradient(both, 1, 0, out=planes[_GRADIENT])
    _gradient(both, 0, 1, out=planes[_ACROSS])
    _gradient(left, 1, 0, out=planes[_LEFT_X])
    _gradient(left, 0, 1, out=planes[_LEFT_Y])
    np.subtract(warped, left, out=planes[_ERROR])
    means = window_means(planes, FLOOR_TEST_TERMS, config.window_px)
    shape = left.shape
    test = FloorTest(
        textured=np.empty(shape, np.bool_),
        x_textured=np.empty(shape, np.bool_),
        along_baseline=np.empty(shape, np.bool_),
        matchable=np.empty(shape, np.bool_),
        shift_px=np.empty(shape, np.float32),
        agree=np.empty(shape, np.bool_),
        contradict=np.empty(shape, np.bool_),
        left_x_gray=planes[_LEFT_X],
    )
    _floor_decisions(
        means,
        inside,
        FloorTestThresholds.of(config),
        test.textured,
        test.x_textured,
        test.along_baseline,
        test.matchable,
        test.shift_px,
        test.agree,
        test.contradict,
    )
    return test


def floor_shift_2d(left: F32, warped: F32, config: FloorModelConfig) -> tuple[F32, F32]:
    """Residual shift (x, y) between ``left`` and ``warped`` per pixel: the 2-D Lucas–Kanade step
    (x alone is what :func:`floor_test` measures every frame; y shows the rows' misalignment).
    NaN where the window's gradients leave a component undetermined."""
    k = (config.window_px, config.window_px)
    both = left + warped
    gx = np.asarray(cv2.Sobel(both, cv2.CV_32F, 1, 0, ksize=3, scale=1.0 / 16.0), np.float32)
    gy = np.asarray(cv2.Sobel(both, cv2.CV_32F, 0, 1, ksize=3, scale=1.0 / 16.0), np.float32)
    error = warped - left
    # Zero-mean in each window, as the correlation is: a gain or offset between cameras is no shift.
    error -= np.asarray(cv2.blur(error, k), np.float32)
    gx -= np.asarray(cv2.blur(gx, k), np.float32)
    gy -= np.asarray(cv2.blur(gy, k), np.float32)
    xx, xy, yy = cv2.blur(gx * gx, k), cv2.blur(gx * gy, k), cv2.blur(gy * gy, k)
    ex, ey = cv2.blur(error * gx, k), cv2.blur(error * gy, k)
    det = xx * yy - xy * xy
    floor = config.texture_gray**2
    determined = (det > floor * np.maximum(xx, yy)) & (np.minimum(xx, yy) > floor / 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        shift_x = np.where(determined, (yy * ex - xy * ey) / det, np.nan).astype(np.float32)
        shift_y = np.where(determined, (xx * ey - xy * ex) / det, np.nan).astype(np.float32)
    return shift_x, shift_y


def _median(values: npt.NDArray[np.floating[Any]]) -> float:
    """``np.median`` of finite values (the middle one, or the float32 mean of the middle two),
    without its general machinery: on the few thousand values of a block or a gain sample that
    was most of its cost."""
    middle = values.size // 2
    if values.size % 2:
        return float(np.partition(values, middle)[middle])
    return float(np.mean(np.partition(values, (middle - 1, middle))[middle - 1 : middle + 1]))


def gain_fields(ratios: list[F32], valid: Mask, step: int, shape: tuple[int, int]) -> list[F32]:
    """The gain of each camera against its background over the image (``shape``), from its
    ``ratios`` (image over background) at every ``step``-th pixel where ``valid``. A lighting
    circuit switched off over part of a hall darkens the floor by a factor that varies over metres
    (0.26–0.51 across one view in the simulation), which no single gain takes off: where the
    blocks' medians spread wider than ``GAIN_AGREE`` about the overall median, a quadratic surface
    in the pixel (to 2.5 % on that light, :func:`_gain_surface`); else the overall median, one
    gain (exposure, a uniform change), as a 1 × 1 field that broadcasts."""
    rows, cols = shape
    v_sample, u_sample = np.nonzero(valid)
    if v_sample.size < GAIN_MIN_SAMPLES:
        return [UNIT_GAIN for _ in ratios]
    u_norm = (u_sample * (2.0 * step / max(cols - 1, 1)) - 1.0).astype(np.float64)
    v_norm = (v_sample * (2.0 * step / max(rows - 1, 1)) - 1.0).astype(np.float64)
    band_v = np.minimum(v_sample * GAIN_BLOCKS // valid.shape[0], GAIN_BLOCKS - 1)
    band_u = np.minimum(u_sample * GAIN_BLOCKS // valid.shape[1], GAIN_BLOCKS - 1)
    block = band_v * GAIN_BLOCKS + band_u
    counts = np.bincount(block, minlength=GAIN_BLOCKS * GAIN_BLOCKS)
    full = counts >= GAIN_BLOCK_MIN
    centre_u = (np.bincount(block, u_norm, counts.size) / np.maximum(counts, 1))[full]
    centre_v = (np.bincount(block, v_norm, counts.size) / np.maximum(counts, 1))[full]
    fields = []
    for ratio in ratios:
        values: F64 = ratio[v_sample, u_sample].astype(np.float64)
        overall = max(_median(values), 1e-3)  # at least: a covered lens, the lights all out
        medians = block_medians(values, block, counts)[full]
        if medians.size < QUADRATIC_TERMS or np.all(np.abs(medians / overall - 1.0) <= GAIN_AGREE):
            fields.append(np.full((1, 1), overall, np.float32))
            continue
        coef, kept = _gain_surface(centre_u, centre_v, medians, u_norm, v_norm, values)
        across, down = np.linspace(-1.0, 1.0, cols), np.linspace(-1.0, 1.0, rows)
        along_u = coef[0] + coef[1] * across + coef[3] * across * across
        along_v = coef[2] * down + coef[5] * down * down
        field = np.outer(coef[4] * down, across) + along_u[None, :] + along_v[:, None]
        lowest = float(medians[kept].min()) / GAIN_EXTRAPOLATION
        highest = float(medians[kept].max()) * GAIN_EXTRAPOLATION
        fields.append(np.clip(field, lowest, highest).astype(np.float32))
    return fields


def _gain_normalised(image: F32, gain: F32) -> F32:
    """``image`` on its background's scale: divided by its gain field (a gain held at 1e-3 at
    least: a covered lens gives no infinities)."""
    return (image / np.maximum(gain, np.float32(1e-3))).astype(np.float32, copy=False)


def block_medians(values: F64, block: npt.NDArray[np.intp], counts: npt.NDArray[np.intp]) -> F64:
    """The median of ``values`` in each block (``block`` is each value's, ``counts`` the blocks'
    sizes; NaN for an empty block), from one sort: values clipped to [0, GAIN_RATIO_MAX) and
    offset by their block's index times it sort by block, then by value."""
    if values.size == 0:
        return np.full(counts.size, np.nan)
    keyed = np.sort(block * GAIN_RATIO_MAX + np.clip(values, 0.0, GAIN_RATIO_MAX * 0.999))
    starts = np.cumsum(counts) - counts
    middle_low = np.clip(starts + (counts - 1) // 2, 0, keyed.size - 1)
    middle_high = np.clip(starts + counts // 2, 0, keyed.size - 1)
    offsets = np.arange(counts.size) * GAIN_RATIO_MAX
    medians: F64 = (keyed[middle_low] + keyed[middle_high]) / 2.0 - offsets
    return np.where(counts > 0, medians, np.nan)


def _gain_surface(
    centre_u: F64, centre_v: F64, medians: F64, u_norm: F64, v_norm: F64, values: F64
) -> tuple[F64, Mask]:
    """The quadratic a + b·u + c·v + d·u² + e·u·v + f·v² through the blocks' medians, less the
    block it misses most while it misses one by over ``GAIN_AGREE`` (``GAIN_BLOCKS_KEPT`` kept),
    then through the sampled pixels within ``GAIN_OUTLIER`` of that; and the blocks kept."""

    def basis(u: F64, v: F64) -> F64:
        return np.stack([np.ones_like(u), u, v, u * u, u * v, v * v], axis=-1).astype(np.float64)

    def fit(a: F64, y: F64) -> F64:
        # The normal equations: 25 µs a call here, lstsq's SVD 90 µs.
        normal = a.T @ a + 1e-9 * np.eye(QUADRATIC_TERMS)
        return np.linalg.solve(normal, a.T @ y).astype(np.float64)

    at = basis(centre_u, centre_v)
    blocks = np.ones(medians.size, np.bool_)
    while True:
        coef = fit(at[blocks], medians[blocks])
        missed = np.abs(medians / np.maximum(at @ coef, 1e-3) - 1.0)
        worst = int(np.argmax(np.where(blocks, missed, -1.0)))
        if missed[worst] <= GAIN_AGREE or np.count_nonzero(blocks) <= GAIN_BLOCKS_KEPT:
            break
        blocks[worst] = False
    pixels = basis(u_norm, v_norm)
    near = np.abs(values / np.maximum(pixels @ coef, 1e-3) - 1.0) <= GAIN_OUTLIER
    if np.count_nonzero(near) >= GAIN_MIN_SAMPLES:
        coef = fit(pixels[near], values[near])
    return coef, blocks


def robust_affine_fit(basis: npt.NDArray[np.float32], values: F32) -> npt.NDArray[np.float64]:
    """a + b·u' + c·v' by least squares with Cauchy weights (scale ``RESIDUAL_SCALE_PX``), the
    slopes held toward zero (ridge): the floor's residual is a fraction of a pixel, pixels on low
    objects or mismatches must not pull it, and pixels bunched in one corner of the image must
    not tilt it across the rest."""
    weights = np.ones(values.size, np.float64)
    a = basis.astype(np.float64)
    coef: npt.NDArray[np.float64] = np.zeros(basis.shape[1], np.float64)
    for _ in range(3):
        ridge = np.diag([0.0] + [RESIDUAL_RIDGE * float(weights.sum())] * (basis.shape[1] - 1))
        weighted = (a * weights[:, None]).T
        normal = weighted @ a + ridge
        coef = np.asarray(np.linalg.solve(normal, weighted @ values), np.float64)
        weights = 1.0 / (1.0 + ((values - a @ coef) / RESIDUAL_SCALE_PX) ** 2)
    clipped: npt.NDArray[np.float64] = np.clip(coef, -MAX_RESIDUAL_PX, MAX_RESIDUAL_PX)
    return clipped


OFFSET_CAPTURE_PX = 1.5
"""The coarse offset fit looks for the floor this far either side of the calibration's floor
disparity (a poor calibration is off by ±1 px at the image's edges: ``--seed 2``'s p0)."""
OFFSET_BLOCKS = (4, 3)
"""Columns × rows of image blocks the coarse fit takes one floor offset from each."""
OFFSET_BIN_PX = 0.05
OFFSET_OUTLIER_PX = 0.3
"""A block whose mode lies further than this from the floor's plane is not the floor's (a
pallet)."""
BELOW_FLOOR_COST = 4.0
"""A block's mode further than OFFSET_OUTLIER_PX below a plane costs this many times one as far
above (nothing stands below the floor; a plane through low tops leaves the floor below it)."""
MIN_FLOOR_BLOCKS = 4
"""The coarse fit needs this many blocks on its plane: the three that make it and one more."""
MIN_TRIO_SPAN = 0.1
"""Three blocks whose modes' places span less than this (twice their triangle's area in
(u', v'), the image 2 × 2; two blocks side by side and one below span 0.33) make no plane: with
one row of blocks measuring, they lie in a line but for the scatter of their pixels (0.02), and a
plane through them took its slope across the row from that scatter (1.0 px, the clip, 1.7 px off
at a corner; a review)."""


@dataclass(frozen=True)
class CoarseOffset:
    """The floor's disparity offset found without a starting guess (:func:`coarse_floor_offset`)."""

    coef: npt.NDArray[np.float64]
    """Affine a + b·u' + c·v' through the blocks' modes."""
    modes_px: npt.NDArray[np.float64]
    """Each block's mode (the floor's offset there), and where it is in (u', v')."""
    basis: npt.NDArray[np.float64]
    blocks: tuple[tuple[slice, slice], ...]
    """Each block's rows and columns in the offsets the fit was given."""


def coarse_floor_offset(
    offset_px: F32, usable: Mask, basis: npt.NDArray[np.float32]
) -> CoarseOffset | None:
    """The floor's disparity offset (measured minus the calibration's floor disparity) over the
    image, with no starting guess: in each block the mode of the offsets within
    ±``OFFSET_CAPTURE_PX``, placed where the pixels that make the mode are; then the plane
    through three blocks' modes that explains them best, one vote a block (a pallet's strongly
    textured deck must not outweigh sparse concrete): a block costs its squared distance, at most
    ``OFFSET_OUTLIER_PX``² (something standing on the floor), and ``BELOW_FLOOR_COST`` times that
    where it lies further below (nothing stands below the floor); and the affine fit through the
    blocks within ``OFFSET_OUTLIER_PX`` of it (at least ``MIN_FLOOR_BLOCKS``). Blocks whose modes
    lie coherently a pixel below the floor (not seen on the renders: a reflection on a glossy
    floor could) would tilt it: two of twelve did by 1.2 px in a review's test. A block's mode is
    the floor only where the floor is most of what the matcher measures there; on a plain floor
    the textured tops of low boxes are, in most blocks: grown from the modes' median, the fit went
    through them (``--floor plain --seed 4``: a pair's floor 1 px high, a 0.3 m box 86 % free).
    The fine fits start from it: they only see pixels near their current estimate, and from a
    wrong start they creep (0.02 px a fit) or never begin."""
    height, width = offset_px.shape
    cols, rows = OFFSET_BLOCKS
    edges = np.arange(-OFFSET_CAPTURE_PX, OFFSET_CAPTURE_PX + OFFSET_BIN_PX / 2, OFFSET_BIN_PX)
    modes, where, slices = [], [], []
    with np.errstate(invalid="ignore"):
        near = usable & (np.abs(offset_px) < OFFSET_CAPTURE_PX)
    for j in range(rows):
        for i in range(cols):
            block = (
                slice(j * height // rows, (j + 1) * height // rows),
                slice(i * width // cols, (i + 1) * width // cols),
            )
            chosen = near[block]
            values = offset_px[block][chosen]
            if values.size < MIN_FIT_PIXELS // 4:
                continue
            # np.histogram's counts (edges[k] <= value < edges[k + 1]; every value lies within them)
            # without its sort.
            histogram = np.bincount(
                np.searchsorted(edges, values, side="right") - 1, minlength=edges.size - 1
            )
            smooth = np.convolve(histogram, np.ones(3), mode="same")
            peak = int(np.argmax(smooth))
            centre = (edges[peak] + edges[peak + 1]) / 2
            around = np.abs(values - centre) <= 2 * OFFSET_BIN_PX
            modes.append(_median(values[around]))
            where.append(basis[:, block[0], block[1]][:, chosen][:, around].mean(axis=1))
            slices.append(block)
    if len(modes) < MIN_FLOOR_BLOCKS:
        return None
    a = np.asarray(where, np.float64)
    b = np.asarray(modes, np.float64)
    # Every plane through three blocks, scored at once: the cheapest is the floor's.
    trios = np.array(list(itertools.combinations(range(len(b)), 3)), np.intp)
    trio_basis = a[trios]  # (trios, 3 blocks, 3 terms)
    planar = np.abs(np.linalg.det(trio_basis)) > MIN_TRIO_SPAN
    if not planar.any():
        return None
    trios, trio_basis = trios[planar], trio_basis[planar]
    planes = np.linalg.solve(trio_basis, b[trios][..., None])[..., 0]  # (trios, 3 terms)
    residual_px = b[None, :] - planes @ a.T  # (trios, blocks)
    limit_px2 = OFFSET_OUTLIER_PX**2
    cost = np.where(
        residual_px < -OFFSET_OUTLIER_PX,
        BELOW_FLOOR_COST * limit_px2,
        np.minimum(residual_px**2, limit_px2),
    )
    keep = np.abs(residual_px[int(np.argmin(cost.sum(axis=1)))]) <= OFFSET_OUTLIER_PX
    if int(keep.sum()) < MIN_FLOOR_BLOCKS:
        return None
    coef = np.linalg.lstsq(a[keep], b[keep], rcond=None)[0]
    clipped = np.clip(coef, -MAX_RESIDUAL_PX, MAX_RESIDUAL_PX)
    blocks = tuple(slices[k] for k in np.flatnonzero(keep))
    return CoarseOffset(coef=clipped, modes_px=b[keep], basis=a[keep], blocks=blocks)


FLOOR_STILL_SEEN_SHARE = 0.5
"""A block whose mode lies off the current floor still shows that floor where at least this share
as many of its offsets lie near the floor as near its mode."""


def restarts_from_blocks(
    coarse: CoarseOffset,
    current_coef: npt.NDArray[np.float64],
    current_px: F32,
    offset_px: F32,
    usable: Mask,
    tolerance_px: float,
    started: bool,
) -> bool:
    """Whether the fine fits begin again from the coarse fit's plane: where a quarter of its
    blocks (two at least) lie further than ``tolerance_px`` from the current floor
    (``current_coef``; ``current_px`` at each of ``offset_px``'s pixels). Eager: the blocks'
    fit is robust, and starting again from it beat waiting for a third of the blocks by 0.02 of
    IoU on the poorly calibrated seeds 2, 4 and 5.

    But not, once ``started`` (the blocks have been compared with the current floor before: at
    first it is no estimate), where those blocks all lie above the current floor and are half
    the blocks or fewer, or where each of them still shows it (FLOOR_STILL_SEEN_SHARE as many of
    its ``offset_px`` near it as near its mode): what made their modes stands on that floor, the
    floor has not moved. On a plain floor a pallet's textured deck made two of the five blocks
    that measured, and the plane through the decks and the other three took that pair's floor
    0.5 px up, through the deck (``--floor plain --seed 2``: 0.97 of the deck's cells read as floor
    in a frame, 347 of its 384 free in the map, until the next restart 3.5 s on). Either test
    alone missed cases the other caught on the plain floors (the floor beside a plain top has no
    texture to show). A camera knocked askew restarts where its floor fell in a block or rose in
    most of them and left them; where it rose in half the blocks or fewer and fell in none, this
    declines, and the fine fits, which see only pixels within ``floor_tolerance_px`` of their
    floor, follow no rise beyond it: a limit, untested (telling a deck from a risen floor by where
    its pixels lie, a compact patch or spread over the block, is untried)."""
    off_px = coarse.modes_px - coarse.basis @ current_coef
    off = np.abs(off_px) > tolerance_px
    off_count = int(np.count_nonzero(off))
    if off_count < max(2, off.size // 4):
        return False
    if not started:
        return True
    if not np.any(off_px < -tolerance_px) and 2 * off_count <= off.size:
        return False
    with np.errstate(invalid="ignore"):
        for k in np.flatnonzero(off):
            rows, cols = coarse.blocks[k]
            chosen = usable[rows, cols]
            values = offset_px[rows, cols][chosen]
            near_floor = np.count_nonzero(
                np.abs(values - current_px[rows, cols][chosen]) <= tolerance_px
            )
            near_mode = np.count_nonzero(np.abs(values - coarse.modes_px[k]) <= tolerance_px)
            if near_floor < FLOOR_STILL_SEEN_SHARE * near_mode:
                return True
    return False


class LineOfSight:
    """Pixels whose ray to the floor passes through the column under a measured obstacle point.

    A vertical segment (an obstacle point and the floor below it) images as a segment toward the
    nadir: from the point's pixel inward to its foot, at a radius (1 − h/C_z) times the point's
    from the nadir. In polar coordinates about the nadir that is a run along the radius, so "is any
    column over me" is a cumulative minimum of the feet's radii from the rim inward.
    """

    def __init__(self, shape: tuple[int, int], nadir_px: tuple[float, float]) -> None:
        height, width = shape
        cx, cy = nadir_px
        corners = np.array([[0, 0], [width, 0], [0, height], [width, height]], np.float64)
        max_radius = float(np.max(np.hypot(corners[:, 0] - cx, corners[:, 1] - cy)))
        step = LINE_OF_SIGHT_BIN_PX
        radii = max(2, math.ceil(max_radius / step))
        angles = max(8, math.ceil(2 * math.pi * max_radius / step))
        # Rows run from the rim inward, so the cumulative minimum runs down the rows.
        radius = (np.arange(radii, dtype=np.float64)[::-1] * step)[:, None]
        theta = np.linspace(0, 2 * math.pi, angles, endpoint=False, dtype=np.float64)[None, :]
        self._to_polar = (
            (cx + radius * np.cos(theta)).astype(np.float32),
            (cy + radius * np.sin(theta)).astype(np.float32),
        )
        self._inner_radius = np.ascontiguousarray(
            np.broadcast_to((radius - LINE_OF_SIGHT_MARGIN_PX).astype(np.float32), (radii, angles))
        )
        v, u = np.mgrid[0:height, 0:width].astype(np.float64)
        self.pixel_radius_px = np.hypot(u - cx, v - cy).astype(np.float32)
        back_theta = np.mod(np.arctan2(v - cy, u - cx), 2 * math.pi)
        self._from_polar = (
            np.mod(np.round(back_theta * angles / (2 * math.pi)), angles).astype(np.float32),
            (radii - 1 - np.minimum(np.round(self.pixel_radius_px / step), radii - 1)).astype(
                np.float32
            ),
        )
        self._spread = np.ones((2 * math.ceil(step) + 1,) * 2, np.uint8)

    def top_runs(self, start: Mask, passable: Mask, reach_px: float, grace_px: float) -> Mask:
        """Pixels on a closed run of ``passable`` ones outward (away from the nadir) of a ``start``
        pixel: one that ends within ``reach_px`` at pixels that are not passable or at the image's
        edge (an open run is floor, or a top too large to tell from it). The first ``grace_px``
        need not be passable (the start's own window holds texture)."""
        step = LINE_OF_SIGHT_BIN_PX
        polar_start = self._polar(
            np.asarray(cv2.dilate(start.view(np.uint8), self._spread), np.uint8), 0
        )
        polar_passable = self._polar(passable.view(np.uint8), 0)
        runs = np.zeros_like(polar_start)
        _top_runs(polar_start, polar_passable, round(reach_px / step), round(grace_px / step), runs)
        return self._image(runs)

    def blocked(self, foot_radius_px: F32) -> Mask:
        """``foot_radius_px``: per pixel, the radius of its obstacle point's foot (inf: none)."""
        # A minimum over the polar bins' spacing first, so no column falls between two rays.
        polar = self._polar(np.asarray(cv2.erode(foot_radius_px, self._spread), np.float32), np.inf)
        inward = np.minimum.accumulate(polar, axis=0)
        return self._image((inward < self._inner_radius).view(np.uint8))

    def _polar(self, image: npt.NDArray[ScalarT], outside: float) -> npt.NDArray[ScalarT]:
        """``image`` on the polar bins (rows from the rim inward, a column per angle); bins past
        the image's edge take ``outside``."""
        polar: npt.NDArray[ScalarT] = np.asarray(
            cv2.remap(
                image,
                *self._to_polar,
                cv2.INTER_NEAREST,
                borderMode=cv2.BORDER_CONSTANT,
                borderValue=outside,
            ),
            image.dtype,
        )
        return polar

    def _image(self, polar: U8) -> Mask:
        """A mask on the polar bins back on the image's pixels."""
        mask: Mask = cv2.remap(polar, *self._from_polar, cv2.INTER_NEAREST) > 0
        return mask


@compiled
def _top_runs(start: U8, passable: U8, reach_bins: int, grace_bins: int, runs: U8) -> None:
    """Per polar column (an angle about the nadir; rows run from the rim inward), from the nadir
    outward: a start opens a run, which goes on over passable bins (any bin for the first
    ``grace_bins``, and a lone other one: sensor noise passes for texture now and then on a plain
    surface) and ends at two others in a row; a run still open after ``reach_bins`` is taken
    back."""
    radii, angles = start.shape
    for angle in range(angles):
        left, grace, first = 0, 0, 0
        for row in range(radii - 1, -1, -1):
            goes_on = passable[row, angle] or (row > 0 and passable[row - 1, angle])
            if start[row, angle]:
                left, grace, first = reach_bins, grace_bins, row - 1
            elif left > 0 and (goes_on or grace > 0):
                runs[row, angle] = 1
                left -= 1
                grace = max(grace - 1, 0)
                if left == 0 and row > 0 and passable[row - 1, angle]:  # it would go on
                    runs[row : first + 1, angle] = 0
            else:
                left = 0


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


BACKGROUND_TEXTURE_WINDOW_PX = 10
TEXTURE_SAMPLE_STEP = 2
TEXTURE_WINDOW_SIDES = (0, 1, 0)
"""The texture checks' weighted windows (:meth:`FloorModel._texture_checks`), by camera: the
background's texture kept in either camera (over its pixels alike their background), and gone in
the left one (over the modelled pixels)."""
_KEPT_WINDOWS, _GONE_WINDOW = (0, 1), 2
"""Which of those windows each check reads (:func:`_texture_verdicts`)."""
_MEAN_PLANES, _IMAGE_PLANES = (0, 1), (2, 3)
"""The texture checks' planes on the sampled grid: each camera's background mean and image; then,
per window, its weight and the background and image where weighted (zero elsewhere)."""


def _window_planes(window: int) -> tuple[int, int, int]:
    """The weight, weighted background and weighted image planes of a texture window."""
    first = len(_MEAN_PLANES) + len(_IMAGE_PLANES) + 3 * window
    return first, first + 1, first + 2


def _window_terms(window: int, side: int) -> tuple[tuple[int, int], ...]:
    """A texture window's terms: its weight, weighted background and image, and their products
    with the camera's background and image (:func:`_window_moments` reads them in this order)."""
    weight, background, now = _window_planes(window)
    return (
        (weight, NO_PLANE),
        (background, NO_PLANE),
        (now, NO_PLANE),
        (background, _MEAN_PLANES[side]),
        (now, _IMAGE_PLANES[side]),
        (now, _MEAN_PLANES[side]),
    )


TERMS_PER_TEXTURE_WINDOW = len(_window_terms(0, 0))
TEXTURE_PLANE_COUNT = _window_planes(len(TEXTURE_WINDOW_SIDES))[0]
TEXTURE_TERMS = np.array(
    [
        term
        for window, side in enumerate(TEXTURE_WINDOW_SIDES)
        for term in _window_terms(window, side)
    ],
    np.int64,
)
"""Every texture window's terms, window after window."""
BACKGROUND_TEXTURE_GRAY = 1.5
"""Local standard deviation (gray levels) of a background below which it has no texture to check."""
COVERED_ZNCC = 0.3
"""Correlation of image and background below which the background's texture is gone (a shadow
scales it: about 1; another surface: about 0)."""
MODELLED_WINDOW_SHARE = 0.95
"""A window less modelled than this holds something that was never floor: its texture check fails."""
TEXTURE_KEPT = 0.5
"""Share of the background's texture (regression slope) a pixel must still show to match it."""


@compiled
def _window_moments(
    means: F32, window: int, row: int, col: int
) -> tuple[np.float32, np.float32, np.float32, np.float32]:
    """A texture window's weighted share, background and image variances and their covariance at
    one pixel of the sampled grid, in float32 as numpy computes them; NaN where the window holds
    no weighted pixel."""
    first = TERMS_PER_TEXTURE_WINDOW * window
    share = means[first, row, col]
    if share == 0:  # every weighted sum is 0 too: numpy's 0 / 0
        nan = np.float32(np.nan)
        return share, nan, nan, nan
    mean_bg = means[first + 1, row, col] / share
    mean_now = means[first + 2, row, col] / share
    var_bg = means[first + 3, row, col] / share - mean_bg * mean_bg
    var_now = means[first + 4, row, col] / share - mean_now * mean_now
    covariance = means[first + 5, row, col] / share - mean_now * mean_bg
    return share, var_bg, var_now, covariance


@compiled
def _texture_verdicts(means: F32, kept: Mask, gone: Mask) -> None:
    """Per pixel of the sampled grid, from the windows' means (``TEXTURE_TERMS``): both cameras'
    background texture kept, and the left one's gone (:meth:`FloorModel._texture_checks`)."""
    textured_var = np.float32(BACKGROUND_TEXTURE_GRAY**2)
    kept_slope, covered_zncc = np.float32(TEXTURE_KEPT), np.float32(COVERED_ZNCC)
    modelled_share, tiny = np.float32(MODELLED_WINDOW_SHARE), np.float32(1e-6)
    rows, cols = kept.shape
    for row in range(rows):
        for col in range(cols):
            both_kept = True
            for window in _KEPT_WINDOWS:  # a plain background (or none: NaN): nothing to check
                _, var_bg, _, covariance = _window_moments(means, window, row, col)
                if var_bg >= textured_var and not covariance / var_bg >= kept_slope:
                    both_kept = False
            kept[row, col] = both_kept
            share, var_bg, var_now, covariance = _window_moments(means, _GONE_WINDOW, row, col)
            is_gone = share < modelled_share
            if var_bg >= textured_var:
                zncc = covariance / np.sqrt(max(var_bg * var_now, tiny))
                is_gone |= zncc < covered_zncc
            gone[row, col] = is_gone


ProbedT = TypeVar("ProbedT", np.bool_, np.float32)


def _probed(
    image: npt.NDArray[ProbedT], probe: npt.NDArray[np.int64], outside: ProbedT
) -> npt.NDArray[ProbedT]:
    """``image`` at each pixel's probe (:meth:`FloorModel.__init__`), ``outside`` beyond the
    image: cv2.remap's nearest neighbour without its per-call map decoding (a third of a
    millisecond each)."""
    if image.shape != probe.shape:  # the kernel reads wherever an index points
        raise ValueError(f"probe of shape {probe.shape} for an image of {image.shape}")
    picked = np.empty_like(image)
    _gather(image.ravel(), probe.ravel(), outside, picked.ravel())
    return picked


@compiled
def _gather(
    values: npt.NDArray[Any], index: npt.NDArray[np.int64], outside: Any, out: npt.NDArray[Any]
) -> None:
    """``out[i] = values[index[i]]``, ``outside`` where the index is negative."""
    for pixel in range(index.size):
        out[pixel] = values[index[pixel]] if index[pixel] >= 0 else outside


WindowT = TypeVar("WindowT", np.int32, np.float32)


def _window_max_at(values: npt.NDArray[WindowT], half_px: int, at: Mask) -> npt.NDArray[WindowT]:
    """The maximum of ``values`` over the (2·half_px + 1)² square about each pixel of ``at``,
    in order, pixels beyond the image not counted: ``cv2.dilate``'s figures at a few pixels,
    without dilating the whole image."""
    maxima = np.empty(np.count_nonzero(at), values.dtype)
    _window_max(values, half_px, at, maxima)
    return maxima


@compiled
def _window_max(values: npt.NDArray[Any], half_px: int, at: Mask, maxima: npt.NDArray[Any]) -> None:
    """:func:`_window_max_at`'s loop."""
    rows, cols = values.shape
    found = 0
    for row in range(rows):
        for col in range(cols):
            if not at[row, col]:
                continue
            top = values[row, col]
            for near_row in range(max(row - half_px, 0), min(row + half_px + 1, rows)):
                for near_col in range(max(col - half_px, 0), min(col + half_px + 1, cols)):
                    top = max(top, values[near_row, near_col])
            maxima[found] = top
            found += 1


def _blur(image: U8 | F32, sigma_px: float) -> F32:
    blurred: F32 = np.asarray(
        cv2.GaussianBlur(image.astype(np.float32), (0, 0), sigma_px), dtype=np.float32
    )
    return blurred


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
        _top_runs(no_runs, no_runs, 1, 1, no_runs)
        _column_support(
            np.zeros((1, 1), np.float32),
            np.zeros((1, 1), np.float32),
            no_runs.view(np.bool_),
            no_runs.view(np.bool_),
            1,
            1,
            ROW_TOLERANCE_M,
            no_runs.view(np.bool_).copy(),
        )
        _march_outward(no_runs.view(np.bool_), no_runs.view(np.bool_), (0.0, 0.0), 1, 1, no_runs)
        tiny, none = np.zeros((8, 8), np.float32), np.zeros((8, 8), np.bool_)
        floor_test(tiny, tiny, none, self.config)
        _texture_verdicts(np.zeros((len(TEXTURE_TERMS), 8, 8), np.float32), none, none.copy())
        _probed(tiny, np.zeros(tiny.shape, np.int64), np.float32(0.0))
        _probed(none, np.zeros(tiny.shape, np.int64), np.False_)
        _window_max_at(tiny, 1, none)
        _window_max_at(np.zeros((8, 8), np.int32), 1, none)
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
        return "ready" if self.modelled_share() >= self.config.ready_share else "learning"

    # -- one frame --------------------------------------------------------------------------

    def update(self, left_rect: U8, right_rect: U8, disparity: F32) -> F32:
        """The disparity the tile is built from: this frame under the evidence rules (NaN where
        there is no evidence). Learns from the frame as well."""
        cfg = self.config
        left = _blur(left_rect, cfg.blur_sigma_px)
        right = _blur(right_rect, cfg.blur_sigma_px)
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

        both_match, departed, covered, grey_alike = self._match(left, warped, inside)
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
            else self._fill_departed_regions(measured, ~np.isfinite(measured) & ~observed & departs)
        )
        fallen = self._keep_standing(measured, bridged | filled, floor_seen)
        observed |= self._paint(matches, test, inside & ~np.isfinite(measured) & ~fallen)  # 11
        # Floor observations sit at height 0 (measurements are corrected to the calibration's floor).
        out = np.where(observed, self.geometry.floor_disparity_px, measured).astype(np.float32)
        self._close_gaps(out)  # rule 9

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
        holds its cells on it: README, "One-sided rows on a plain floor")."""
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
            grey = _gain_normalised(left, self._gain[0])
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
        column within EDGE_REACH_PX agree with (:func:`_column_support`). Beside an edge along the
        baseline, such as a wall's foot, the floor test's window holds the edge, whose texture
        runs across the baseline only, so the window reads as grain along x and the reading was
        dropped (the floor along the walls along x stayed unknown, two cells wide), yet the
        pixel's own row has texture along x for the matcher (a pallet's boards along x give
        their rows little)."""
        held = np.zeros(self.shape, np.bool_)
        _column_support(
            test.left_x_gray,
            height_m,
            anchors,
            candidates,
            self.config.window_px // 2,
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

    def _match(self, left: F32, warped: F32, inside: Mask) -> tuple[Mask, float, Mask, Mask]:
        """Whether both cameras match their backgrounds at each pixel after gain normalisation
        (their grey and texture: :meth:`_texture_checks`); the share of modelled pixels that
        departs (for the re-learn decision); where the left background's texture is gone; and
        whether both match in grey alone."""
        modelled = self._modelled & inside
        self._gain = self._gains(left, warped, modelled)
        normalised = [
            _gain_normalised(image, gain)
            for image, gain in zip((left, warped), self._gain, strict=True)
        ]
        alike = [
            modelled & (np.abs(normalised[side] - self.mean[side]) <= self.tolerance[side])
            for side in (0, 1)
        ]
        both = alike[0] & alike[1]
        kept, gone = self._texture_checks(normalised, alike, modelled)
        count = int(np.count_nonzero(modelled))
        departed = 0.0 if count < MIN_FIT_PIXELS else 1.0 - float(np.count_nonzero(both)) / count
        return both & kept, departed, gone, both

    def _texture_checks(
        self, normalised: list[F32], alike: list[Mask], modelled: Mask
    ) -> tuple[Mask, Mask]:
        """Whether both cameras' images still show their background's texture, and where the
        left one's is gone, from windowed moments on every other pixel of each axis (a window's
        statistics hardly change from one pixel to the next).

        *Kept*: the slope of the image regressed on the background over a window of the pixels
        whose grey matches it (``alike``: an object's own pixels beside the floor do not count)
        is about 1 on the floor and about 0 on a plain surface whose grey lies within the
        background's tolerance (a plain orange forklift over grey concrete: the same luma).
        Where the background has no texture (a plain floor), there is nothing to check.

        *Gone*: the windowed correlation of image and background over the modelled pixels is
        under COVERED_ZNCC where the background has texture. A shadow scales the floor's texture
        and keeps it; something standing over the floor hides it. Where under
        MODELLED_WINDOW_SHARE of the window is modelled, something that was never floor stands
        within it (an object beside the pixel): a floor reading there is no more believed
        (offline, default scene: false-free overall 0.9 → 0.7 %, the person's cells)."""
        step = TEXTURE_SAMPLE_STEP
        grid = modelled[::step, ::step]
        planes = np.empty((TEXTURE_PLANE_COUNT, *grid.shape), np.float32)
        for side in (0, 1):
            planes[_MEAN_PLANES[side]] = self.mean[side, ::step, ::step]
            planes[_IMAGE_PLANES[side]] = normalised[side][::step, ::step]
        weights = (alike[0], alike[1], modelled)
        for window, side in enumerate(TEXTURE_WINDOW_SIDES):
            weight, background, now = _window_planes(window)
            planes[weight] = weights[window][::step, ::step]
            np.multiply(planes[_MEAN_PLANES[side]], planes[weight], out=planes[background])
            np.multiply(planes[_IMAGE_PLANES[side]], planes[weight], out=planes[now])
        means = window_means(planes, TEXTURE_TERMS, BACKGROUND_TEXTURE_WINDOW_PX // step)
        kept, gone = np.empty(grid.shape, np.bool_), np.empty(grid.shape, np.bool_)
        _texture_verdicts(means, kept, gone)
        return self._upsampled(kept), self._upsampled(gone)

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
            top = _window_max_at(band_height, len(self._gap_kernel) // 2, gap)
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
        region = _window_max_at(np.asarray(labels, np.int32), REGION_EDGE_PX // 2, edge)
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
        touching = _probed(seeds, self._outward_probe, np.False_)
        # A line at floor level (a marking) vouches for both sides: inward of it as well, where
        # the floor beyond it looks the same as here (a box's base has its face beyond).
        seed_inward = _probed(seeds, self._inward_probe, np.False_)
        across = _probed(left, self._beyond_probe, np.float32(0.0))
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
        unknown 4.99 → 3.53 % of the seen floor, IoU +0.017; README, "The floor at a wall's
        foot")."""
        reach = grown.copy()
        rising = (_probed(gradient, self._step_out_probe, np.float32(0.0)) > gradient) & ~contradict
        for _ in range(EDGE_CREEP_PX):
            step = rising & ~reach & _probed(reach, self._step_in_probe, np.False_)
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
            _gain_normalised(image, gain) for image, gain in zip((left, warped), gains, strict=True)
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
