"""How good ``map/objects`` is against ground truth: static objects' sizes (found once, no splits,
no merges), movers' velocities and identity over time. Pure: scores lists of objects."""

from __future__ import annotations

import math
from collections.abc import Collection, Sequence
from dataclasses import dataclass

import numpy as np

from common.arrays import Mask
from common.footprints import footprint_polygon
from common.lattice import Window
from common.messages import TrackedObject, TruthObject
from services.camera_sim.truth import footprint_mask
from services.evaluation.metrics import OBSTACLE_BAND_M, true_extent

MATCH_MARGIN_M = 0.15
"""A track belongs to a truth object whose footprint, grown by this, holds the track's centre."""
MOVER_MATCH_M = 1.0
"""A moving track within this of a mover's true centre is taken as that mover."""


def _inside(obj: TruthObject, xy_m: tuple[float, float], margin_m: float) -> bool:
    dx, dy = xy_m[0] - obj.center_m[0], xy_m[1] - obj.center_m[1]
    if obj.shape == "cylinder":
        return math.hypot(dx, dy) <= obj.size_m[0] / 2 + margin_m
    c, s = math.cos(obj.yaw_rad), math.sin(obj.yaw_rad)
    along, across = c * dx + s * dy, -s * dx + c * dy
    return (
        abs(along) <= obj.size_m[0] / 2 + margin_m and abs(across) <= obj.size_m[1] / 2 + margin_m
    )


@dataclass(frozen=True)
class ObjectMatch:
    name: str
    true_length_m: float
    true_width_m: float
    tracks: int
    """Tracks matched to it: 1 is right, 0 missed, more a split."""
    length_m: float
    width_m: float
    partial: bool
    unsure: bool
    """Its size is a lower bound (``partial``) or the median of views that disagree."""
    merged: bool
    """Its track's footprint also covers another object's centre."""

    @property
    def errors_pct(self) -> tuple[float, float]:
        return (
            100 * abs(self.length_m - self.true_length_m) / self.true_length_m,
            100 * abs(self.width_m - self.true_width_m) / self.true_width_m,
        )


def blocking_static(
    objects: Sequence[TruthObject], floor_size_m: tuple[float, float]
) -> list[TruthObject]:
    """The static objects a map should show: on the floor (not its walls), tall enough to block."""
    return [
        obj
        for obj in objects
        if not obj.moving
        and 0 <= obj.center_m[0] <= floor_size_m[0]
        and 0 <= obj.center_m[1] <= floor_size_m[1]
        and obj.top_m >= OBSTACLE_BAND_M[0]
    ]


def match_static(
    tracks: Sequence[TrackedObject], truth: Sequence[TruthObject]
) -> list[ObjectMatch]:
    """Each static truth object with the tracks whose centres lie on it; the one seen most often
    gives the size."""
    out = []
    for obj in truth:
        mine = [t for t in tracks if _inside(obj, t.center_m, MATCH_MARGIN_M)]
        length_true, width_true = true_extent(obj)
        if not mine:
            out.append(
                ObjectMatch(obj.name, length_true, width_true, 0, 0.0, 0.0, False, False, False)
            )
            continue
        best = max(mine, key=lambda t: t.detections)
        polygon = footprint_polygon(best.center_m, best.size_m, best.yaw_rad, best.round)
        others = [o for o in truth if o is not obj]
        merged = any(_in_polygon(polygon, (o.center_m[0], o.center_m[1])) for o in others)
        out.append(
            ObjectMatch(
                obj.name,
                length_true,
                width_true,
                len(mine),
                best.size_m[0],
                best.size_m[1],
                best.partial,
                best.size_unsure,
                merged,
            )
        )
    return out


def size_errors(
    matches: Sequence[ObjectMatch], in_view: Collection[str] = frozenset()
) -> dict[str, float]:
    """The headline size figures over the objects found: mean and max of their length and width
    errors (%), over all of them, over those measured with confidence (``_complete``: seen
    whole, by views that agree; neither ``partial`` nor ``size_unsure``), and over those found
    whose top lies wholly in the cameras' views (``_in_view``, names from :func:`seen_whole`: the
    others no camera can measure whole, whatever the tracker says of them), and how many those
    are."""
    found = [m for m in matches if m.tracks >= 1]
    errors = [e for m in found for e in m.errors_pct]
    sure = [m for m in found if not (m.partial or m.unsure)]
    complete = [e for m in sure for e in m.errors_pct]
    viewed = [e for m in found if m.name in in_view for e in m.errors_pct]
    return {
        "objects_measured_sure": len(sure),
        "objects_in_view": sum(1 for m in found if m.name in in_view),
        "length_error_mean_pct": float(np.mean(errors)) if errors else math.nan,
        "length_error_max_pct": max(errors, default=math.nan),
        "length_error_mean_pct_complete": float(np.mean(complete)) if complete else math.nan,
        "length_error_max_pct_complete": max(complete, default=math.nan),
        "length_error_mean_pct_in_view": float(np.mean(viewed)) if viewed else math.nan,
        "length_error_max_pct_in_view": max(viewed, default=math.nan),
    }


def seen_whole(
    objects: Sequence[TruthObject], seen: Mask, window: Window, resolution_m: float
) -> set[str]:
    """Names of the objects every cell of whose footprint is ``seen`` (at its top's height:
    :func:`metrics.seen_by_cameras`, the union of the pairs' views, since fusion joins the parts
    that pairs see of one object): the ones whose size the cameras can measure whole."""
    masks = {obj.name: footprint_mask(obj, window, resolution_m) for obj in objects}
    return {name for name, mask in masks.items() if mask.any() and not (mask & ~seen).any()}


def _in_polygon(polygon: np.ndarray, xy_m: tuple[float, float]) -> bool:
    x, y = xy_m
    for (ax, ay), (bx, by) in zip(polygon, np.roll(polygon, -1, axis=0), strict=True):
        if (bx - ax) * (y - ay) - (by - ay) * (x - ax) < 0:
            return False
    return True


@dataclass(frozen=True)
class MoverScores:
    velocity_error_mps: list[float]
    id_switches: dict[str, int]
    tracked_share: dict[str, float]
    """Per mover, the share of object lists in which a moving track followed it."""
    phantom_share: float
    """The share of object lists holding a moving track that follows no mover (none within
    ``MOVER_MATCH_M``): a static object's pieces, or a wall's, taken for one that drives, which a
    fleet planner would steer around as if it came at it."""


def score_movers(
    history: Sequence[tuple[Sequence[TrackedObject], Sequence[TruthObject]]],
) -> MoverScores:
    """Over a sequence of (object list, truth at its stamp): per mover, the nearest moving track's
    velocity error and how often the track following it changed id; and how often a list holds
    a moving track no mover is near."""
    errors: list[float] = []
    last_id: dict[str, int] = {}
    switches: dict[str, int] = {}
    seen: dict[str, int] = {}
    total: dict[str, int] = {}
    phantom_lists = 0
    for tracks, truth in history:
        moving = [t for t in tracks if t.object_class == "moving"]
        movers = [obj for obj in truth if obj.moving]
        phantom_lists += any(
            all(math.dist(t.center_m, obj.center_m[:2]) > MOVER_MATCH_M for obj in movers)
            for t in moving
        )
        for obj in movers:
            total[obj.name] = total.get(obj.name, 0) + 1
            switches.setdefault(obj.name, 0)
            if not moving:
                continue
            nearest = min(
                moving,
                key=lambda t: math.hypot(
                    t.center_m[0] - obj.center_m[0], t.center_m[1] - obj.center_m[1]
                ),
            )
            distance = math.hypot(
                nearest.center_m[0] - obj.center_m[0], nearest.center_m[1] - obj.center_m[1]
            )
            if distance > MOVER_MATCH_M:
                continue
            seen[obj.name] = seen.get(obj.name, 0) + 1
            errors.append(
                math.hypot(
                    nearest.velocity_mps[0] - obj.velocity_mps[0],
                    nearest.velocity_mps[1] - obj.velocity_mps[1],
                )
            )
            if obj.name in last_id and last_id[obj.name] != nearest.id:
                switches[obj.name] += 1
            last_id[obj.name] = nearest.id
    return MoverScores(
        errors,
        switches,
        {name: seen.get(name, 0) / n for name, n in total.items() if n},
        phantom_lists / len(history) if history else 0.0,
    )
