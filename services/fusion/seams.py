"""Pieces of one object that a seam's blind gap keeps apart.

Two pairs' views overlap on the floor but shrink toward the ceiling, so a tall object at a seam
can have part of its top in neither view: each pair sees a piece cut by its image's border, with
a gap between the pieces that no pair saw. Two objects side by side at a seam mostly leave floor
between them that some camera sees free; one object leaves none. So two cut pieces of different
pairs, as high as each other, on measured ground (:func:`measured`), whose gap holds few free
cells of the map's evidence, are one object (:func:`one_object_across`, :func:`seam_groups`).
Two objects whose floor between no camera sees are joined too: the object list then says one,
where a planner could not have driven between them without knowing that floor free.

Pure numpy: the map's evidence comes in as a :class:`MapEvidence` (``FusedGrid``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from common.arrays import F64, Mask
from common.footprints import (
    convex_hull,
    corners,
    fit_rectangle,
    polygon_cells,
    polygons_overlap,
)
from common.lattice import Window
from common.messages import TrackedObject


class MapEvidence(Protocol):
    """The frames' evidence over a window of the map, not the served layers (``FusedGrid``)."""

    @property
    def resolution_m(self) -> float: ...

    def occupied_in(self, window: Window) -> Mask: ...

    def free_in(self, window: Window) -> Mask: ...


@dataclass(frozen=True)
class SeamConfig:
    reach_m: float = 1.5
    """The widest gap joined, as the separating-axis gap between the pieces' outlines. Offline
    (20 s), the gaps of tall objects at the default rig's seams: a 0.68 m box's 0.3 m (``--seed
    2``), a 1.6 m shelf's 1.2 m (``--seed 4``)."""
    top_share: float = 0.15
    """The pieces' tops differ by at most this share of the higher one (or ``top_min_m``)."""
    top_min_m: float = 0.15
    """... or by this: a piece's top is where its points end, a few centimetres either way."""
    covered_share: float = 0.5
    """At least this share of each view's cells is occupied in the map's evidence: the gap is
    judged on measured ground (not on an empty map at start-up, nor beyond its bounds, where
    every cell is unknown)."""
    free_share: float = 0.35
    """At most this share of the gap's cells may read free: floor beside the object that the
    pieces' footprints, fitted along an aslant cut, take in, or seen past a noisy rim. Offline,
    every capture over 30–60 s: a 0.68 m box's gap (``--seed 2``) 7–26 % free, a 1.6 m shelf's
    (``--seed 4``) 0 %; the gaps between distinct objects passing the other tests 60–93 %."""
    max_length_m: float = 3.0
    """The longest object joined (a rack, a truck), measured on the rectangle around the pieces:
    longer, a row of distinct objects at a seam chains into one, and a wall's pieces, one per
    pair along it, into a wall (no object: fusion outlines nothing over ``max_size_m``)."""


@dataclass(frozen=True)
class SeamView:
    """A partial view of a standing object (a track's footprint), or a group of them: the pairs
    that saw it, its footprint (a convex counter-clockwise polygon, N × 2) and its top's height."""

    pairs: frozenset[str]
    polygon_m: F64
    top_m: float

    @staticmethod
    def around(views: list[SeamView]) -> SeamView:
        """The group of ``views``: their pairs, the hull of their footprints, the highest top."""
        return SeamView(
            frozenset().union(*(v.pairs for v in views)),
            convex_hull(np.vstack([v.polygon_m for v in views])),
            max(v.top_m for v in views),
        )


def gap_cells(a_m: F64, b_m: F64, resolution_m: float) -> tuple[Window, Mask]:
    """The cells between two convex polygons: their hull's cells less their own."""
    window, between = polygon_cells(convex_hull(np.vstack([a_m, b_m])), resolution_m)
    for polygon in (a_m, b_m):
        own_window, own = polygon_cells(polygon, resolution_m)
        part = own_window.intersect(window)
        if not part.empty:
            between[part.slices_in(window)] &= ~own[part.slices_in(own_window)]
    return window, between


def measured(polygon_m: F64, cells: MapEvidence, config: SeamConfig) -> bool:
    """Whether the map's evidence calls ``covered_share`` or more of a view's cells (a convex
    polygon's) occupied: a gap is judged on measured ground. A view longer than √2 ×
    ``max_length_m`` is not, and its cells are not looked at (a forged 2 km view asked for tens
    of GiB): no rectangle ``max_length_m`` long holds it (the diagonal would), so it joins
    nothing (:func:`one_object_across`)."""
    if len(polygon_m) < 3 or fit_rectangle(polygon_m)[2] > math.sqrt(2) * config.max_length_m:
        return False
    window, own = polygon_cells(polygon_m, cells.resolution_m)
    count = int(np.count_nonzero(own))
    occupied = int(np.count_nonzero(cells.occupied_in(window) & own))
    return count > 0 and occupied >= config.covered_share * count


def one_object_across(a: SeamView, b: SeamView, cells: MapEvidence, config: SeamConfig) -> bool:
    """Whether two cut pieces (each :func:`measured`) are one object across a seam's gap: seen
    by different pairs (one pair's pieces are apart in its own view), within ``reach_m`` of each
    other, as high, together no longer than ``max_length_m``, with cells between them (pieces
    with none are one object already, or none), at most ``free_share`` of them seen free."""
    if a.pairs & b.pairs:
        return False
    higher = max(a.top_m, b.top_m)
    if abs(a.top_m - b.top_m) > max(config.top_min_m, config.top_share * higher):
        return False
    if not polygons_overlap(a.polygon_m, b.polygon_m, config.reach_m):
        return False
    if fit_rectangle(np.vstack([a.polygon_m, b.polygon_m]))[2] > config.max_length_m:
        return False
    window, between = gap_cells(a.polygon_m, b.polygon_m, cells.resolution_m)
    gap = int(np.count_nonzero(between))
    free = int(np.count_nonzero(cells.free_in(window) & between))
    return gap > 0 and free <= config.free_share * gap


def seam_groups(views: list[SeamView], cells: MapEvidence, config: SeamConfig) -> list[list[int]]:
    """The views grouped into objects across seams' gaps (indices; a view alone, a group of
    one): each view :func:`measured` in the map, joins nearest first, each judged
    (:func:`one_object_across`) on the groups as joined so far."""
    measured_views = [measured(view.polygon_m, cells, config) for view in views]
    groups = [[k] for k, ok in enumerate(measured_views) if ok]
    alone = [[k] for k, ok in enumerate(measured_views) if not ok]
    pieces = [views[k] for k, ok in enumerate(measured_views) if ok]
    judged: dict[tuple[int, int], float | None] = {}  # by the groups' first views
    while True:
        found = []
        for i, a in enumerate(groups):
            for j, b in enumerate(groups[i + 1 :], i + 1):
                key = (a[0], b[0])
                if key not in judged:
                    one = one_object_across(pieces[i], pieces[j], cells, config)
                    gap_m = pieces[i].polygon_m.mean(axis=0) - pieces[j].polygon_m.mean(axis=0)
                    judged[key] = float(np.linalg.norm(gap_m)) if one else None
                distance = judged[key]
                if distance is not None:
                    found.append((distance, i, j))
        if not found:
            return groups + alone
        _, i, j = min(found)
        groups[i] = groups[i] + groups.pop(j)
        pieces.pop(j)
        pieces[i] = SeamView.around([views[k] for k in groups[i]])
        judged = {key: d for key, d in judged.items() if groups[i][0] not in key}


def join_across_seams(
    objects: list[TrackedObject], cells: MapEvidence, config: SeamConfig
) -> list[TrackedObject]:
    """The objects with static partial ones a seam's gap keeps apart (:func:`seam_groups`) joined
    into one: the rectangle around their footprints, the oldest one's id, ``partial``. The list
    alone: the map keeps each piece's outline, as measured (its cells, joined, paid: offline
    ``--seed 2`` IoU −0.005, live −0.011 over four runs)."""
    candidates = [o for o in objects if o.object_class == "static" and o.partial]
    views = [
        SeamView(frozenset(o.pairs), corners(o.center_m, o.size_m, o.yaw_rad), o.top_m)
        for o in candidates
    ]
    joined = [group for group in seam_groups(views, cells, config) if len(group) > 1]
    if not joined:
        return objects
    gone = {candidates[k].id for group in joined for k in group}
    out = [o for o in objects if o.id not in gone]
    for group in joined:
        members = [candidates[k] for k in group]
        around = SeamView.around([views[k] for k in group])
        cx, cy, length, width, yaw = fit_rectangle(around.polygon_m)
        first = min(members, key=lambda o: (o.first_seen_ns, o.id))
        out.append(
            first.model_copy(
                update={
                    "center_m": (cx, cy),
                    "size_m": (length, width),
                    "yaw_rad": yaw,
                    "top_m": around.top_m,
                    "last_seen_ns": max(o.last_seen_ns for o in members),
                    "pairs": sorted(around.pairs),
                    "size_unsure": any(o.size_unsure for o in members),
                    "round": False,
                    "detections": max(o.detections for o in members),
                }
            )
        )
    return sorted(out, key=lambda o: o.id)
