"""What a real camera does to the light a render gives: optics, exposure, sensor noise, 8 bits.

The render is taken as relative scene radiance (1.0 = a white surface under the site's nominal
light). A camera then applies, in order (EMVA 1288's linear camera model):

1. optics: vignetting (a fraction of the cos⁴ natural fall-off) and a Gaussian blur (lens + pixel);
2. auto-exposure: the exposure (then analog gain, once exposure is at its limit) that brings the
   frame's mean to a target, converging with a time constant after a lighting change;
3. the sensor: electrons = radiance · exposure, times a fixed per-pixel gain (PRNU); photon shot
   noise (Poisson, drawn as its Gaussian limit) and read noise; then gain, clipping and 8-bit
   quantisation.

Every random draw is seeded by (seed, camera, frame stamp), so a frame is a pure function of the
render, the frame time, the camera and the seed: tests are reproducible and several sim processes
agree. Defaults are those of a 1/3" global-shutter industrial camera (≈10 ke⁻ full well, ≈3 e⁻
read noise).
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass

import numpy as np

from common.arrays import F32, U8

DN_MAX = 255.0


@dataclass(frozen=True)
class SensorParams:
    full_well_e: float = 10_000.0
    read_noise_e: float = 3.0
    prnu_pct: float = 0.5
    """Photo-response non-uniformity: a fixed per-pixel gain spread (σ, % of signal)."""
    blur_sigma_px: float = 0.6
    vignetting: float = 0.4
    """Share of the natural cos⁴ fall-off left after the lens' correction (0: none)."""
    ae_target_dn: float = 110.0
    """Auto-exposure brings the frame's mean to this level."""
    ae_time_constant_s: float = 0.6
    """How fast auto-exposure follows a lighting change (exponential convergence)."""
    white_e_at_max_exposure: float = 20_000.0
    """Electrons a white surface under nominal light gives at the longest exposure the frame rate
    allows; past that, auto-exposure adds analog gain (noise grows with it)."""
    max_gain: float = 16.0

    def __post_init__(self) -> None:
        if min(self.full_well_e, self.white_e_at_max_exposure, self.ae_target_dn) <= 0:
            raise ValueError("full well, white level and exposure target must be positive")
        if min(self.read_noise_e, self.prnu_pct, self.blur_sigma_px, self.vignetting) < 0:
            raise ValueError("noise, blur and vignetting must not be negative")
        if self.max_gain < 1:
            raise ValueError(f"max_gain must be at least 1, got {self.max_gain}")


def frame_rng(seed: int, camera: str, stamp_ns: int) -> np.random.Generator:
    """The random stream of one camera's frame: the same inputs give the same noise."""
    return np.random.default_rng([seed & 0xFFFFFFFF, zlib.crc32(camera.encode()), stamp_ns])


def vignetting_gain(width: int, height: int, focal_px: float, strength: float) -> F32:
    """Per-pixel transmission: 1 − strength·(1 − cos⁴θ), θ the angle off the optical axis."""
    u = np.arange(width, dtype=np.float64) - (width - 1) / 2
    v = np.arange(height, dtype=np.float64) - (height - 1) / 2
    tan2 = (u[None, :] ** 2 + v[:, None] ** 2) / focal_px**2
    cos4 = 1.0 / (1.0 + tan2) ** 2
    gain: F32 = (1.0 - strength * (1.0 - cos4)).astype(np.float32)
    return gain


def gaussian_blur(image: F32, sigma_px: float) -> F32:
    """Separable Gaussian blur with replicated borders, in numpy (the sim install has no OpenCV)."""
    if sigma_px <= 0:
        return image
    radius = max(1, math.ceil(3 * sigma_px))
    taps = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sigma_px) ** 2)
    taps = (taps / taps.sum()).astype(np.float32)
    out = image
    for axis in (0, 1):
        padded = np.pad(out, [(radius, radius) if a == axis else (0, 0) for a in (0, 1)], "edge")
        length = out.shape[axis]
        acc = np.zeros_like(out)
        for k, tap in enumerate(taps):
            acc += tap * (padded[k : k + length] if axis == 0 else padded[:, k : k + length])
        out = acc
    return out


@dataclass(frozen=True)
class Exposure:
    """One frame's exposure: electrons per unit radiance, and the analog gain after it."""

    electrons_per_radiance: float
    gain: float


def auto_exposure(mean_radiance: float, light_lag_ratio: float, params: SensorParams) -> Exposure:
    """Exposure that maps ``mean_radiance`` to the target, off by ``light_lag_ratio`` (the light's
    level now over the level auto-exposure has converged to: 1 when settled, just after half the
    luminaires go off the share of its view's light the camera keeps, 0.38 over the dark half)."""
    target_e = params.ae_target_dn / DN_MAX * params.full_well_e
    wanted = target_e / max(mean_radiance, 1e-6) * light_lag_ratio
    exposure = min(wanted, params.white_e_at_max_exposure)
    gain = min(max(wanted / exposure, 1.0), params.max_gain)
    return Exposure(electrons_per_radiance=exposure, gain=gain)


class CameraSensor:
    """One physical camera: its fixed-pattern response and its frame-by-frame capture."""

    def __init__(
        self, name: str, width: int, height: int, focal_px: float, params: SensorParams, seed: int
    ) -> None:
        self.name = name
        self.params = params
        self.seed = seed
        fixed = np.random.default_rng([seed & 0xFFFFFFFF, zlib.crc32(name.encode()), 0])
        prnu = 1.0 + params.prnu_pct / 100.0 * fixed.standard_normal((height, width))
        self._response = (
            vignetting_gain(width, height, focal_px, params.vignetting) * prnu
        ).astype(np.float32)

    def capture(self, radiance: F32, stamp_ns: int, light_lag_ratio: float = 1.0) -> U8:
        """The 8-bit frame this camera gives of ``radiance`` (relative, H×W) at ``stamp_ns``."""
        p = self.params
        optical = gaussian_blur(radiance * self._response, p.blur_sigma_px)
        exposure = auto_exposure(float(optical.mean()), light_lag_ratio, p)
        electrons = np.minimum(optical * np.float32(exposure.electrons_per_radiance), p.full_well_e)
        noise_sigma_e = np.sqrt(electrons + np.float32(p.read_noise_e**2))
        rng = frame_rng(self.seed, self.name, stamp_ns)
        electrons += noise_sigma_e * rng.standard_normal(electrons.shape, dtype=np.float32)
        dn = electrons * np.float32(exposure.gain * DN_MAX / p.full_well_e)
        frame: U8 = np.clip(np.rint(dn), 0, DN_MAX).astype(np.uint8)
        return frame
