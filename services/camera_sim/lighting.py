"""The site's light level over time, and how far behind it auto-exposure runs.

A pure function of the frame time (seconds since the epoch), so every sim process and ``sim/truth``
agree on when the lights changed without talking to each other.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

DRIFT_PERIOD_S = 40.0
"""Slow cycle between 60 % and 100 % of the light, as daylight through windows."""
STEP_LEVEL = 0.5
"""Half the luminaires off: the light's mean over the floor."""
LUMINAIRE_HEIGHT_M = 7.5
LUMINAIRE_SPACING_M = 3.0
"""High-bay luminaires on a grid about this far apart, this high over the floor (above the
cameras); a step switches off the circuit over one half of the hall (the rows below half the
floor's length), so the light falls off across the floor rather than by one factor everywhere:
a camera over the dark half keeps about 0.38 of its view's light, one over the lit half 0.6, and
auto-exposure's lag (:meth:`Lighting.lag_ratio`) follows each camera's own step."""


@dataclass(frozen=True)
class Lighting:
    drift: bool = False
    step_period_s: float = 0.0
    """Lights switch: half of them are off in the second half of every period (0: never)."""

    def __post_init__(self) -> None:
        if self.step_period_s < 0 or not math.isfinite(self.step_period_s):
            raise ValueError(f"step period must be ≥ 0 s, got {self.step_period_s}")

    def _drift(self, t_s: float) -> float:
        return 0.8 + 0.2 * math.sin(2 * math.pi * t_s / DRIFT_PERIOD_S) if self.drift else 1.0

    def _switched(self, t_s: float) -> float:
        if not self.step_period_s:
            return 1.0
        return STEP_LEVEL if math.fmod(t_s, self.step_period_s) >= self.step_period_s / 2 else 1.0

    def level(self, t_s: float) -> float:
        """Light at ``t_s`` relative to nominal, its mean over the floor."""
        return self._drift(t_s) * self._switched(t_s)

    def drift_level(self, t_s: float) -> float:
        """The light every luminaire gives at ``t_s`` (the daylight's drift), relative to nominal."""
        return self._drift(t_s)

    def switched_off(self, t_s: float) -> bool:
        """One half's circuit is off at ``t_s`` (:func:`switched_share` says where it is dark)."""
        return self._switched(t_s) < 1.0

    def steps_s(self, start_s: float, end_s: float) -> list[float]:
        """Times of the switching steps in [start_s, end_s)."""
        if not self.step_period_s:
            return []
        half = self.step_period_s / 2
        first = math.ceil(start_s / half)
        return [k * half for k in range(first, math.ceil(end_s / half)) if k * half < end_s]

    def lag_ratio(
        self, t_s: float, time_constant_s: float, switched_level: float = STEP_LEVEL
    ) -> float:
        """Light now over the light auto-exposure has converged to, for a camera whose view keeps
        ``switched_level`` of its light while the circuit is off (its mean
        :func:`switched_share`; the hall's, 0.5, by default).

        Auto-exposure follows the slow drift; after a step it converges exponentially, so its level
        is the new one plus the step's size decaying with ``time_constant_s``. The last two steps
        suffice: older ones have decayed by e^(-period/2τ)."""
        if not self.step_period_s or time_constant_s <= 0:
            return 1.0

        def light(t_s: float) -> float:
            return switched_level if self.switched_off(t_s) else 1.0

        half = self.step_period_s / 2
        now = converged = light(t_s)
        for step_s in self.steps_s(t_s - 2 * half, t_s + 1e-9):
            before = light(step_s - 1e-6 * half)
            converged += (before - light(step_s)) * math.exp(-(t_s - step_s) / time_constant_s)
        return now / converged


def switched_share(
    points_xy_m: npt.NDArray[np.float64], floor_size_m: tuple[float, float]
) -> npt.NDArray[np.float64]:
    """The light at floor points with one half's circuit off, over the light with all on: point
    luminaires (illuminance h / d³, inverse square and cosine) in an even number of rows along
    x, centred on the floor, the first half of them off; 0.27–0.73 on the default floor, 0.5 on
    average on any floor (the rows are symmetric about its middle)."""
    length_m, width_m = floor_size_m
    rows = max(2, 2 * round(length_m / (2 * LUMINAIRE_SPACING_M)))
    xs = (np.arange(rows) + 0.5) * (length_m / rows)
    ys = np.arange(LUMINAIRE_SPACING_M / 2, width_m, LUMINAIRE_SPACING_M)
    if ys.size == 0:  # a floor narrower than half the spacing: one luminaire across
        ys = np.array([width_m / 2])
    on = np.zeros(points_xy_m.shape[:-1])
    every = np.zeros(points_xy_m.shape[:-1])
    for row, x in enumerate(xs):
        for y in ys:
            squared = (
                (points_xy_m[..., 0] - x) ** 2
                + (points_xy_m[..., 1] - y) ** 2
                + LUMINAIRE_HEIGHT_M**2
            )
            light = LUMINAIRE_HEIGHT_M / squared**1.5
            every += light
            if row >= rows // 2:
                on += light
    share: npt.NDArray[np.float64] = on / every
    return share
