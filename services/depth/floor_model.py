"""The fixed-camera floor model of one stereo pair (DESIGN.md, "The fixed-camera floor model").

The cameras never move and the floor is the plane z = 0 of the calibration, so after rectification
the floor's disparity is a known affine function of the pixel. Two cues follow, per pair and frame,
on the rectified images at the processing resolution:

- **Floor test** (plane consistency): the right image is remapped at the floor's disparity, so that
  a floor pixel of the left image meets its own floor point in the right; zero-mean normalised
  cross-correlation over a small window says *agree* (textured and matching), *contradict*
  (textured and not matching: something above or below the floor) or nothing (too little texture).
- **Background**: a per-pixel appearance model of the empty floor for each camera (the right one on
  the floor-warped grid, so pixel p of both models looks at the same floor point), mean and spread
  after a global gain normalisation (auto-exposure, a lighting step scale every floor pixel alike).

Evidence rules (what :meth:`FloorModel.update` returns):

1. A pixel with a stereo disparity keeps it, except *fattening*: an object disparity where the
   floor test agrees, or where both cameras match their backgrounds and the floor test does not
   contradict, is the matcher's window dragging a nearby edge's disparity onto the floor: it
   becomes a floor observation.
2. A pixel without a disparity is a floor observation only where both cameras' pixels (the left
   pixel and its floor-homography partner in the right) match their backgrounds and the floor test
   does not contradict.
3. The floor test alone never makes a floor observation: a uniform box top also "agrees" under the
   floor warp.
4. A pixel whose appearance departs from the background and has no disparity gives no evidence
   (unknown); it is never called free, and occupied only where stereo says so.
5. Shadows lie on the floor: on texture they keep the floor test's agreement and stereo's floor
   disparity (rule 1 and the matcher's own output), on a plain floor they are a departure (rule 4,
   unknown), never an obstacle.

Learning (never from pixels where something stands):

- *Seeds* are pixels stereo measures at the floor's disparity, or that the floor test agrees on.
- The model grows from seeds over *smooth* pixels (no intensity edge, no contradiction): a smooth
  connected region holding enough seeds is floor, so a plain floor is learned from the few floor
  edges stereo can measure (object bases, wall bases, markings). An object standing since start-up
  is bounded by its outline (an intensity edge, a contradiction or an object disparity) and never
  joins: it stays unmodelled, so it is never a floor observation.
- A pixel is modelled once it has been confirmed as floor in ``confirm_frames`` frames; later it is
  updated (running mean and variance) only while it is confirmed and still matches.
- When most modelled pixels depart at once after gain normalisation (a lighting change that is not
  a global scale), the model re-learns: every pixel confirmed in that frame starts again from it.
- The floor's disparity from the calibration is off by a fraction of a pixel when the calibration
  is: an affine offset in the pixel is fitted to the pixels stereo measures near the floor.

Pure numpy/OpenCV, no I/O: the depth pipeline owns one per pair.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

F32 = npt.NDArray[np.float32]
Mask = npt.NDArray[np.bool_]


FLOOR_WINDOW_SHARE = 0.6
"""A seed needs this share of its window measured at the floor's disparity."""
OFFSET_EVERY_FRAMES = 4
"""The calibration offset drifts, if at all, over hours: fit it every few frames only."""


@dataclass(frozen=True)
class FloorModelConfig:
    enabled: bool = True
    window_px: int = 5
    """Side of the floor test's correlation window (processing pixels)."""
    blur_sigma_px: float = 1.0
    """Gaussian blur before every comparison: sensor noise, JPEG blocks, a fraction-of-a-pixel
    calibration error all matter less on a slightly blurred image."""
    texture_gray: float = 1.0
    """Local standard deviation (gray levels) both windows need for the floor test to speak."""
    agree_zncc: float = 0.7
    contradict_zncc: float = 0.3
    floor_tolerance_px: float = 0.35
    """Stereo measures the floor when its disparity is within this of the floor's."""
    edge_gray: float = 1.0
    """Gradient (gray levels per pixel, blurred image) that stops the model's growth."""
    min_seeds: int = 40
    """A smooth region is learned as floor only with at least this many seeds in it …"""
    seed_share: float = 0.002
    """… and at least this share of its pixels."""
    match_sigmas: float = 4.0
    match_min_gray: float = 6.0
    match_relative: float = 0.05
    """A pixel matches its background within max(match_sigmas·σ, match_min_gray, match_relative·mean)."""
    learn_rate: float = 0.05
    confirm_frames: int = 2
    ready_share: float = 0.3
    """The model reports *ready* once this share of the image is modelled."""
    relearn_share: float = 0.5
    """Re-learn when more than this share of the modelled pixels departs at once."""
    offset_rate: float = 0.2
    min_offset_pixels: int = 200


@dataclass(frozen=True)
class FloorFrame:
    """One frame's verdict: what goes to the sensor model, and what the health report shows."""

    disparity_px: F32
    """Stereo disparity with fattening removed and floor observations filled in at the floor's
    disparity; NaN where there is no evidence."""
    floor_observed: Mask
    """Pixels whose evidence is the floor model's (rules 1 and 2), not the matcher's own."""
    modelled_share: float
    state: str


def floor_disparity_px(
    rays_world: F32, camera_height_m: float, focal_px: float, baseline_m: float
) -> F32:
    """Disparity of the plane z = 0 at every rectified pixel: depth z = -C_z / ray_z along rays
    scaled so that P = C + z·ray (``Rectifier.pixel_rays_world``), then d = f·b / z."""
    down = np.maximum(-rays_world[2].astype(np.float64), 1e-9)
    disparity: F32 = (focal_px * baseline_m * down / camera_height_m).astype(np.float32)
    return disparity


def _blur(image: npt.NDArray[np.uint8] | F32, sigma_px: float) -> F32:
    blurred: F32 = np.asarray(
        cv2.GaussianBlur(image.astype(np.float32), (0, 0), sigma_px), dtype=np.float32
    )
    return blurred


class FloorModel:
    """Floor test, background per camera, and the evidence rules of the module docstring."""

    def __init__(self, floor_disparity: F32, config: FloorModelConfig | None = None) -> None:
        self.config = config or FloorModelConfig()
        self.floor_disparity = floor_disparity.astype(np.float32)
        height, width = floor_disparity.shape
        self.shape = (height, width)
        v, u = np.mgrid[0:height, 0:width].astype(np.float32)
        self._u, self._v = u, v
        # Affine floor-disparity offset a + b·u' + c·v' (u', v' in [-1, 1]); fitted at run time.
        self._basis = np.stack([np.ones_like(u), u / width * 2 - 1, v / height * 2 - 1])
        self.offset_coef = np.zeros(3, np.float64)
        self.mean = np.zeros((2, height, width), np.float32)
        self.var = np.zeros((2, height, width), np.float32)
        self.confirmed = np.zeros((height, width), np.uint8)
        self.frames = 0
        self.relearned = 0
        side = self.config.window_px
        self._neighbourhood = np.ones((side, side), np.uint8)
        self._gain = (1.0, 1.0)
        self._touch = np.ones((3, 3), np.uint8)
        self._floor_now = self._offset_floor()

    # -- geometry -------------------------------------------------------------------------------

    def floor_disparity_now(self) -> F32:
        """The floor's disparity with the fitted calibration offset."""
        return self._floor_now

    def _offset_floor(self) -> F32:
        offset = np.tensordot(self.offset_coef.astype(np.float32), self._basis, axes=1)
        disparity: F32 = (self.floor_disparity + offset).astype(np.float32)
        return disparity

    def _fit_offset(self, disparity: F32, floor_now: F32) -> None:
        """Least-squares affine fit of stereo − floor over pixels within a pixel of the floor."""
        step = 3
        d = disparity[::step, ::step]
        r = d - floor_now[::step, ::step]
        near = np.isfinite(r) & (np.abs(r) < 1.0)
        if int(near.sum()) < self.config.min_offset_pixels // (step * step):
            return
        basis = self._basis[:, ::step, ::step][:, near].T
        residual = r[near] + basis @ self.offset_coef  # residual against the calibration's floor
        coef, *_ = np.linalg.lstsq(basis, residual, rcond=None)
        rate = 1.0 if self.frames == 0 else self.config.offset_rate
        self.offset_coef += rate * (coef - self.offset_coef)
        self._floor_now = self._offset_floor()

    # -- one frame --------------------------------------------------------------------------

    @property
    def modelled(self) -> Mask:
        modelled: Mask = self.confirmed >= self.config.confirm_frames
        return modelled

    def modelled_share(self) -> float:
        return float(np.count_nonzero(self.modelled)) / float(self.confirmed.size)

    def state(self) -> str:
        return "ready" if self.modelled_share() >= self.config.ready_share else "learning"

    def update(
        self, left_rect: npt.NDArray[np.uint8], right_rect: npt.NDArray[np.uint8], disparity: F32
    ) -> FloorFrame:
        """Apply the evidence rules to one frame, then learn from it."""
        cfg = self.config
        floor_now = self.floor_disparity_now()
        left = _blur(left_rect, cfg.blur_sigma_px)
        right_full = _blur(right_rect, cfg.blur_sigma_px)
        map_x = self._u - floor_now
        warped = np.asarray(
            cv2.remap(right_full, map_x, self._v, cv2.INTER_LINEAR, borderValue=np.nan),
            dtype=np.float32,
        )
        inside = np.isfinite(warped)
        warped[~inside] = 0.0

        agree, contradict, textured = self._floor_test(left, warped, inside)

        valid = np.isfinite(disparity)
        with np.errstate(invalid="ignore"):
            at_floor = valid & (np.abs(disparity - floor_now) <= cfg.floor_tolerance_px)
        near_object = cv2.dilate((valid & ~at_floor).astype(np.uint8), self._neighbourhood) > 0
        # A disparity on an untextured pixel is the matcher's interpolation, not a measurement; and
        # one pixel at the floor's disparity is noise unless most of its window is there too.
        window = (cfg.window_px, cfg.window_px)
        floor_share = cv2.blur(at_floor.astype(np.float32), window)
        measured_floor = textured & (floor_share >= FLOOR_WINDOW_SHARE)
        seeds = (measured_floor | (agree & ~valid & ~near_object)) & inside

        match_left, match_right, departed = self._match(left, warped, inside)
        modelled = self.modelled & inside
        matches = modelled & match_left & match_right & ~contradict

        # Rules 1 and 2: fattening over the floor, and floor without a disparity.
        fattened = valid & ~at_floor & ~textured & matches
        filled = ~valid & matches
        floor_observed = fattened | filled
        out = disparity.copy()
        out[floor_observed] = floor_now[floor_observed]

        self._learn(left, warped, inside, seeds, contradict, matches, departed, modelled)
        if self.frames % OFFSET_EVERY_FRAMES == 0:
            self._fit_offset(disparity, floor_now)
        self.frames += 1
        return FloorFrame(out, floor_observed, self.modelled_share(), self.state())

    def _floor_test(self, left: F32, warped: F32, inside: Mask) -> tuple[Mask, Mask, Mask]:
        """Agree, contradict (both on texture only) and textured, from ZNCC over a small window."""
        cfg = self.config
        k = (cfg.window_px, cfg.window_px)
        mean_l = cv2.blur(left, k)
        mean_r = cv2.blur(warped, k)
        var_l = cv2.blur(left * left, k) - mean_l * mean_l
        var_r = cv2.blur(warped * warped, k) - mean_r * mean_r
        cov = cv2.blur(left * warped, k) - mean_l * mean_r
        texture = cfg.texture_gray**2
        textured_left: Mask = var_l > texture
        textured = textured_left & (var_r > texture) & inside
        zncc = cov / np.sqrt(np.maximum(var_l * var_r, 1e-6))
        agree: Mask = textured & (zncc >= cfg.agree_zncc)
        contradict: Mask = textured & (zncc < cfg.contradict_zncc)
        return agree, contradict, textured_left

    def _gains(self, left: F32, warped: F32, modelled: Mask) -> tuple[float, float]:
        """Global gain of each camera against its background (median ratio over modelled pixels):
        exposure, gain and a uniform lighting change scale every floor pixel alike."""
        step = 4
        sample = modelled[::step, ::step]
        if int(sample.sum()) < 50:
            return 1.0, 1.0
        gains = []
        for side, image in ((0, left), (1, warped)):
            background = self.mean[side, ::step, ::step][sample]
            ratio = image[::step, ::step][sample] / np.maximum(background, 1.0)
            gains.append(float(np.median(ratio)))
        return gains[0], gains[1]

    def _match(self, left: F32, warped: F32, inside: Mask) -> tuple[Mask, Mask, float]:
        """Per camera, whether each pixel matches its background after gain normalisation; and
        the share of modelled pixels that departs (for the re-learn decision)."""
        cfg = self.config
        modelled = self.modelled & inside
        self._gain = self._gains(left, warped, modelled)
        matches = []
        for side, image in ((0, left), (1, warped)):
            mean = self.mean[side] * np.float32(self._gain[side])
            tolerance = np.maximum(
                np.maximum(cfg.match_sigmas * np.sqrt(self.var[side]), cfg.match_min_gray),
                cfg.match_relative * mean,
            )
            matches.append(np.abs(image - mean) <= tolerance)
        both = matches[0] & matches[1]
        count = int(modelled.sum())
        if count < self.config.min_offset_pixels:
            return matches[0], matches[1], 0.0
        departed = 1.0 - float(np.count_nonzero(both & modelled)) / count
        return matches[0], matches[1], departed

    def _grown(self, left: F32, seeds: Mask, contradict: Mask) -> Mask:
        """Smooth connected regions holding enough seeds (the plain floor around floor edges)."""
        cfg = self.config
        gx = cv2.Sobel(left, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
        gy = cv2.Sobel(left, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
        smooth = (np.abs(gx) + np.abs(gy) < cfg.edge_gray) & ~contradict
        count, labels = cv2.connectedComponents(smooth.astype(np.uint8), connectivity=4)
        if count <= 1:
            return np.zeros(self.shape, np.bool_)
        sizes = np.bincount(labels.ravel(), minlength=count)
        # Seeds sit on floor-level edges, next to the smooth floor rather than inside it.
        touching = cv2.dilate(seeds.astype(np.uint8), self._touch) > 0
        seeded = np.bincount(labels[touching & smooth], minlength=count)
        enough = (seeded >= cfg.min_seeds) & (seeded >= cfg.seed_share * sizes)
        enough[0] = False  # label 0 is the non-smooth background
        grown: Mask = enough[labels]
        return grown

    def _learn(
        self,
        left: F32,
        warped: F32,
        inside: Mask,
        seeds: Mask,
        contradict: Mask,
        matches: Mask,
        departed: float,
        modelled: Mask,
    ) -> None:
        cfg = self.config
        confirmed = (seeds | self._grown(left, seeds, contradict)) & inside
        relearn = departed > cfg.relearn_share and self.frames > 0
        if relearn:
            # Most of the floor changed at once, and not by a global gain: start again from here.
            self.relearned += 1
            self.confirmed[:] = 0
        fresh = confirmed & (self.confirmed == 0)
        # Modelled pixels learn only while they still match: a pixel under something never does.
        rate = np.where(confirmed & ~fresh & (matches | ~modelled), np.float32(cfg.learn_rate), 0)
        rate = rate.astype(np.float32)
        gains = self._gain if not relearn else (1.0, 1.0)
        var_start = np.float32(cfg.match_min_gray**2 / cfg.match_sigmas**2)
        for side, image in ((0, left), (1, warped)):
            normalised = image * np.float32(1.0 / max(gains[side], 1e-3))
            mean, var = self.mean[side], self.var[side]
            delta = normalised - mean
            mean += rate * delta
            var += rate * (delta * delta - var)
            np.copyto(mean, normalised, where=fresh)
            np.copyto(var, var_start, where=fresh)
        self.confirmed += (confirmed & (self.confirmed < 255)).view(np.uint8)
