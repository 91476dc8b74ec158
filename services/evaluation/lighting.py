"""The map's quality over a run, from maps recorded along it: the means after start-up, and
around a lighting step (before it, while cameras and models adapt, after).

Pure: takes a timeline of (capture time, cell scores) already computed, and the step instants.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from services.evaluation.metrics import CellScores

BEFORE_S = 10.0
"""Samples up to this long before a step describe the map before it."""
DURING_S = 3.0
"""Auto-exposure settles within about 5 time constants (0.6 s): samples this long after a step
are "during" it; the next ones, until the next step, "after"."""
UNKNOWN_EXCESS = 0.02
"""Unknown share of the seen floor away from the movers (``unknown_fraction_still``) above its
pre-step level that counts as "turned unknown"."""


@dataclass(frozen=True)
class TimelineScore:
    """One recorded map scored against the truth at its own capture time."""

    stamp_s: float
    iou: float
    false_free_rate_static: float
    unknown_fraction: float
    precision: float
    recall: float
    false_free_rate: float
    unknown_fraction_still: float
    """The unknown share of the floor away from the movers (metrics.unknown_away_from_movers)."""

    @staticmethod
    def of(
        stamp_s: float, scores: CellScores, static: CellScores, unknown_fraction_still: float
    ) -> TimelineScore:
        """A map's scores against the truth (``scores``) and its static objects (``static``)."""
        return TimelineScore(
            stamp_s,
            scores.iou,
            static.false_free_rate,
            scores.unknown_fraction,
            scores.precision,
            scores.recall,
            scores.false_free_rate,
            unknown_fraction_still,
        )


RUN_WARMUP_SHARE = 1 / 3
"""The first third of a run's recorded maps is start-up (the floor model learning, tracks
forming), as ``bench/map_accuracy.py`` skips it."""


def over_run(timeline: Sequence[TimelineScore]) -> dict[str, float]:
    """The mean scores of the recorded maps after the first third of the run. One snapshot is
    decided by where the movers happen to be at its instant: a mover the newest capture's pair
    saw a frame late reads wholly free, and single live runs of one code gave IoU 0.74–0.84."""
    ordered = sorted(timeline, key=lambda s: s.stamp_s)
    kept = ordered[int(len(ordered) * RUN_WARMUP_SHARE) :]
    return {
        "maps": len(kept),
        **{
            name: _mean([getattr(s, name) for s in kept])
            for name in (
                "iou",
                "precision",
                "recall",
                "false_free_rate",
                "false_free_rate_static",
                "unknown_fraction",
            )
        },
    }


def _mean(values: Sequence[float]) -> float:
    finite = [v for v in values if math.isfinite(v)]
    return float(np.mean(finite)) if finite else math.nan


def _phase(scores: Sequence[TimelineScore]) -> dict[str, float]:
    return {
        "samples": len(scores),
        "iou": _mean([s.iou for s in scores]),
        "false_free_rate_static": _mean([s.false_free_rate_static for s in scores]),
        "false_free_rate_static_max": max(
            (s.false_free_rate_static for s in scores), default=math.nan
        ),
        "unknown_fraction": _mean([s.unknown_fraction for s in scores]),
        "unknown_fraction_still": _mean([s.unknown_fraction_still for s in scores]),
    }


def step_phases(
    steps_s: Sequence[float], timeline: Sequence[TimelineScore]
) -> list[dict[str, Any]]:
    """Per step with samples on both sides: the phases' mean scores, the IoU drop (before minus the
    worse of during and after) and until when after it the unknown share of the floor away from
    the movers stood above its level before (its last sample there)."""
    out = []
    ordered = sorted(steps_s)
    for index, step_s in enumerate(ordered):
        end_s = ordered[index + 1] if index + 1 < len(ordered) else math.inf
        start_s = max(step_s - BEFORE_S, ordered[index - 1] if index else -math.inf)
        before = [s for s in timeline if start_s <= s.stamp_s < step_s]
        during = [s for s in timeline if step_s <= s.stamp_s < min(step_s + DURING_S, end_s)]
        after = [s for s in timeline if step_s + DURING_S <= s.stamp_s < end_s]
        if not before or not (during or after):
            continue
        phases = {"before": _phase(before), "during": _phase(during), "after": _phase(after)}
        # On the floor away from the movers: their occlusion shadows come and go on their own.
        baseline = phases["before"]["unknown_fraction_still"]
        excess = [
            s.stamp_s
            for s in during + after
            if s.unknown_fraction_still > baseline + UNKNOWN_EXCESS
        ]
        worst_iou = min(
            v for v in (phases["during"]["iou"], phases["after"]["iou"]) if not math.isnan(v)
        )
        out.append(
            {
                "step_s": step_s,
                **phases,
                "iou_drop": phases["before"]["iou"] - worst_iou,
                "unknown_excess_s": (max(excess) - step_s) if excess else 0.0,
            }
        )
    return out
