"""Objects over time: every pair's detections of one capture merged (one object at a seam is one
object: :mod:`services.fusion.capture_merge`), associated with tracks (Hungarian on centre distance, in turns), each track a
constant-velocity Kalman filter; the cells a moving track sweeps ahead (DESIGN.md, Objects) and
those it left behind.

Pure numpy/scipy: no Zenoh, no threads. Fusion holds one :class:`ObjectTracker` behind its lock.

Rules that shape the tracks:
- a static object never turns into a moving track: once a track has stood still for
  ``static_after_s`` it is locked static (velocity held at zero); if the object is moved, its
  detections leave the static gate, the track ends and a new one begins;
- association runs in turns, each a Hungarian assignment on what the turns before left: tracks
  standing in one place take the detections where they stand (a tight gate); then the other
  tracks seen before theirs around their predictions; then moving tracks that turned between
  frames (:meth:`ObjectTracker._turned`), whose motion restarts; then the rest (new tracks, and
  an object starting off from where it stood). At a frame a second a forklift runs 2 m between
  frames and reverses within one: one assignment over all let a young box's track take the
  forklift passing it and a reversing person's track take the box beside it;
- a track is ``moving`` while its recent centres lie along a line covering ``moving_travel_m``
  (three times their scatter about it) at ``moving_speed_mps`` or more;
- a detection overlapping a track's footprint that the track did not take is a piece of it (a
  plain top matches in fragments): joined to it, never a track of its own;
- a partial detection (at an image border) updates the position loosely and never the size, unless
  no pair has ever seen all of the object, or the views that show all of it are few and much
  smaller than the partial ones (pieces: ``Track.size``); then the object says ``partial``;
- a moving track's wake (where it stood over the last ``wake_s``, less where any track stands
  now) is handed to the grid, which forgets the hits there that no frame has shown since
  (:meth:`wake`);
- the map's occupied cells check what the views cannot (:mod:`services.fusion.map_check`): a standing
  object they show larger than measured says ``partial``, and where its footprint is such a
  piece or a plain top (the frames' evidence does not agree with it), the
  rectangle its connected cells span is handed to the grid as contested (:meth:`check_against`);
  around a static object the frames agree with, its occupied cells 1–25 cm outside its
  footprint (less every track's footprint) are handed over as its fringe (of a ``partial`` one,
  those 1–10 cm out with free floor beyond them; of a ``size_unsure`` one, from half its views'
  spread out); the cells within 1 cm outside any static object's footprint, its rim, as
  contested (``Outline.rim``);
- a size is the median of the views seen whole; fewer than four of them, or views that disagree,
  make it ``size_unsure`` (:func:`_views_unsure`);
- the object list (not the tracks, nor the map's outlines) joins static partial tracks a seam's
  blind gap keeps apart into one object, the rectangle around their footprints
  (:func:`services.fusion.seams.join_across_seams`).
"""

from __future__ import annotations

import math
from collections import Counter, deque
from collections.abc import Callable, Collection
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt
from scipy.optimize import linear_sum_assignment

from common.arrays import F64, Mask
from common.footprints import (
    Rectangle,
    convex_hull,
    corners,
    footprint_polygon,
    polygon_cells,
    polygons_overlap,
)
from common.lattice import Window
from common.messages import DetectionRecord, TrackedObject
from services.fusion.capture_merge import (
    Observation,
    at_top,
    join_pieces,
    merge_capture,
    observation_polygon,
)
from services.fusion.captures import CaptureGroups
from services.fusion.map_check import (
    MapCheck,
    OccupiedCells,
    Outline,
    connected_cells,
    subtract_cells,
)
from services.fusion.seams import MapEvidence, SeamConfig, join_across_seams

NOT_ALLOWED = 1e6


@dataclass(frozen=True)
class TrackerConfig:
    merge_gap_m: float = 0.1
    """Footprints of different pairs closer than this in one capture are one object."""
    seam: SeamConfig = field(default_factory=SeamConfig)
    """Static tracks of partial views farther apart: one object across a seam's gap."""
    measurement_sigma_m: float = 0.05
    partial_sigma_m: float = 0.15
    """A partial detection's centre is off by up to half the unseen part."""
    accel_sigma_mps2: float = 1.0
    """Constant-velocity model's white acceleration: a forklift braking or turning."""
    initial_speed_sigma_mps: float = 2.5
    gate_sigmas: float = 3.5
    gate_min_m: float = 0.3
    gate_max_m: float = 2.0
    lost_after_s: float = 1.5
    """A track unseen this long has left (or was removed)."""
    confirm_detections: int = 2
    """Tracks seen fewer times are not reported (one-frame ghosts)."""
    moving_speed_mps: float = 0.3
    moving_travel_m: float = 0.5
    moving_detections: int = 4
    moving_span_s: float = 0.75
    """A track is moving once its last ``moving_detections`` centres, over ``moving_span_s`` or
    more, lie along a line covering ``moving_travel_m``: see ``_moves_steadily``."""
    sweep_max_speed_mps: float = 4.0
    """Faster than this is a wrong association, not a mover on a warehouse floor: not swept."""
    turns_in_row: int = 2
    """A track turns at most this many frames in a row (a forklift's U-turn at an aisle's end,
    seen once a second), then runs straight for a frame first: else one wrong turn onto a piece
    of something leads to the next across the floor (two frames straight lost the person's track
    at its reversals more often on a recorded ``--seed 2`` run)."""
    turn_speed_gain: float = 1.5
    """A track that turned between frames reached at most this times as far as its speed
    carries it: a turn changes a mover's direction more than its speed."""
    size_ratio: float = 1.4
    """A track turns only onto a view no larger than this times its size along an axis (a person
    is not a forklift), nor smaller along both (a forklift is not a person; a piece of it may
    be): :meth:`ObjectTracker._fits`."""
    mover_top_drop_m: float = 0.3
    """A pair's detection of a moving track whose top reads this much or more below the track's
    (measured whole) is put back at the track's top on its rays (:func:`at_top`): a plain top
    within a metre of a pair's nadir, its sides hidden, matched nowhere and filled at the height
    of the fattened floor around it (the forklift's at 0.19–0.45 m), lies larger about that
    nadir (1.4–1.55 × 0.96–1.18 m for 1.2 × 0.8). Offline, thirteen scenes, 20 s: IoU 0.8893 →
    0.8914 on the default, +0.0010 to +0.0034 on three more, the rest and false-free the same
    (docs/accuracy-journal.md, "Phantom movers")."""
    sweep_max_s: float = 1.5
    """A sweep reaches at most this far past the track's last capture."""
    sweep_missed_frames: float = 1.5
    """A moving track missed for more than this many frame intervals is not swept."""
    static_after_s: float = 3.0
    static_travel_m: float = 0.2
    """A track that stayed within this of one place for ``static_after_s`` is static for good."""
    stamp_jitter_s: float = 0.05
    """Capture stamps of a steady frame rate differ by this much: three frames a second apart
    may span 2.9999 s."""
    size_history: int = 20
    best_view_share: float = 0.5
    """A track's size is the median over its views with at least this share of the points of its
    best-measured one: fewer are pieces (a plain top matched in fragments, a pallet's deck while
    the floor model still learns; offline, seed 5 / 6 pairs: pallet_0 0.875 × 0.517 m after 20 s
    from 7 such views of 14, while every later view measured 1.20–1.29 × 0.75–0.83)."""
    piece_share: float = 0.5
    """A complete view less than this share as long or as wide as the object's partial views
    is a piece of it, where they outnumber such views (``Track.size``). Offline, ``--seed 1
    --pairs 6``: box_3 (1.19 × 0.98 m) was reported 0.49 × 0.15 from one view of 57 points, over
    20 partial views of 4 000 points that measured 1.19 × 0.97."""
    view_spread_share: float = 0.05
    view_spread_min_views: int = 4
    """A size needs this many complete views (1.5 s apart at 2 Hz) whose lengths and widths
    spread (interquartile range) over no more than this share of their median; otherwise it is
    their median but no confident measure, and the object says ``size_unsure``. Offline, nine
    scenes (20 s): every object measured within 3 % spread 0.047 or less; of those off by more
    than 5 % and not flagged ``partial``, most spread 0.052–0.34 (a plain top matched in part, its
    image edges found on its print: ``--floor speckle`` box_3's widths 0.17–0.32 m, 0.40 true),
    and two had one or two views."""
    raster_margin_m: float = 0.15
    """Connected map cells this far outside a footprint or nearer are its own edge's …"""
    raster_overflow_share: float = 0.2
    """A standing object whose occupied map cells more than ``raster_margin_m`` outside its
    footprint, connected to those inside, number this share of the cells inside or more is larger
    than its views saw: its size is a lower bound and it says ``partial``
    (:meth:`ConnectedCells.overflow`). A whole object's cells reach a cell or two past its
    sides (a cell holding an edge point is occupied, and a pixel of fattening): offline, nine
    scenes, 20 s, the share was at most 0.09 for the 45 objects measured within 5 %, and
    0.23–0.51 for the four reported whole 21–68 % too small (``--seed 3`` box_1 0.49 × 0.41 m
    of 0.86 × 0.65)."""
    raster_reach_m: float = 1.0
    """… those cells are looked for this far around the footprint."""
    fringe_margin_m: float = 0.01
    fringe_reach_m: float = 0.25
    """A static object's cells whose centres lie outside its footprint by ``fringe_margin_m`` at
    most are its rim (:attr:`Outline.rim`: never served free); its occupied cells whose
    centres lie more than ``fringe_margin_m`` and at most ``fringe_reach_m`` outside it are its
    fringe (:meth:`ConnectedCells.fringe`):
    the cells its side faces and the matcher's fattening make occupied, that its footprint,
    measured to a centimetre or two, does not hold. Offline, nine scenes (20 s), served unknown:
    IoU +0.007 to +0.025 on eight, false-free unchanged (docs/accuracy-journal.md). A
    ``partial`` object's (its size a lower bound) only where free floor lies beyond it; a
    ``size_unsure`` one's from farther out (``unsure_fringe_spread``). The matcher carries a
    top's disparity over a plain floor, and over a plain face below the top's edge, further than
    a cell: lines of false obstacles 10 cm out along a side facing a camera at a slant
    (``--floor plain``, box_0). Reaching 0.25 m rather than 0.1 (a partial object's: 0.1),
    thirteen scenes (20 s): IoU +0.0006 (default) to
    +0.0084 (``--floor plain --seed 4``), +0.0068 on ``--floor plain``, 0 on ``--floor
    speckle``; false-free and recall the same to the digit, unknown up to +0.08 points. Its
    occupied cells, not only those connected to it: the scatter of its faces' points lands a
    cell or two off its ring too; thirteen scenes, IoU +0.0002 to +0.0035 more (default +0.0033),
    false-free and recall the same to the digit."""
    partial_fringe_reach_m: float = 0.1
    """… and a ``partial`` object's: past a cut side the object goes on, and where it ends on free
    floor within a reach as wide as a whole one's, the rest of it is served unknown (with 0.25
    m, ``--floor plain --seed 2`` recall 0.9613 → 0.9592)."""
    unsure_fringe_spread: float = 0.5
    """A ``size_unsure`` object's fringe starts this share of its views' spread outside its
    footprint (:meth:`Track.spread_m`; ``fringe_margin_m`` at least): its size is their median, off
    by about that much. With none, an object kept its ring of false obstacles while its views
    disagreed (``--floor plain``: crate_0's 40–50 cells 1–17 cm out, its first 11 s). Offline,
    thirteen scenes (20 s), IoU +0.0019 to +0.0223 on eleven (``--floor plain`` +0.0063),
    −0.0007 on ``--floor speckle``, −0.0033 on ``--seed 4`` (a crate measured 19 cm narrow:
    its cells 5–10 cm out served unknown); false-free the same to the digit. With the whole
    spread, IoU −0.0005 to +0.0134; with a fixed 5 cm, ``--seed 4`` −0.0047
    (docs/accuracy-journal.md, "An unsure size's fringe")."""
    default_frame_interval_s: float = 0.5
    wake_s: float = 3.0
    """Where a moving track was seen in the last this-many seconds, and is not now, is its
    wake …"""
    wake_margin_m: float = 0.2
    """… each footprint grown by this (the hits of its side faces and fattening around it, and
    of a plain face's pixels that take its top's disparity: the forklift's, 1.1 m high, up to
    0.19 m out toward the camera) …; and its cells within this of its footprint as a capture
    measured it whole (not ``partial``) are its fringe then, as a static object's
    (``fringe_margin_m``; served unknown). 0.1 m before the fringe: offline, nine scenes and
    four plain ones (20 s), the fringe, the faces' edges (``services.depth.object_edges``) and
    this margin together IoU +0.001 to +0.006 on twelve, −0.001 on ``--floor plain --seed 1
    --pairs 6``; false-free within +0.03 points (docs/accuracy-journal.md) …"""
    wake_missed_frames: float = 0.5
    """… and occupied wake cells no frame has shown for this many frame intervals are forgotten:
    half a frame, so those the newest capture did not show (the floor a mover uncovered in its own
    shadow for the camera, or too sparse in pixels to be measured free again). With 1.5 frames a
    forklift at 2 m/s trailed a band of false obstacles a frame deep; offline, IoU +0.003 to
    +0.013 on nine scenes at the same false-free to the digit (docs/accuracy-journal.md)."""
    low_margin_m: float = 0.02
    """A low track's (a pallet's) outline is its footprint grown by this on every side: its sides
    are where its points' density halves less the matcher's fattening along the baseline
    (``DetectionConfig.low_fattening_px``), right on average and off by up to 3 cm either way, and
    its rim cells read free as often as not (offline, nine scenes, static false-free on ``--seed
    5 --pairs 6`` 0.42 → 0.63 % without the margin)."""
    max_size_m: float = 10.0
    """A footprint longer than this is a broken detection: it makes no wake, sweep nor outline
    (fusion refuses a detection longer at once: ``services.fusion.intake``)."""
    unsettled_max_size_m: float = 2.0
    """A track neither moving nor standing whose newest view is longer than this is no mover
    but several objects and a mover merged in one detection (offline, ``--seed 5 --pairs 6``:
    views 3–5 m long, their footprints 2–6 m² of floor served unknown). A moving track's view
    as long is such a merge too, and has no top (:meth:`ObjectTracker.mover_tops`)."""
    mover_top_margin_m: float = 0.1
    """A moving track's view in the newest capture, this much inside its sides, is its top
    (:meth:`ObjectTracker.mover_tops`): its views run a few centimetres to 0.15 m long at each
    end (the forklift's 1.3–1.5 m for 1.2). Offline, thirteen scenes (20 s), its cells no frame
    measured served occupied: IoU +0.0013 to +0.011, false-free the same; 5 cm in, −0.0006 to
    +0.0017 more; 15 cm, −0.0019 to +0.0002 (docs/accuracy-journal.md, "A mover's top no frame
    measured")."""


View = tuple[float, float, float, float, int, float, bool]
"""One view of an object: length, width, yaw, top, points, capture time (s), round."""
TrackSize = tuple[float, float, float, float, bool, bool, bool]
"""A track's length, width, yaw, top, whether that is a partial view's lower bound, whether it is
the median of complete views too few or that disagree (:func:`_views_unsure`), and whether most
of those views saw a round top."""


def _view(obs: Observation, stamp_ns: int) -> View:
    return (*obs.size_m, obs.yaw_rad, obs.top_m, obs.points, stamp_ns / 1e9, obs.round)


@dataclass
class Track:
    id: int
    state: F64
    """x, y, vx, vy (world, metres and m/s) at ``stamp_ns``."""
    covariance: F64
    stamp_ns: int
    first_seen_ns: int
    sizes: deque[View]
    """Complete views."""
    partial_sizes: deque[View]
    """Partial views, used while no complete one exists but pieces (``size``)."""
    pairs: tuple[str, ...]
    anchor_m: tuple[float, float]
    """Where the track has stood since ``still_since_ns`` (within ``static_travel_m``)."""
    still_since_ns: int
    centres: deque[tuple[float, float, float]] = field(default_factory=lambda: deque(maxlen=6))
    """Recent observed centres: capture time (s) and x, y; a turn restarts them."""
    still_detections: int = 1
    """Detections since ``still_since_ns``."""
    cruise_mps: float = 0.0
    """Its speed before it last turned (a chord across a corner is shorter than the path)."""
    turns: int = 0
    """Frames in a row at which it turned."""
    detections: int = 1
    static: bool = False
    moving: bool = False
    low_views: int = 0
    """Views (partial ones too) that saw it all top (a pallet): a track is low where they are
    most of its detections; its sides stand within ``low_margin_m`` either way."""
    _size: tuple[TrackerConfig, TrackSize, float] | None = field(default=None, repr=False)
    """The size of the views as they are and their spread (:meth:`_measured`): asked for several
    times a capture."""

    def add_view(self, view: View, partial: bool, low: bool) -> None:
        """A view of the object, complete or ``partial``, ``low`` or not; the size is worked out
        anew."""
        (self.partial_sizes if partial else self.sizes).append(view)
        self.low_views += low
        self._size = None

    @property
    def low(self) -> bool:
        """Most of its views saw it all top."""
        return 2 * self.low_views > self.detections

    @property
    def center_m(self) -> tuple[float, float]:
        return float(self.state[0]), float(self.state[1])

    def unseen_s(self, stamp_ns: int) -> float:
        """Seconds from its last observed centre to ``stamp_ns``."""
        return stamp_ns / 1e9 - self.centres[-1][0]

    @property
    def standing(self) -> bool:
        """Static, or seen twice or more in one place and not moving."""
        return self.static or (not self.moving and self.still_detections >= 2)

    def size(self, config: TrackerConfig) -> TrackSize:
        """:data:`TrackSize` (:meth:`_measured`)."""
        return self._measured(config)[0]

    def spread_m(self, config: TrackerConfig) -> float:
        """The interquartile range of the lengths or widths (the wider) of the views :meth:`size`
        takes its size from, in metres: how far a ``size_unsure`` footprint may be off."""
        return self._measured(config)[1]

    def _measured(self, config: TrackerConfig) -> tuple[TrackSize, float]:
        """The size and the spread of the views it is taken from: the size over the complete views
        with ``best_view_share`` of the best one's points or more (partial views joined from pieces
        add up their points, not their measure), else over the partial ones (a lower bound).
        Complete views shorter or narrower than ``piece_share`` of what the partial views saw (their
        median) are pieces of the object, not all of it (a fragment of a plain top, the corner of a
        box a taller neighbour hides) where the partial views of the same time (since the oldest
        complete view kept) outnumber them; where they do not, the partial views are what is wrong
        (another object's, taken once). A static track's complete views older than every partial
        view of a full history, too few or too spread to agree on a size, are stale: a pair that
        sees a standing object whole sees it so every frame (the cameras stand still), so such views
        were the first frames' or a merge's."""
        if self._size is not None and self._size[0] is config:
            return self._size[1], self._size[2]
        views = np.asarray(self.sizes, np.float64).reshape(-1, 7)
        partial = np.asarray(self.partial_sizes, np.float64).reshape(-1, 7)
        if self.static and len(self.partial_sizes) == self.partial_sizes.maxlen:
            stale = views[:, 5] < partial[:, 5].min()
            if _views_unsure(views[stale, :2], config):
                views = views[~stale]
        recent = partial[partial[:, 5] >= views[:, 5].min(initial=math.inf)]
        if len(recent):
            seen = np.median(recent[:, :2], axis=0)
            whole = (views[:, :2] >= config.piece_share * seen).all(axis=1)
            if np.count_nonzero(~whole) < len(recent):
                views = views[whole]
        complete = bool(len(views))
        array = views if complete else partial
        if complete:
            array = array[array[:, 4] >= config.best_view_share * array[:, 4].max()]
        doubled = 2 * array[:, 2]  # yaw is modulo π: average on the doubled circle
        yaw = math.atan2(float(np.sin(doubled).mean()), float(np.cos(doubled).mean())) / 2
        length, width = float(np.median(array[:, 0])), float(np.median(array[:, 1]))
        round_views = array[array[:, 6] > 0]
        round_ = 2 * len(round_views) > len(array)
        if round_:  # a circle: the round views' diameter (a yaw means nothing)
            length = width = float(np.median(round_views[:, 0]))
            yaw = 0.0
        size = (
            length,
            width,
            yaw % math.pi,
            float(np.median(array[:, 3])),
            not complete,
            complete and _views_unsure(array[:, :2], config),
            round_,
        )
        spread_m = _spread_m(array[:, :2])
        self._size = (config, size, spread_m)
        return size, spread_m


def _spread_m(sizes_m: F64) -> float:
    """The interquartile range of views' lengths and widths (the wider; 0 for one view)."""
    if not len(sizes_m):
        return 0.0
    low, high = np.quantile(sizes_m, (0.25, 0.75), axis=0)
    return float((high - low).max())


def _views_unsure(sizes_m: F64, config: TrackerConfig) -> bool:
    """Whether an object's views (length, width each) are too few to agree on a size (under
    ``view_spread_min_views``), or spread over more than ``view_spread_share`` of their median
    (interquartile range, either side)."""
    if len(sizes_m) < config.view_spread_min_views:
        return True
    low, median, high = np.quantile(sizes_m, (0.25, 0.5, 0.75), axis=0)
    return bool(((high - low) > config.view_spread_share * median).any())


def _transition(dt_s: float) -> F64:
    f = np.eye(4)
    f[0, 2] = f[1, 3] = dt_s
    return f


def _process_noise(dt_s: float, accel_sigma: float) -> F64:
    """White-acceleration noise of the constant-velocity model, per axis."""
    q = accel_sigma**2 * np.array([[dt_s**4 / 4, dt_s**3 / 2], [dt_s**3 / 2, dt_s**2]])
    out = np.zeros((4, 4))
    out[np.ix_([0, 2], [0, 2])] = q
    out[np.ix_([1, 3], [1, 3])] = q
    return out


H = np.array([[1.0, 0, 0, 0], [0, 1.0, 0, 0]])


@dataclass(frozen=True)
class MoverView:
    """One observation of a moving track: its capture, its footprint as measured, and whether
    the view was cut (``partial``: the footprint is a lower bound)."""

    stamp_ns: int
    rectangle: Rectangle
    partial: bool

    def polygon(self, grown_m: float = 0.0) -> F64:
        """The footprint's corners, grown by ``grown_m`` on every side."""
        x, y, length, width, yaw = self.rectangle
        return corners((x, y), (length + 2 * grown_m, width + 2 * grown_m), yaw)


@dataclass
class ObjectTracker:
    config: TrackerConfig = field(default_factory=TrackerConfig)
    tracks: list[Track] = field(default_factory=list)
    next_id: int = 1
    version: int = 0
    stamp_ns: int = 0
    frame_interval_s: float = 0.0
    paused: bool = False
    """The tracks were forgotten (:meth:`forget`) since the last capture."""
    captures: CaptureGroups[DetectionRecord] = field(default_factory=CaptureGroups)
    """Detections waiting for the rest of their capture."""
    wake_footprints: deque[MoverView] = field(default_factory=deque)
    """Every observation of a moving track over the last ``wake_s``."""
    late: Counter[str] = field(default_factory=Counter)
    """Per live pair, detections dropped as late: their capture came after a later one was
    tracked (a filter steps forward in time only)."""
    cameras_m: dict[str, tuple[float, float, float]] = field(default_factory=dict)
    """Per live pair, where its camera stands (``DetectionsHeader.camera_m``), as it last said."""

    def add(
        self,
        pair: str,
        stamp_ns: int,
        detections: list[DetectionRecord],
        now_s: float,
        camera_m: tuple[float, float, float] | None = None,
    ) -> None:
        """One pair's detections of one frame (an empty list says it saw nothing: still counts),
        and where its camera stands if it says."""
        if camera_m is not None:
            self.cameras_m[pair] = camera_m
        self.captures.add(pair, stamp_ns, detections, now_s)

    def flush(self, now_s: float, live_pairs: set[str]) -> bool:
        """Process every complete (or waited-for) capture in stamp order; True if tracks changed."""
        for gone in set(self.cameras_m) - live_pairs:  # a pair that left, or a forged one
            del self.cameras_m[gone]
        changed = False
        for group, detections in self.captures.ready(now_s, live_pairs):
            if group <= self.stamp_ns:  # older than a capture already processed
                self.late.update(pair for pair, _ in detections if pair in live_pairs)
                continue
            movers = self._movers_at(group)
            lifted = [(pair, self._at_mover_top(pair, d, movers)) for pair, d in detections]
            self.update(group, merge_capture(lifted, self.config.merge_gap_m))
            changed = True
        return changed

    def _movers_at(self, stamp_ns: int) -> list[tuple[TrackSize, tuple[float, float]]]:
        """The followed moving tracks sized from complete views: each size and where it is
        predicted at ``stamp_ns`` (once a capture, for :meth:`_at_mover_top`)."""
        out = []
        for track in self.tracks:
            if not track.moving or not self._followed(track):
                continue
            size = track.size(self.config)
            if not size[4]:
                state, _ = self._predict(track, stamp_ns)
                out.append((size, (float(state[0]), float(state[1]))))
        return out

    def _at_mover_top(
        self,
        pair: str,
        record: DetectionRecord,
        movers: list[tuple[TrackSize, tuple[float, float]]],
    ) -> DetectionRecord:
        """``record`` put back at the top of the moving track it is a view of (``movers``:
        :meth:`_movers_at`), where it reads ``mover_top_drop_m`` or more below it
        (:attr:`TrackerConfig.mover_top_drop_m`): the record complete (a partial one's top may be
        where the image's edge cut the object: the person's lower half at a seam, lifted, went
        0.4 m off), of the track's size (:meth:`_fits`; not a neighbour's, nor a piece) and
        within ``gate_min_m`` of where the track is predicted."""
        camera_m = self.cameras_m.get(pair)
        if camera_m is None or record.partial:  # a view's edge may cut a tall object's top off
            return record
        for size, centre in movers:
            top_m = size[3]
            if (
                record.top_m <= top_m - self.config.mover_top_drop_m
                and math.dist(record.center_m, centre) <= self.config.gate_min_m
                and self._fits(size, record)
            ):
                return at_top(record, camera_m, top_m)
        return record

    def forget(self) -> None:
        """Every track ends: no capture has come for longer than the map keeps evidence. The gap
        until the next capture is no frame interval (a minute's pause taken as one had movers'
        paths swept a dozen seconds ahead)."""
        self.tracks = []
        self.wake_footprints.clear()
        self.version += 1
        self.paused = True

    def restart(self) -> None:
        """Every track ends, and so does the order of captures by stamp: the clock they were
        stamped by stepped back (``FusionState.check_clock``)."""
        self.forget()
        self.stamp_ns = 0
        self.captures = self.captures.emptied()

    def _predict(self, track: Track, stamp_ns: int) -> tuple[F64, F64]:
        dt = (stamp_ns - track.stamp_ns) / 1e9
        f = _transition(dt)
        accel = 0.0 if track.static else self.config.accel_sigma_mps2
        return f @ track.state, f @ track.covariance @ f.T + _process_noise(dt, accel)

    def _gate_m(self, covariance: F64) -> float:
        """Where a track's detection may fall around its prediction."""
        spread = self.config.gate_sigmas * math.sqrt(float(covariance[0, 0] + covariance[1, 1]))
        return min(self.config.gate_min_m + spread, self.config.gate_max_m)

    def update(self, stamp_ns: int, observations: list[Observation]) -> None:
        """One capture's observations: predict, associate (in turns, see the module's rules),
        update, start and end tracks."""
        if self.stamp_ns and not self.paused:
            gap_s = (stamp_ns - self.stamp_ns) / 1e9
            self.frame_interval_s = (
                gap_s if not self.frame_interval_s else 0.8 * self.frame_interval_s + 0.2 * gap_s
            )
        self.paused = False
        predicted = [self._predict(t, stamp_ns) for t in self.tracks]
        sizes = [t.size(self.config) for t in self.tracks]  # a median: once
        gates = [self._gate_m(covariance) for _, covariance in predicted]
        matches: dict[int, list[int]] = {}

        def predicted_at(row: int) -> tuple[float, float]:
            return float(predicted[row][0][0]), float(predicted[row][0][1])

        centres_m = np.array([obs.center_m for obs in observations], np.float64).reshape(-1, 2)

        def assign(rows: list[int], cost_of: Callable[[list[int], list[int]], F64]) -> None:
            taken = {m[0] for m in matches.values()}
            cols = [c for c in range(len(observations)) if c not in taken]
            rows = [r for r in rows if r not in matches]
            if not rows or not cols:
                return
            cost = cost_of(rows, cols)
            for i, j in zip(*linear_sum_assignment(cost), strict=True):
                if cost[i, j] < NOT_ALLOWED:
                    matches[rows[int(i)]] = [cols[int(j)]]

        def near(
            centre_of: Callable[[int], tuple[float, float]], gate_of: Callable[[int], float]
        ) -> Callable[[list[int], list[int]], F64]:
            """Each observation's distance from each track's centre, within its gate: one
            array, not a call per pair (a forged pair's hundreds of detections against as many
            tracks stalled the loop)."""

            def cost_of(rows: list[int], cols: list[int]) -> F64:
                centres = np.array([centre_of(r) for r in rows], np.float64)
                gates = np.array([gate_of(r) for r in rows], np.float64)
                offsets = centres_m[cols][None, :, :] - centres[:, None, :]
                distance = np.hypot(offsets[..., 0], offsets[..., 1])
                cost: F64 = np.where(distance <= gates[:, None], distance, NOT_ALLOWED)
                return cost

            return cost_of

        def each(
            distance: Callable[[int, Observation], float | None],
        ) -> Callable[[list[int], list[int]], F64]:
            def cost_of(rows: list[int], cols: list[int]) -> F64:
                cost = np.full((len(rows), len(cols)), NOT_ALLOWED)
                for i, row in enumerate(rows):
                    for j, col in enumerate(cols):
                        d = distance(row, observations[col])
                        if d is not None:
                            cost[i, j] = d
                return cost

            return cost_of

        rows = range(len(self.tracks))
        standing = [r for r in rows if self.tracks[r].standing]
        # Where a standing object stands (not where a leftover velocity carries it), within what
        # a partial view or pieces of it shift its centre: half its length.
        assign(
            standing,
            near(
                lambda r: self.tracks[r].center_m,
                lambda r: max(self.config.gate_min_m, 0.5 * sizes[r][0]),
            ),
        )
        established = [r for r in rows if r not in standing and self.tracks[r].detections > 1]
        assign(established, near(predicted_at, gates.__getitem__))
        moving = [r for r in rows if self._steady(self.tracks[r], stamp_ns)]
        assign(moving, each(lambda r, obs: self._turned(self.tracks[r], sizes[r], obs, stamp_ns)))
        # A moving track that met an object its size far off its prediction turned: its motion
        # restarts (a piece's centre is no measure of that).
        turned = {
            r
            for r in moving
            if r in matches
            and self._fits(sizes[r], observations[matches[r][0]])
            and math.dist(observations[matches[r][0]].center_m, predicted_at(r))
            > max(self.config.gate_min_m, 0.5 * self._predicted_travel_m(self.tracks[r], stamp_ns))
        }
        new = [r for r in rows if self.tracks[r].detections == 1 or r in standing]
        assign([r for r in new if not self.tracks[r].static], near(predicted_at, gates.__getitem__))

        # Pieces join the track whose footprint they overlap: a turned track's is where it met
        # its object, not where its old motion would have carried it.
        footprint_centres = [
            observations[matches[r][0]].center_m if r in turned else predicted_at(r) for r in rows
        ]
        footprints = [corners(footprint_centres[r], sizes[r][:2], sizes[r][2]) for r in rows]
        # Only footprints whose circles come within twice the gap can come within the gap
        # (separating axes along the sides overstate a gap by √2 at most).
        centres_now = np.array(footprint_centres, np.float64).reshape(-1, 2)
        footprint_radii = np.array([0.5 * math.hypot(*size[:2]) for size in sizes])
        matched = {col for cols_of in matches.values() for col in cols_of}
        for col, obs in enumerate(observations):
            if col in matched:
                continue
            # A piece of a tracked object (a plain top matches in fragments) joins it; it never
            # starts a track of its own.
            offsets = centres_now - centres_m[col]
            reach = footprint_radii + 0.5 * math.hypot(*obs.size_m) + 2 * self.config.merge_gap_m
            on = [
                int(row)
                for row in np.flatnonzero(np.hypot(offsets[:, 0], offsets[:, 1]) <= reach)
                if polygons_overlap(
                    footprints[row], observation_polygon(obs), self.config.merge_gap_m
                )
            ]
            taken = [row for row in on if row in matches]
            if not on:
                self._start(stamp_ns, obs)
            elif taken:
                matches[taken[0]].append(col)
        for row, cols_of in matches.items():
            track = self.tracks[row]
            obs = join_pieces([observations[col] for col in cols_of])
            state, covariance = predicted[row]
            if row in turned:
                self._restart_motion(track, stamp_ns, observations[cols_of[0]])
                state, covariance = self._predict(track, stamp_ns)
            self._correct(track, state, covariance, stamp_ns, obs)
        lost_ns = self.config.lost_after_s * 1e9
        self.tracks = [t for t in self.tracks if stamp_ns - t.stamp_ns <= lost_ns]
        self.stamp_ns = stamp_ns
        self.version += 1

    def _turned(
        self, track: Track, size: TrackSize, obs: Observation, stamp_ns: int
    ) -> float | None:
        """A moving track its prediction lost (it turned or reversed between frames): the distance
        from where it was last seen to an observation it can have reached at its speed (times
        ``turn_speed_gain``) and that fits its size; else None."""
        _, x, y = track.centres[-1]
        distance = math.hypot(obs.center_m[0] - x, obs.center_m[1] - y)
        speed = max(math.hypot(*track.state[2:4]), track.cruise_mps)
        reach_m = self.config.turn_speed_gain * speed * track.unseen_s(stamp_ns)
        if distance > self.config.gate_min_m + reach_m or not self._fits(size, obs):
            return None
        return distance

    def _steady(self, track: Track, stamp_ns: int) -> bool:
        """Moving, missed by at most ``sweep_missed_frames`` + 1 frame intervals and not turned
        ``turns_in_row`` frames in a row: only such a track can have turned."""
        return (
            track.moving
            and track.turns < self.config.turns_in_row
            and track.unseen_s(stamp_ns) <= (self.config.sweep_missed_frames + 1) * self.ahead_s()
        )

    def _predicted_travel_m(self, track: Track, stamp_ns: int) -> float:
        """How far the track's velocity carries it from its last centre to ``stamp_ns``."""
        return math.hypot(*track.state[2:4]) * track.unseen_s(stamp_ns)

    def _fits(self, size: TrackSize, obs: Observation | DetectionRecord) -> bool:
        """Whether ``obs`` is the object of a track of ``size`` (``size_ratio``): neither larger
        along an axis nor smaller along both."""
        length, width, *_ = size
        pairs = list(zip(sorted((length, width)), sorted(obs.size_m), strict=True))
        ratio = self.config.size_ratio
        larger = any(seen > own * ratio for own, seen in pairs)
        smaller = all(seen < own / ratio for own, seen in pairs)
        return not larger and not smaller

    def _restart_motion(self, track: Track, stamp_ns: int, obs: Observation) -> None:
        """A turned track's motion begins again from its last centre, with the velocity that
        reaches ``obs`` at ``stamp_ns``, as uncertain as a new track's; its line of centres
        starts anew."""
        seen_s, x, y = track.centres[-1]
        track.cruise_mps = max(track.cruise_mps, math.hypot(*track.state[2:4]))
        velocity = (np.asarray(obs.center_m) - (x, y)) / max(track.unseen_s(stamp_ns), 1e-3)
        track.state = np.array([x, y, velocity[0], velocity[1]])
        track.stamp_ns = round(seen_s * 1e9)
        track.covariance = self._initial_covariance(obs)
        track.centres = deque([track.centres[-1]], maxlen=track.centres.maxlen)
        track.turns += 1

    def _footprint(self, track: Track) -> tuple[tuple[float, float], float]:
        length, width, yaw, *_ = track.size(self.config)
        return (length, width), yaw

    def _sigma_m(self, obs: Observation) -> float:
        """The error of an observation's centre."""
        return self.config.partial_sigma_m if obs.partial else self.config.measurement_sigma_m

    def _initial_covariance(self, obs: Observation) -> F64:
        """A motion's beginning: at ``obs`` to its centre's error, at any walking or driving speed."""
        sigma, speed_var = self._sigma_m(obs), self.config.initial_speed_sigma_mps**2
        return np.diag([sigma**2, sigma**2, speed_var, speed_var])

    def _start(self, stamp_ns: int, obs: Observation) -> None:
        track = Track(
            id=self.next_id,
            state=np.array([obs.center_m[0], obs.center_m[1], 0.0, 0.0]),
            covariance=self._initial_covariance(obs),
            stamp_ns=stamp_ns,
            first_seen_ns=stamp_ns,
            sizes=deque(maxlen=self.config.size_history),
            partial_sizes=deque(maxlen=self.config.size_history),
            pairs=obs.pairs,
            anchor_m=obs.center_m,
            still_since_ns=stamp_ns,
        )
        track.add_view(_view(obs, stamp_ns), obs.partial, obs.low)
        track.centres.append((stamp_ns / 1e9, *obs.center_m))
        self.tracks.append(track)
        self.next_id += 1

    def _correct(
        self, track: Track, state: F64, covariance: F64, stamp_ns: int, obs: Observation
    ) -> None:
        innovation = np.asarray(obs.center_m) - H @ state
        s = H @ covariance @ H.T + np.eye(2) * self._sigma_m(obs) ** 2
        gain = covariance @ H.T @ np.linalg.inv(s)
        track.state = state + gain @ innovation
        track.covariance = (np.eye(4) - gain @ H) @ covariance
        if track.static:
            track.state[2:] = 0.0
            track.covariance[2:, :] = track.covariance[:, 2:] = 0.0
        track.stamp_ns = stamp_ns
        track.centres.append((stamp_ns / 1e9, *obs.center_m))
        track.pairs = obs.pairs
        track.detections += 1
        track.add_view(_view(obs, stamp_ns), obs.partial, obs.low)
        self._classify(track)
        if track.moving and max(obs.size_m) <= self.config.max_size_m:
            rectangle = (*obs.center_m, *obs.size_m, obs.yaw_rad)
            self.wake_footprints.append(MoverView(stamp_ns, rectangle, obs.partial))

    def _moves_steadily(self, track: Track) -> bool:
        """A straight line fitted to the track's recent centres: it moves if the line covers
        ``moving_travel_m`` at ``moving_speed_mps`` or more, three times what the centres scatter
        about it. The filter's speed alone is not enough: a static object seen in pieces, or
        partly then whole, jumps its centre back and forth."""
        history = track.centres
        if len(history) < self.config.moving_detections:
            return False
        t = np.array([h[0] for h in history])
        span_s = float(t[-1] - t[0])
        if span_s < self.config.moving_span_s:
            return False
        xy = np.array([h[1:] for h in history])
        design = np.column_stack([np.ones_like(t), t - t.mean()])
        fit, *_ = np.linalg.lstsq(design, xy, rcond=None)
        speed = float(np.hypot(*fit[1]))
        scatter = float(np.sqrt(np.mean(np.sum((xy - design @ fit) ** 2, axis=1))))
        travel = speed * span_s
        return (
            speed >= self.config.moving_speed_mps
            and travel >= self.config.moving_travel_m
            and travel >= 3.0 * scatter
        )

    def _classify(self, track: Track) -> None:
        if track.static:
            return
        if math.dist(track.center_m, track.anchor_m) > self.config.static_travel_m:
            track.anchor_m, track.still_since_ns, track.still_detections = (
                track.center_m,
                track.stamp_ns,
                1,
            )
        else:
            track.still_detections += 1
        # Judged anew at every frame once there is a line of centres to judge: a wrong "moving"
        # (pieces of a static object lining up once) does not stick; a track that turned keeps
        # its class until its new line is long enough.
        if len(track.centres) >= 3:  # it ran straight for a frame since it last turned
            track.turns = 0
        if len(track.centres) >= self.config.moving_detections:
            track.moving = self._moves_steadily(track)
            track.cruise_mps = 0.0  # a line again: its filtered speed is measured
        still_s = (track.stamp_ns - track.still_since_ns) / 1e9
        if not track.moving and still_s >= self.config.static_after_s - self.config.stamp_jitter_s:
            track.static = True
            track.state[2:] = 0.0
            track.covariance[2:, :] = track.covariance[:, 2:] = 0.0

    def objects(
        self, pieces: Collection[int] = frozenset(), cells: MapEvidence | None = None
    ) -> list[TrackedObject]:
        """Confirmed tracks as ``map/objects`` reports them; those in ``pieces`` (the map's cells
        show them larger than measured: :attr:`MapCheck.pieces`) say ``partial``; given the map's
        ``cells``, static partial ones a seam's gap keeps apart are one object
        (:func:`services.fusion.seams.join_across_seams`)."""
        out = []
        for t in self.tracks:
            if t.detections < self.config.confirm_detections or (
                t.moving and not self._followed(t)
            ):
                continue
            length, width, yaw, top, partial, unsure, round_ = t.size(self.config)
            moving = t.moving
            partial = partial or t.id in pieces
            velocity = (float(t.state[2]), float(t.state[3])) if moving else (0.0, 0.0)
            cov = t.covariance[2:, 2:] if moving else np.zeros((2, 2))
            out.append(
                TrackedObject(
                    id=t.id,
                    object_class="moving" if moving else "static",
                    center_m=t.center_m,
                    size_m=(length, width),
                    yaw_rad=yaw,
                    top_m=top,
                    velocity_mps=velocity,
                    velocity_cov_m2ps2=(
                        (float(cov[0, 0]), float(cov[0, 1])),
                        (float(cov[1, 0]), float(cov[1, 1])),
                    ),
                    first_seen_ns=t.first_seen_ns,
                    last_seen_ns=t.stamp_ns,
                    pairs=list(t.pairs),
                    partial=partial,
                    size_unsure=unsure,
                    round=round_,
                    detections=t.detections,
                    settled=t.static,
                )
            )
        return out if cells is None else join_across_seams(out, cells, self.config.seam)

    def sweep(
        self, resolution_m: float, from_ns: int, until_ns: int
    ) -> list[tuple[Window, npt.NDArray[np.bool_]]]:
        """Per moving track, the cells its footprint sweeps from max(its last capture, ``from_ns``)
        until ``until_ns`` along its velocity: where it is while the map that shows it is read."""
        out = []
        for t in self.tracks:
            if not t.moving or not self._followed(t):
                continue
            velocity = t.state[2:4]
            (length, width), yaw = self._footprint(t)
            if max(length, width) > self.config.max_size_m:
                continue  # a broken detection's: no sweep, as no wake
            start_s = (max(t.stamp_ns, from_ns) - t.stamp_ns) / 1e9
            end_s = min(max((until_ns - t.stamp_ns) / 1e9, start_s), self.config.sweep_max_s)
            start_s = min(start_s, end_s)
            a = corners(tuple(t.state[:2] + velocity * start_s), (length, width), yaw)
            b = corners(tuple(t.state[:2] + velocity * end_s), (length, width), yaw)
            out.append(polygon_cells(convex_hull(np.vstack([a, b])), resolution_m))
        return out

    def _followed(self, track: Track) -> bool:
        """Whether a moving track follows its mover: seen by the last ``sweep_missed_frames``
        frame intervals (else where it went is a guess, not a prediction: a person that reversed
        goes on as another track while this one waits out ``lost_after_s``), at no more than
        ``sweep_max_speed_mps``. Only such a track is swept and reported."""
        return (
            math.hypot(*track.state[2:4]) <= self.config.sweep_max_speed_mps
            and self.stamp_ns - track.stamp_ns
            <= self.config.sweep_missed_frames * self.ahead_s() * 1e9
        )

    def movers_now(self, resolution_m: float) -> list[tuple[Window, npt.NDArray[np.bool_]]]:
        """The cells of each moving track's footprint at the newest capture (a track missed by
        it, where it is predicted then; none for a track missed longer: :meth:`sweep`), and of
        each *unsettled* track's newest view, where the track is: one the newest capture saw,
        seen twice or more, neither moving nor standing in one place (a mover whose track was
        lost at a turn or has just started, or whose moving flag dropped at a curve). Fusion
        serves those the frames do not call occupied unknown (the contested layer), but a
        mover's top no frame measured occupied (:meth:`mover_tops`): something stands there now,
        and a free reading there is the floor before it came, or a plain side of the floor's grey
        that the floor model took for floor (offline, ``--floor plain``: the person's cells 23 %
        free)."""
        unsettled = []
        for t in self.tracks:
            if t.moving or t.standing or t.stamp_ns != self.stamp_ns:
                continue
            if t.detections < self.config.confirm_detections:
                continue
            # Its newest view (by capture time), not its size: an unsettled track's views may
            # be a broken detection's.
            length, width, yaw, _, _, _, round_ = max(
                (views[-1] for views in (t.sizes, t.partial_sizes) if views),
                key=lambda view: view[5],
            )
            if max(length, width) <= self.config.unsettled_max_size_m:
                polygon = footprint_polygon(t.center_m, (length, width), yaw, bool(round_))
                unsettled.append(polygon_cells(polygon, resolution_m))
        return self.sweep(resolution_m, self.stamp_ns, self.stamp_ns) + unsettled

    def mover_tops(self, resolution_m: float) -> list[tuple[Window, Mask]]:
        """The cells whose centres lie ``mover_top_margin_m`` or more inside a moving track's view
        in the newest capture, for views no longer than ``unsettled_max_size_m``: its top. Where
        no frame measured such a cell (a plain top the matcher found nothing on, its floor
        hidden), fusion serves it occupied: offline, on the default scene, 41 cells a map the
        movers stand on and 4 of floor (of those, partial views 31 and 1: a view cut by the
        image's border, or pieces joined around, lies on the mover too)."""
        margin_m = self.config.mover_top_margin_m
        return [
            polygon_cells(view.polygon(-margin_m), resolution_m)
            for view in self._views_now()
            if max(view.rectangle[2:4]) <= self.config.unsettled_max_size_m
            and min(view.rectangle[2:4]) > 2 * margin_m
        ]

    def _views_now(self) -> list[MoverView]:
        """The moving tracks' views in the newest capture."""
        return [view for view in self.wake_footprints if view.stamp_ns == self.stamp_ns]

    def wake(self, resolution_m: float) -> tuple[list[tuple[Window, npt.NDArray[np.bool_]]], float]:
        """The cells of the movers' wakes over the last ``wake_s``, and the observation time
        before which an occupied one is forgotten (``FusedGrid.forget_occupied``): a hit a mover
        left on floor too sparse in pixels to be measured free again would stay for seconds."""
        while self.wake_footprints and (
            self.stamp_ns - self.wake_footprints[0].stamp_ns > self.config.wake_s * 1e9
        ):
            self.wake_footprints.popleft()
        cells = [
            polygon_cells(view.polygon(self.config.wake_margin_m), resolution_m)
            for view in self.wake_footprints
        ]
        # Where something stands now is no wake, even where no frame has measured it: a mover as
        # this capture saw it, and every track where it is now (a mover this capture missed, an
        # object standing beside the path whose plain top frames rarely measure).
        standing = [view.polygon() for view in self._views_now()]
        for footprint in standing + self._footprints_now():
            subtract_cells(cells, polygon_cells(footprint, resolution_m))
        return cells, self.stamp_ns / 1e9 - self.config.wake_missed_frames * self.ahead_s()

    def _footprints_now(self, with_movers: bool = True) -> list[F64]:
        """Every track's footprint (its polygon) where it is at the newest capture, as predicted: a
        mover this capture missed, an object whose plain top frames rarely measure (without the
        moving tracks' unless ``with_movers``)."""
        out = []
        for track in self.tracks:
            if track.moving and not with_movers:
                continue
            length, width, yaw, *_, round_ = track.size(self.config)
            if max(length, width) <= self.config.max_size_m:
                state, _ = self._predict(track, self.stamp_ns)
                center = (float(state[0]), float(state[1]))
                out.append(footprint_polygon(center, (length, width), yaw, round_))
        return out

    def outlines(self, resolution_m: float) -> list[Outline]:
        """Per static track, the cells whose centres its footprint holds (and its edge and rim:
        :class:`Outline`): measured to a centimetre
        or two on its points and image edges, where the frames' evidence decides a rim cell (its
        centre 0–3 cm inside) by a share of pixels that a pixel of fattening or a side face's
        noise tips either way; fusion serves them occupied where the frames agree, except the
        edge cells (:attr:`Outline.edge`) they call free, which it serves unknown, as it does the
        free cells of a footprint they do not agree with (the contested layer). A partial view's
        footprint is a lower bound, so its cells lie inside the object as far as the track's views
        agree on where the piece lies (the centre is filtered over them; the agreement test guards
        the rest).
        Objects cut by an image's border or at a seam keep their rims so (offline static
        false-free 0.32 → 0.14 % on the default scene, 0.66 → 0.09 % on ``--seed 2``)."""
        out = []
        for track in self.tracks:
            if not track.static or track.detections < self.config.confirm_detections:
                continue
            length, width, yaw, *_, round_ = track.size(self.config)
            if max(length, width) > self.config.max_size_m:
                continue
            rim_m = 0.0  # a round or low track's outline is grown by as much or more instead
            if round_:  # its rim cells lie within a centimetre of a circle measured to one
                grow_m = 2 * self.config.fringe_margin_m
                length, width = length + grow_m, width + grow_m
            elif track.low:  # its sides stand within a few centimetres either way
                grow_m = 2 * self.config.low_margin_m
                length, width = length + grow_m, width + grow_m
            else:
                rim_m = self.config.fringe_margin_m
            size = (length, width)
            out.append(Outline.of(track.center_m, size, yaw, round_, resolution_m, rim_m))
        return out

    def check_against(self, cells: OccupiedCells) -> MapCheck:
        """What the map's cells say of the confirmed standing tracks, worked out once a capture
        (:class:`MapCheck`): a track whose connected cells more than ``raster_margin_m`` outside
        its footprint number ``raster_overflow_share`` of those inside or more is a piece of what
        they show; a static track that is such a piece, or that the frames' evidence does not
        agree with (a plain top measured at its rim alone: ``FusedGrid.agrees``), encloses the
        rectangle through its footprint and those cells (:meth:`ConnectedCells.enclosure`).
        Fusion serves the enclosures' cells the frames do not call occupied unknown (the
        contested layer), not free: the rest of a plain top of the floor's grey, which the floor
        model may have taken for floor. Two objects that touch are one part of the map: both are
        pieces of it, and both enclose the pair. A static track the frames agree with hands over
        its fringe instead (:meth:`ConnectedCells.fringe`, less every track's footprint; of a
        partial one, only where free floor lies beyond; an unsure one's from farther out), which
        fusion serves unknown (the fringe layer); so does each whole view of a moving track in
        the newest capture (:meth:`_mover_fringes`)."""
        config, resolution_m = self.config, cells.resolution_m
        pieces, enclosures, fringes = set(), [], []
        for track in self.tracks:
            if track.moving or track.detections < config.confirm_detections:
                continue
            length, width, yaw, _, partial, unsure, round_ = track.size(config)
            footprint = (*track.center_m, length, width, yaw)
            connected = connected_cells(
                cells, footprint, config.max_size_m, config.raster_reach_m, round_
            )
            if connected is None:
                continue
            overflow = connected.overflow(footprint, config.raster_margin_m)
            piece = overflow >= config.raster_overflow_share
            if piece:
                pieces.add(track.id)
            if track.static and (piece or not cells.agrees(*connected.footprint_cells)):
                enclosures.append(connected.enclosure(footprint, resolution_m))
            elif track.static:
                margin_m = config.fringe_margin_m
                if unsure:
                    margin_m = max(margin_m, config.unsure_fringe_spread * track.spread_m(config))
                fringes.append(
                    connected.fringe(
                        footprint,
                        margin_m,
                        config.partial_fringe_reach_m if partial else config.fringe_reach_m,
                        free_beyond=cells.free_in(connected.window) if partial else None,
                    )
                )
        return MapCheck(
            frozenset(pieces),
            enclosures,
            self._outside_tracks(fringes, resolution_m) + self._mover_fringes(cells),
        )

    def _mover_fringes(self, cells: OccupiedCells) -> list[tuple[Window, Mask]]:
        """The fringe of each whole view of a moving track in the newest capture, out to
        ``wake_margin_m``, less every other view of that capture and the footprints of the tracks
        that are not moving (a mover's own track, sized on all its views, is mostly larger than
        this one: the faces' hits stretch most of them)."""
        config, resolution_m = self.config, cells.resolution_m
        views = self._views_now()
        fringes: list[tuple[Window, Mask]] = []
        for view in views:
            connected = (
                None
                if view.partial
                else connected_cells(
                    cells, view.rectangle, config.max_size_m, config.raster_reach_m
                )
            )
            if connected is None:
                continue
            fringe = [
                connected.fringe(view.rectangle, config.fringe_margin_m, config.wake_margin_m)
            ]
            for other in views:
                if other is not view:
                    subtract_cells(fringe, polygon_cells(other.polygon(), resolution_m))
            fringes += fringe
        return self._outside_tracks(fringes, resolution_m, with_movers=False)

    def _outside_tracks(
        self, cells: list[tuple[Window, Mask]], resolution_m: float, with_movers: bool = True
    ) -> list[tuple[Window, Mask]]:
        """``cells`` less every track's footprint where it is now, the moving ones' only
        ``with_movers`` (a fringe is no other object's cells: a box beside it, a mover passing,
        one just put down)."""
        if cells:
            for footprint in self._footprints_now(with_movers):
                subtract_cells(cells, polygon_cells(footprint, resolution_m))
        return cells

    def ahead_s(self) -> float:
        """One frame interval: how far past the visible time a sweep must reach."""
        return self.frame_interval_s or self.config.default_frame_interval_s
