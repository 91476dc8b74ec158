"""The floor model's parameters (:class:`FloorModelConfig`): declared once, nested in the depth
settings, read by the floor model and its floor test."""

from __future__ import annotations

from dataclasses import dataclass


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
    """The model reports *ready* once this share of the image is modelled …"""
    no_floor_frames: int = 40
    no_floor_share: float = 0.01
    """… and *no_floor* when after ``no_floor_frames`` frames under this share is: left and right
    swapped, or a calibration not this pair's (renders, 24 frames: 0.00–0.04 % modelled so, 65–85 %
    right, on concrete and on a plain floor)."""
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
