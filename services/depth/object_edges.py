"""An object's top face refined on the left image's edges: its sides where the image shows them,
below the pixel, where stereo's points only bound them to a pixel or two (DESIGN.md, Objects).

Why: a top face's points end where the matcher's window stops straddling its edge, a pixel or two
either way (2–5 cm at a half-resolution pixel), and a round top loses its rim to the rectangle
fit. The image itself shows the outline as a step of grey. The top is flat at a known height, so
the left image is sampled on that plane (a homography), where the face has its true shape; each
side moves to the nearest strong step along its normal, near where the points put it, in the grey
averaged along the side, so texture cancels and only an edge running the whole side counts. A round
top is found the same way, per sector of rings around its centre, and a circle fitted to them. The
outline whose steps are stronger wins; a side with no step (no contrast: a grey box on a grey
floor) keeps the points' estimate.

Pure numpy + OpenCV (one remap per object).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import cv2
import numpy as np
import numpy.typing as npt

from common.arrays import F64
from common.footprints import long_side_first
from services.depth.objects import Detection


@dataclass(frozen=True)
class EdgeConfig:
    step_m: float = 0.004
    """Sampling step on the top's plane, along a side's normal (a fifth of a processed pixel)."""
    search_m: float = 0.07
    """A side is looked for this far either side of where the points put it: their error is a
    pixel or two plus the matcher's fattening (measured up to 5 cm on the simulated site)."""
    plain_search_m: float = 0.12
    """…and this far inside it where the floor beyond is plain: with no texture there to hold it,
    the matcher carries a top's disparity further over the floor (``--floor plain``: box_0 0.73 m
    wide of 0.64, crate_0 0.62 of 0.46). Not on texture: 12 cm inside, a textured top's print
    took over from its edge (``--floor speckle``: box_0 0.54 m wide)."""
    face_search_m: float = 0.3
    """…and, on a side whose face the camera sees, its face's width (:func:`_side_band_m`), up to
    this, further either way: for the top's edge behind the face, and the face's foot beyond the
    top's edge (``_Across.find_side``)."""
    face_tolerance: float = 0.15
    """The top's edge behind a face is looked for within this share of the face's width (and a
    centimetre) of where the face's foot puts it: the blur widens a face's band by both its steps
    (drawn 12.8 cm wide, 14 cm found)."""
    plain_grey: float = 0.7
    """The floor beyond a side is plain where its grey changes by less than this from one pixel to
    the next along the side (median, grey levels): the sensor's noise, not texture. Offline, the
    floors beyond the objects' sides changed by 0.48 (median; plain), 1.36 (concrete) and 6.1
    (speckle); a shadow's or the light's slow change does not count."""
    along_share: float = 0.7
    """The central share of a side whose grey is averaged: its corners blur into the next side."""
    min_step_grey: float = 6.0
    """A step weaker than this (grey levels, across one pixel's footprint) is texture or noise."""
    nearest_share: float = 0.5
    """Of the steps at least this share of the strongest, the nearest to the points' side is
    taken: a low object's side face ends in a second step (side to floor) just outside its top's."""
    sectors: int = 12
    """A round top's rim is found in this many sectors, and a circle fitted through them (at least
    half of them: a top as grey as the floor shows only the rim before its dark side face)."""
    round_max_aspect: float = 1.25
    """Only a footprint this close to square may be a round top."""
    further_search_m: float = 0.16
    further_grey_share: float = 0.25
    """On a side facing away from the camera, the matcher can carry the top's disparity over the
    floor beyond it further than ``search_m`` (``--seed 5 --pairs 6``: box_4, 0.24 m high on
    concrete, 0.67 m wide of 0.59, its step 7.5-12 cm inside the points' side). Where the search
    there sees no strong step, or its strongest at its inner end, a step up to
    ``further_search_m`` inside is the top's edge if the grey just inside it is the grey just
    inside the sides found (the same top), and the grey between it and the points' side the
    floor's beyond, each within ``further_grey_share`` of the step's contrast
    (:func:`_further_side`).
    Without the first test a print on a top took over (``--floor speckle``: box_3 0.21 m wide
    of 0.40, 0.29 without the further search)."""


@dataclass(frozen=True)
class ImageView:
    """Where a world point falls in the rectified left image: its pinhole (focal and principal
    point, processed pixels), rotation rectified-left → world and camera centre."""

    focal_px: float
    cx_px: float
    cy_px: float
    R_world_rect: F64
    C_world: F64

    def pixels(
        self, x_m: F64, y_m: F64, height_m: float
    ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
        """Image column and row of world points at one height (NaN behind the camera)."""
        r = self.R_world_rect
        dx, dy, dz = x_m - self.C_world[0], y_m - self.C_world[1], height_m - self.C_world[2]
        x_rect, y_rect, z_rect = (r[0, i] * dx + r[1, i] * dy + r[2, i] * dz for i in range(3))
        z_rect = np.where(z_rect > 1e-6, z_rect, np.nan)
        u = self.focal_px * x_rect / z_rect + self.cx_px
        v = self.focal_px * y_rect / z_rect + self.cy_px
        return u.astype(np.float32), v.astype(np.float32)


def _sample(
    image: npt.NDArray[np.float32], view: ImageView, x_m: F64, y_m: F64, top_m: float
) -> F64:
    """Grey at world points on the plane at ``top_m``; NaN outside the image."""
    u, v = view.pixels(x_m, y_m, top_m)
    height, width = image.shape
    inside = (u >= 0) & (u <= width - 1) & (v >= 0) & (v <= height - 1)
    grey = cv2.remap(
        image, np.nan_to_num(u, nan=-1.0), np.nan_to_num(v, nan=-1.0), cv2.INTER_LINEAR
    ).astype(np.float64)
    return np.where(inside, grey, np.nan)


def _step_at(
    grey: F64,
    offsets_m: F64,
    lag: int,
    side_band_m: float,
    config: EdgeConfig,
    searched_m: tuple[float, float] = (-math.inf, math.inf),
    face_growth: float | None = None,
) -> tuple[float, float] | None:
    """Where along a profile (grey averaged along an edge, sampled at ``offsets_m`` outward from
    the points' edge) the top's edge lies, sub-sample, and its step; None if no step is strong.

    The strong step nearest the points' edge, searched within ``searched_m``, except on a side
    the camera sees: its face shows as a band outside the top's edge, often ending in the
    stronger step (side to floor). ``side_band_m`` is the band's width below the points' edge.
    Without ``face_growth`` (a round top's rim), a step of the other sign (the band darker or
    lighter than both its neighbours) that far inside the chosen one is the top's edge. With it
    (1 / (1 - top / camera height)): below an edge e further out the band is narrower, by
    e · (1 - 1 / ``face_growth``); a step of the other sign as strong as half the chosen one,
    where the chosen step's face would end outside it, makes the chosen step the top's edge;
    else one where the top's edge lies if the chosen step is the face's foot f, at
    (f - ``side_band_m``) · ``face_growth``, is the top's edge (past ``searched_m`` only one as
    strong as half the chosen one). The profile past ``searched_m`` is there for those two
    steps alone."""
    if np.isnan(grey).any():
        return None
    outward, at = _steps(grey, offsets_m, lag)
    step = np.abs(outward)
    searched = (at >= searched_m[0]) & (at <= searched_m[1])
    strongest = float(step[searched].max(initial=0.0))
    if strongest < config.min_step_grey:
        return None
    peaks = [
        k
        for k in range(1, len(step) - 1)
        if step[k] >= max(step[k - 1], config.min_step_grey) and step[k] > step[k + 1]
    ]
    # A peak at the search's end is no peak of the search (the profile goes on past it).
    strong = [
        k
        for k in peaks
        if searched[k - 1 : k + 2].all() and step[k] >= config.nearest_share * strongest
    ]
    if not strong:
        return None  # the strongest step lies at the end of the search: past where it may be
    sample_m = float(at[1] - at[0])
    positions = {k: float(at[k]) + sample_m * _vertex(step[k - 1 : k + 2]) for k in peaks}
    k = min(strong, key=lambda p: abs(positions[p]))
    tolerance_m = max(lag * sample_m, 0.01)
    if side_band_m <= tolerance_m:
        return positions[k], float(step[k])
    if face_growth is None:
        inner = [
            p
            for p in peaks
            if abs(positions[p] - (positions[k] - side_band_m)) <= tolerance_m
            and outward[p] * outward[k] < 0
        ]
        if inner:
            k = max(inner, key=lambda p: step[p])
        return positions[k], float(step[k])

    def facing(position_m: float, searched_too: bool) -> list[int]:
        """Peaks of the other sign than k's near ``position_m`` (within ``face_tolerance`` of the
        face's width between them): only as strong as an edge (a print on a top is weaker),
        but for those within the search where ``searched_too``."""
        face_m = abs(position_m - positions[k])
        near_m = max(tolerance_m, config.face_tolerance * face_m)
        return [
            p
            for p in peaks
            if abs(positions[p] - position_m) <= near_m
            and outward[p] * outward[k] < 0
            and ((searched_too and searched[p]) or step[p] >= config.nearest_share * step[k])
        ]

    band_at_k_m = side_band_m - positions[k] * (1.0 - 1.0 / face_growth)
    if band_at_k_m > tolerance_m and facing(positions[k] + band_at_k_m, False):
        return positions[k], float(step[k])  # k is the top's edge: its face's foot lies beyond
    inner = facing((positions[k] - side_band_m) * face_growth, True)
    if inner:
        k = max(inner, key=lambda p: step[p])
    return positions[k], float(step[k])


def _steps(grey: F64, offsets_m: F64, lag: int) -> tuple[F64, F64]:
    """A profile's change outward across ``2 * lag`` samples, and the offsets it is centred at."""
    return grey[2 * lag :] - grey[: -2 * lag], offsets_m[lag:-lag]


def _vertex(three: F64) -> float:
    """Sub-sample offset of a parabola's vertex through three samples around a peak."""
    a, b, c = three
    return float(0.5 * (a - c) / (a - 2 * b + c)) if a - 2 * b + c < 0 else 0.0


def _side_band_m(
    view: ImageView, edge_xy_m: tuple[float, float], normal_xy: tuple[float, float], top_m: float
) -> float:
    """How wide (along the outward normal, on the top's plane) the side face below an edge shows:
    its foot at the floor appears toward the camera's nadir by top/height of its distance from it;
    0 for a side facing away from the camera."""
    nadir_x, nadir_y, height_m = (float(v) for v in view.C_world)
    toward_nadir = normal_xy[0] * (nadir_x - edge_xy_m[0]) + normal_xy[1] * (nadir_y - edge_xy_m[1])
    return max(0.0, toward_nadir * top_m / height_m)


def _face_growth(top_m: float, view: ImageView) -> float:
    """1 / (1 - top / camera height): how far in a top's edge lies per metre its face's foot
    does (:func:`_step_at`)."""
    return 1.0 / max(1.0 - top_m / float(view.C_world[2]), 0.1)


_ALONG_PX = 0.5
"""Samples along a side lie this many pixels apart: enough to average texture out."""
_TINY_M = 1e-9
"""Offsets this close to a search's bound count as within it (sums of steps in floats)."""


@dataclass(frozen=True)
class _Across:
    """How an edge's profile is sampled across it, for one top's height: its pixel's footprint
    there, the step's lag (half a pixel each way, in samples) and the offsets from the points'
    edge, outward positive (reaching ``plain_search_m`` and the widest face inside, or
    ``further_search_m`` and three pixels, and that face outside, in whole samples)."""

    pixel_m: float
    lag: int
    offsets_m: F64
    textured_m: tuple[float, float]
    """The offsets sampled for the search where the floor beyond is textured (``search_m`` and
    the lag either way) …"""
    plain_from_m: float
    """… and from where inside where it is plain (``plain_search_m`` and the lag) …"""
    further_from_m: float
    """… and from where inside on a far side (``further_search_m`` and the lag)."""
    face_growth: float
    """How far in the top's edge lies, per metre the face's foot lies in, from where the points'
    side would have its foot (:func:`_step_at`): the face widens by top / camera height of it."""

    @staticmethod
    def at(top_m: float, view: ImageView, config: EdgeConfig, face_m: float = 0.0) -> _Across:
        """``face_m``: the widest side face the object shows (:func:`_side_band_m`), which the
        offsets reach either way past the search."""
        pixel_m = max(float(view.C_world[2]) - top_m, 0.1) / view.focal_px
        lag = max(1, round(pixel_m / 2 / config.step_m))
        reach = config.search_m + lag * config.step_m
        offsets = np.arange(-reach, reach + config.step_m / 2, config.step_m)
        # The plain floor's and the face's further reach, on the same samples.
        plain = round((config.plain_search_m - config.search_m) / config.step_m)
        further = round((config.further_search_m - config.search_m) / config.step_m)
        face = math.ceil(face_m / config.step_m)
        below = math.ceil(3 * pixel_m / config.step_m)  # a further step's top (:meth:`grey_inside`)
        inside = offsets[0] - config.step_m * np.arange(max(plain + face, further + below), 0, -1)
        outside = offsets[-1] + config.step_m * np.arange(1, face + 1)
        return _Across(
            pixel_m,
            lag,
            np.concatenate([inside, offsets, outside]),
            (float(offsets[0]), float(offsets[-1])),
            float(offsets[0] - plain * config.step_m),
            float(offsets[0] - further * config.step_m),
            _face_growth(top_m, view),
        )

    def find_side(
        self,
        grey: F64,
        along_px: float,
        side_band_m: float,
        config: EdgeConfig,
        behind_face: bool = True,
    ) -> tuple[float, float] | None:
        """:func:`_step_at` on a side's samples (rows: offsets, columns: ``along_px`` apart along
        the side), searched ``plain_search_m`` inside where the floor beyond the side (a pixel
        past it and past its face) is plain and the samples there lie in the image, else
        ``search_m``. It looks at the floor only: a print on a top over a plain floor can still
        take over from its edge. With ``behind_face``, the profile reaches a face's width
        further either way: inside for the top's edge behind the face's foot (a plain face's
        pixels near the top take the top's disparity and put the points' edge out over the
        face: a forklift's, 1.1 m high, 0.19 m out), outside for the foot of the face below a
        top's edge. Not for a round top's rim: offline, the static cylinders came out smaller
        still (``--seed 1 --pairs 6``: 0.41 m wide, 0.43 without, 0.475 true)."""
        plain = self._plain(grey, along_px, side_band_m, config)
        from_m = self.plain_from_m if plain else self.textured_m[0]
        return self._search(grey, from_m, side_band_m, config, behind_face)

    def _plain(self, grey: F64, along_px: float, side_band_m: float, config: EdgeConfig) -> bool:
        """Whether the floor beyond a side (a pixel past it and past its face) is plain and the
        samples ``plain_search_m`` inside lie in the image (:meth:`find_side`)."""
        to_m = self.textured_m[1]
        beyond = grey[(self.offsets_m > side_band_m + self.pixel_m) & (self.offsets_m <= to_m)]
        lag = max(1, round(1.0 / along_px))  # the samples a pixel apart
        change = np.abs(beyond[:, lag:] - beyond[:, :-lag])
        plain_reach = (self.offsets_m >= self.plain_from_m - _TINY_M) & (self.offsets_m <= to_m)
        return (
            bool(change.size)
            and float(np.median(change)) < config.plain_grey
            and not np.isnan(grey[plain_reach]).any()
        )

    def grey_at(self, profile: F64, low_m: float, high_m: float) -> float:
        """The mean of a side's profile (grey per offset) over offsets ``low_m`` … ``high_m``; NaN
        where none lies there (numpy's mean of nothing said so on stderr, into the service's log)."""
        values = profile[(self.offsets_m >= low_m) & (self.offsets_m <= high_m)]
        return float(values.mean()) if values.size else math.nan

    def grey_inside(self, profile: F64, edge_m: float) -> float:
        """The top's grey just inside a step at ``edge_m``: a pixel to three pixels in."""
        return self.grey_at(profile, edge_m - 3 * self.pixel_m, edge_m - self.pixel_m)

    def step_further_in(
        self, grey: F64, along_px: float, side_band_m: float, config: EdgeConfig
    ) -> tuple[float, float] | None:
        """Where :meth:`find_side` found no step on a side that shows no face wider than a pixel
        (facing away from the camera) over a floor that is not plain: a step up to
        ``further_search_m`` inside, if the search saw no strong one or its strongest at its
        inner end (taken or not by :func:`_further_side`)."""
        if side_band_m > self.pixel_m or self._plain(grey, along_px, side_band_m, config):
            return None
        from_m = self.textured_m[0]
        if not self._edge_further_in(grey, from_m, config):
            return None
        return self._search(grey, self.further_from_m, side_band_m, config, True)

    def _profile(self, grey: F64, from_m: float, face_m: float) -> npt.NDArray[np.bool_]:
        """The offsets from ``from_m`` to the search's outer end, and a face's width further
        either way where those samples lie in the image."""
        to_m = self.textured_m[1]
        profile = (self.offsets_m >= from_m - face_m - _TINY_M) & (
            self.offsets_m <= to_m + face_m + _TINY_M
        )
        if np.isnan(grey[profile]).any():  # the face's reach lies off the image: without it
            profile = (self.offsets_m >= from_m - _TINY_M) & (self.offsets_m <= to_m + _TINY_M)
        return profile

    def _searched_m(self, from_m: float, config: EdgeConfig) -> tuple[float, float]:
        """Where a step may peak: a lag in from either end of ``from_m`` … the outer end."""
        step_m = config.step_m
        return (
            from_m + self.lag * step_m - _TINY_M,
            self.textured_m[1] - self.lag * step_m + _TINY_M,
        )

    def _search(
        self, grey: F64, from_m: float, side_band_m: float, config: EdgeConfig, behind_face: bool
    ) -> tuple[float, float] | None:
        """:func:`_step_at` over the offsets from ``from_m`` outward."""
        # The top's edge behind the face, and the face's foot beyond the top's edge: the face's
        # width past the search's own reach, which covers its growth for faces up to 0.3 m. To
        # the growth and the tolerance on it (the reach 0.04-0.07 m further), a box cut by the
        # border beside the forklift's path lost its rim to the floor at times (offline, default
        # scene: static false-free 0.04 -> 0.09 %).
        profile = self._profile(grey, from_m, side_band_m if behind_face else 0.0)
        return _step_at(
            grey[profile].mean(axis=1),
            self.offsets_m[profile],
            self.lag,
            side_band_m,
            config,
            self._searched_m(from_m, config),
            self.face_growth if behind_face else None,
        )

    def _edge_further_in(self, grey: F64, from_m: float, config: EdgeConfig) -> bool:
        """Whether the search from ``from_m`` saw no strong step, or its strongest at its inner
        end (the shoulder of one further in)."""
        profile = self._profile(grey, from_m, 0.0)
        outward, at = _steps(grey[profile].mean(axis=1), self.offsets_m[profile], self.lag)
        low, high = self._searched_m(from_m, config)
        step = np.abs(outward)[(at >= low) & (at <= high)]
        return bool(step.size) and (step.max() < config.min_step_grey or int(np.argmax(step)) == 0)


def _world(d: Detection, along_m: F64 | float, across_m: F64 | float) -> tuple[F64, F64]:
    """World x, y of points given in the detection's frame (along its yaw, across it)."""
    c, s = math.cos(d.yaw_rad), math.sin(d.yaw_rad)
    x = d.center_xy_m[0] + c * np.asarray(along_m) - s * np.asarray(across_m)
    y = d.center_xy_m[1] + s * np.asarray(along_m) + c * np.asarray(across_m)
    return x, y


def _further_side(
    across: _Across, grey: F64, side_band_m: float, top_grey: float, config: EdgeConfig
) -> tuple[float, float] | None:
    """:meth:`_Across.step_further_in`, if the grey just inside its step is ``top_grey`` (the
    grey just inside the sides found: the same top) and between it and the points' side the grey
    beyond (the floor), each within ``further_grey_share`` of its contrast."""
    step = across.step_further_in(grey, _ALONG_PX, side_band_m, config)
    if step is None:
        return None
    profile = grey.mean(axis=1)
    top = across.grey_inside(profile, step[0])
    between = across.grey_at(profile, step[0] + across.pixel_m, 0.0)
    floor = across.grey_at(profile, across.pixel_m, across.textured_m[1])
    tolerance = config.further_grey_share * abs(floor - top)
    if abs(top - top_grey) <= tolerance and abs(between - floor) <= tolerance:
        return step
    return None


def _refine_box(
    image: npt.NDArray[np.float32],
    view: ImageView,
    d: Detection,
    across: _Across,
    config: EdgeConfig,
) -> tuple[Detection, float] | None:
    """The four sides moved to their steps; the mean step size, or None if no side had one."""
    c, s = math.cos(d.yaw_rad), math.sin(d.yaw_rad)
    half = (d.length_m / 2, d.width_m / 2)
    bounds = [-half[0], half[0], -half[1], half[1]]  # along low/high, across low/high
    sides = ((0, -1), (0, 1), (1, -1), (1, 1))
    xs, ys, widths, bands = [], [], [], []
    along_m = _ALONG_PX * across.pixel_m  # the samples' spacing along a side
    for axis, sign in sides:
        other = half[1 - axis] * config.along_share
        along = np.linspace(-other, other, max(3, math.ceil(2 * other / along_m)))
        normal = sign * half[axis] + sign * across.offsets_m  # outward positive
        if axis == 0:
            x, y = _world(d, normal[:, None], along[None, :])
        else:
            x, y = _world(d, along[None, :], normal[:, None])
        xs.append(x)
        ys.append(y)
        widths.append(along.size)
        nu, nw = (sign, 0.0) if axis == 0 else (0.0, sign)
        edge_x, edge_y = _world(d, nu * half[0], nw * half[1])
        normal_xy = (c * nu - s * nw, s * nu + c * nw)
        bands.append(_side_band_m(view, (float(edge_x), float(edge_y)), normal_xy, d.top_m))
    # One lookup for all four sides. Rows: offsets along the normal; columns: along a side.
    grey = _sample(image, view, np.hstack(xs), np.hstack(ys), d.top_m)
    columns = np.split(grey, np.cumsum(widths)[:-1], axis=1)
    found = [
        across.find_side(c, _ALONG_PX, band, config) for c, band in zip(columns, bands, strict=True)
    ]
    tops = [
        across.grey_inside(c.mean(axis=1), f[0]) for c, f in zip(columns, found, strict=True) if f
    ]
    tops = [top for top in tops if math.isfinite(top)]  # not where the image ends
    if tops:
        found = [
            f or _further_side(across, c, band, float(np.mean(tops)), config)
            for c, band, f in zip(columns, bands, found, strict=True)
        ]
    strengths = []
    for side, step in enumerate(found):
        if step is None:
            continue
        axis, sign = sides[side]
        bounds[side] = sign * (half[axis] + step[0])
        strengths.append(step[1])
    if not strengths or bounds[1] <= bounds[0] or bounds[3] <= bounds[2]:
        return None  # no step, or two facing sides moved past each other: no footprint
    du, dw = (bounds[0] + bounds[1]) / 2, (bounds[2] + bounds[3]) / 2
    length, width, yaw = long_side_first(bounds[1] - bounds[0], bounds[3] - bounds[2], d.yaw_rad)
    center_x, center_y = _world(d, du, dw)
    return (
        replace(
            d,
            center_xy_m=(float(center_x), float(center_y)),
            length_m=length,
            width_m=width,
            yaw_rad=yaw,
        ),
        float(np.mean(strengths)),
    )


def _refine_round(
    image: npt.NDArray[np.float32],
    view: ImageView,
    d: Detection,
    across: _Across,
    config: EdgeConfig,
) -> tuple[Detection, float] | None:
    """A circle through the rim found in each sector of rings around the centre."""
    radius = (d.length_m + d.width_m) / 4
    per_sector = 8
    angles = (np.arange(config.sectors * per_sector) + 0.5) * (
        2 * math.pi / (config.sectors * per_sector)
    )
    arc_px = 2 * math.pi * radius / (config.sectors * per_sector) / across.pixel_m
    radii = np.maximum(radius + across.offsets_m, 0.0)
    x = d.center_xy_m[0] + radii[:, None] * np.cos(angles)[None, :]
    y = d.center_xy_m[1] + radii[:, None] * np.sin(angles)[None, :]
    grey = _sample(image, view, x, y, d.top_m).reshape(len(radii), config.sectors, per_sector)
    rim_x, rim_y, strengths = [], [], []
    for k in range(config.sectors):
        theta = (k + 0.5) * 2 * math.pi / config.sectors
        normal = (math.cos(theta), math.sin(theta))
        rim = (d.center_xy_m[0] + radius * normal[0], d.center_xy_m[1] + radius * normal[1])
        band = _side_band_m(view, rim, normal, d.top_m)
        found = across.find_side(grey[:, k], arc_px, band, config, behind_face=False)
        if found is None:
            continue
        rim_x.append((radius + found[0]) * math.cos(theta))
        rim_y.append((radius + found[0]) * math.sin(theta))
        strengths.append(found[1])
    if len(strengths) < config.sectors // 2:
        return None  # a circle through less than half its rim is a guess
    # Kåsa's algebraic circle fit: x² + y² = 2ax + 2by + c.
    px, py = np.asarray(rim_x), np.asarray(rim_y)
    design = np.column_stack([2 * px, 2 * py, np.ones_like(px)])
    (a, b, k0), *_ = np.linalg.lstsq(design, px**2 + py**2, rcond=None)
    fitted = math.sqrt(max(k0 + a * a + b * b, 0.0))
    if fitted <= 0.0:
        return None
    center = (d.center_xy_m[0] + a, d.center_xy_m[1] + b)
    return (
        replace(d, center_xy_m=center, length_m=2 * fitted, width_m=2 * fitted, round=True),
        float(np.mean(strengths)),
    )


def _widest_face_m(view: ImageView, d: Detection, config: EdgeConfig) -> float:
    """A bound on the widest face the detection shows, up to ``face_search_m``: :func:`_side_band_m`
    of an edge as far from the nadir as any of its sides (its centre's distance and half its
    length)."""
    away = np.asarray(d.center_xy_m, np.float64) - np.asarray(view.C_world[:2], np.float64)
    distance_m = float(np.hypot(*away))
    unit = away / distance_m if distance_m > 0 else np.array([1.0, 0.0])
    edge = np.asarray(d.center_xy_m) + unit * d.length_m / 2
    band_m = _side_band_m(view, (float(edge[0]), float(edge[1])), (-unit[0], -unit[1]), d.top_m)
    return min(band_m, config.face_search_m)


def refine_on_edges(
    detections: list[Detection],
    left_rect: npt.NDArray[np.uint8],
    view: ImageView,
    config: EdgeConfig = EdgeConfig(),
) -> list[Detection]:
    """The frame's detections with their sides (or rims) moved onto the image's steps where it
    shows them; a low detection (a pallet) keeps the sides its points' density gave."""
    image = left_rect.astype(np.float32)
    out = []
    for detection in detections:
        if detection.low:
            # A pallet's deck boards, the openings below them and the paint around its zone give
            # steps a few centimetres apart; its points' density found its sides (default scene,
            # pallet_0's width: 0.847 m refined, 0.812 without; 0.8 true).
            out.append(detection)
            continue
        across = _Across.at(detection.top_m, view, config, _widest_face_m(view, detection, config))
        best = _refine_box(image, view, detection, across, config)
        if detection.length_m <= config.round_max_aspect * detection.width_m:
            round_top = _refine_round(image, view, detection, across, config)
            if round_top is not None and (best is None or round_top[1] > best[1]):
                best = round_top
        out.append(detection if best is None else best[0])
    return out
