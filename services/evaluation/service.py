"""``overgrid eval``: score a running system's map against the simulator's ground truth.

It asks ``sim/truth`` for the scene at the map's capture time and ``cam/*/calib`` for what the
cameras can see, watches ``map/updates`` and ``depth/*/tile`` for a while (movers, latencies), and
reports a table or JSON. ``overgrid up`` runs the same :class:`Recorder` and :func:`report`.
"""

from __future__ import annotations

import json
import math
import sys
import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt
import zenoh
from pydantic import Field
from pydantic_settings import SettingsConfigDict

from common import keys
from common.client import (
    MAX_TIMEOUT_S,
    MapFollower,
    MapUnavailable,
    calibrations,
    latest,
    query_first,
)
from common.client import objects as query_objects
from common.codec import CodecError, decode
from common.lattice import Window
from common.lifecycle import stop_on_signals
from common.mapfiles import OCCUPIED_MIN
from common.messages import (
    OBJECTS_KIND,
    TILE_KIND,
    TRUTH_KIND,
    ObjectsHeader,
    TileHeader,
    TrackedObject,
    TruthHeader,
    TruthObject,
)
from common.occupancy_map import OccupancyMap
from common.settings import ZenohSettings, parse_settings
from common.zenoh_session import open_session
from services.camera_sim import truth as scene_truth
from services.camera_sim.truth import footprint_mask, top_heights
from services.evaluation import metrics
from services.evaluation import objects as object_scores
from services.evaluation.lighting import TimelineScore, over_run, step_phases
from services.evaluation.metrics import OBSTACLE_BAND_M

MAX_RECORD_S = 120.0
"""The recorder keeps this much history: a long ``up`` run is scored on its last two minutes."""


def per_minute(counts: dict[str, int], object_lists: Sequence[ObjectsHeader]) -> dict[str, float]:
    """Counts over the recorded object lists, per minute of the time they span (a long run's
    switches were counted over its last two minutes and divided by the whole run)."""
    span_s = (object_lists[-1].stamp_ns - object_lists[0].stamp_ns) / 1e9 if object_lists else 0.0
    minutes = max(span_s, 1.0) / 60.0
    return {name: n / minutes for name, n in counts.items()}


TIMELINE_PERIOD_S = 0.5
MOVER_TRUTH_RESOLUTION_M = 1.0
"""Movers are scored on the truth's object list; its raster is not used, so it is asked coarse."""
"""The recorder keeps the whole map this often, to score it over time (lighting steps)."""

TARGETS = {
    "iou": (">=", 0.90),
    "false_free_rate": ("<=", 0.005),
    "length_error_mean_pct": ("<=", 2.0),
    "length_error_max_pct": ("<=", 5.0),
    "unknown_fraction": ("<=", 0.05),
    "moving_appear_s": ("<=", 0.2),
    "moving_clear_s": ("<=", 1.0),
    "capture_to_map_p50_ms": ("<=", 50.0),
}


LIGHTING_IOU_DROP_MAX = 0.02


class EvalSettings(ZenohSettings):
    model_config = SettingsConfigDict(cli_shortcuts={"json-output": "json"})  # BaseModel has .json

    watch_s: float = Field(
        10.0, ge=0.0, le=MAX_RECORD_S, description="watch the stream this long for latencies"
    )
    json_output: bool = Field(False, description="print JSON instead of a table")
    timeout_s: float = Field(
        10.0, gt=0.0, le=MAX_TIMEOUT_S, description="wait this long for each service"
    )


@dataclass(frozen=True)
class Truth:
    header: TruthHeader
    occupied: npt.NDArray[np.bool_]


def query_truth(
    session: zenoh.Session, stamp_ns: int, resolution_m: float, timeout_s: float = 5.0
) -> Truth:
    selector = (
        f"{keys.SIM_TRUTH}?stamp_ns={stamp_ns};resolution={resolution_m:g};"
        f"band={OBSTACLE_BAND_M[0]:g},{OBSTACLE_BAND_M[1]:g}"
    )
    message = decode(query_first(session, selector, timeout_s), TRUTH_KIND, TruthHeader)
    return Truth(message.header, message.arrays["occupied"].astype(np.bool_))


@dataclass
class Recorder:
    """Watches ``map/updates`` (the map as clients see it, with arrival times) and the tiles (stamps,
    stage times, which cells each capture saw and how long its frame took to reach depth)."""

    session: zenoh.Session
    window: Window
    resolution_m: float
    samples: deque[tuple[metrics.MapSample, int]] = field(default_factory=deque)
    tiles: deque[tuple[float, TileHeader]] = field(default_factory=deque)
    camera_s: dict[int, npt.NDArray[np.float32]] = field(default_factory=dict)
    timeline: deque[tuple[int, npt.NDArray[np.int8]]] = field(default_factory=deque)
    """(capture stamp, occupancy on the window) every ``TIMELINE_PERIOD_S`` of arrivals."""
    object_lists: deque[ObjectsHeader] = field(default_factory=deque)
    """Every ``map/objects`` put: the tracks as they changed."""
    _lock: threading.Lock = field(default_factory=threading.Lock)
    _timeline_last_s: float = -math.inf

    def __post_init__(self) -> None:
        self.started_s = time.time()
        self._tiles = self.session.declare_subscriber(keys.TILES_ALL, self._on_tile)
        self._objects = self.session.declare_subscriber(keys.MAP_OBJECTS, self._on_objects)
        self._follower = MapFollower(self.session, on_change=self._on_map)

    def _on_map(self, occupancy_map: OccupancyMap, arrival_s: float) -> None:
        occupancy = metrics.occupancy_on(occupancy_map, self.window)
        occupied = occupancy >= OCCUPIED_MIN
        with self._lock:
            self.samples.append((metrics.MapSample(arrival_s, occupied), occupancy_map.stamp_ns))
            while self.samples and self.samples[0][0].visible_s < arrival_s - MAX_RECORD_S:
                self.samples.popleft()
            if arrival_s - self._timeline_last_s >= TIMELINE_PERIOD_S:
                self._timeline_last_s = arrival_s
                self.timeline.append((occupancy_map.stamp_ns, occupancy))
                while self.timeline and self.timeline[0][0] < (arrival_s - MAX_RECORD_S) * 1e9:
                    self.timeline.popleft()

    def _on_objects(self, sample: zenoh.Sample) -> None:
        try:
            header = decode(sample.payload.to_bytes(), OBJECTS_KIND, ObjectsHeader).header
        except CodecError:
            return
        with self._lock:
            self.object_lists.append(header)
            while (
                self.object_lists
                and self.object_lists[0].stamp_ns < header.stamp_ns - MAX_RECORD_S * 1e9
            ):
                self.object_lists.popleft()

    def _on_tile(self, sample: zenoh.Sample) -> None:
        arrival_s = time.time()
        try:
            message = decode(sample.payload.to_bytes(), TILE_KIND, TileHeader)
        except CodecError:
            return
        h = message.header
        part = h.window.intersect(self.window)
        if h.resolution_m != self.resolution_m or part.empty:
            return
        seen = message.arrays["count"][part.slices_in(h.window)] > 0
        camera_s = np.float32(h.stage_ms.get("camera", 0.0) / 1e3)
        with self._lock:
            self.tiles.append((arrival_s, h))
            per_cell = self.camera_s.setdefault(
                h.stamp_ns, np.full(self.window.shape, np.nan, np.float32)
            )
            view = per_cell[part.slices_in(self.window)]
            view[seen] = np.fmin(view[seen], camera_s)
            while self.tiles and self.tiles[0][0] < arrival_s - MAX_RECORD_S:
                self.tiles.popleft()
            for stamp in [s for s in self.camera_s if s < (arrival_s - MAX_RECORD_S) * 1e9]:
                del self.camera_s[stamp]

    def close(self) -> None:
        self._follower.close()
        self._tiles.undeclare()  # type: ignore[no-untyped-call]
        self._objects.undeclare()  # type: ignore[no-untyped-call]

    def snapshot(
        self,
    ) -> tuple[list[tuple[metrics.MapSample, int]], list[tuple[float, TileHeader]], dict[int, Any]]:
        with self._lock:
            return list(self.samples), list(self.tiles), dict(self.camera_s)

    def objects_snapshot(self) -> list[ObjectsHeader]:
        with self._lock:
            return list(self.object_lists)

    def timeline_snapshot(self) -> list[tuple[int, npt.NDArray[np.int8]]]:
        with self._lock:
            return list(self.timeline)


class Evaluator:
    """What stays fixed while the system runs: the lattice window of the scene, what the cameras
    see. Made once; scores any number of map snapshots."""

    def __init__(self, session: zenoh.Session, resolution_m: float, timeout_s: float) -> None:
        self.session = session
        self.resolution_m = resolution_m
        self.timeout_s = timeout_s
        first = query_truth(session, time.time_ns(), resolution_m, timeout_s)
        self.window = first.header.window
        self.floor_size_m = first.header.floor_size_m
        self.calibrations = calibrations(session, timeout_s)
        if not self.calibrations:
            raise MapUnavailable("no camera answered on cam/*/calib")
        static = [o for o in first.header.objects if not o.moving]
        self.seen = metrics.seen_by_cameras(
            self.calibrations,
            self.window,
            resolution_m,
            top_heights(static, self.window, resolution_m),
            blockers=static,
        )
        self.rig_coverage = metrics.coverage_by_height(
            self.calibrations, self.floor_size_m, resolution_m
        )
        """Share of the floor the rig sees at each height over the band (metrics.coverage_by_height)."""
        self.in_view = object_scores.seen_whole(
            object_scores.blocking_static(static, self.floor_size_m),
            self.seen,
            self.window,
            resolution_m,
        )
        """Static objects whose top the cameras see whole (their sizes are measurable)."""
        self.static_occupied = scene_truth.occupancy(
            static, self.window, resolution_m, OBSTACLE_BAND_M
        ).astype(np.bool_)
        """Truth of the objects that never move: made once, like the seen mask."""

    def truth(self, stamp_ns: int) -> Truth:
        return query_truth(self.session, stamp_ns, self.resolution_m, self.timeout_s)

    def scores(self, occupancy_map: OccupancyMap) -> tuple[metrics.CellScores, Truth]:
        truth = self.truth(occupancy_map.stamp_ns or time.time_ns())
        occupancy = metrics.occupancy_on(occupancy_map, self.window)
        return metrics.score_cells(occupancy, truth.occupied, self.seen), truth

    def static_false_free_rate(self, occupancy_map: OccupancyMap) -> float:
        """False-free over static objects alone: a mover's leading edge is free in the map until
        the next frame of a pair that sees it, which no sensor model can help at 2 Hz."""
        occupancy = metrics.occupancy_on(occupancy_map, self.window)
        return metrics.score_cells(occupancy, self.static_occupied, self.seen).false_free_rate

    def error_breakdown(self, occupancy_map: OccupancyMap, truth: Truth) -> dict[str, object]:
        """Where the map is wrong, by cause (metrics.error_breakdown), at the map's capture time."""
        return metrics.error_breakdown(
            metrics.occupancy_on(occupancy_map, self.window),
            truth.occupied,
            self.seen,
            truth.header.objects,
            self.window,
            self.resolution_m,
        )

    def static_cells(self, occupancy_map: OccupancyMap) -> dict[str, float]:
        """How the map calls the seen cells of static objects: occupied, free or unknown."""
        occupancy = metrics.occupancy_on(occupancy_map, self.window)
        return metrics.cell_shares(occupancy, self.static_occupied & self.seen)

    def timeline_scores(
        self, timeline: list[tuple[int, npt.NDArray[np.int8]]]
    ) -> list[TimelineScore]:
        """Each recorded map scored against the truth at its own capture time."""
        out = []
        for stamp_ns, occupancy in timeline:
            truth = self.truth(stamp_ns)
            scores = metrics.score_cells(occupancy, truth.occupied, self.seen)
            static = metrics.score_cells(occupancy, self.static_occupied, self.seen)
            out.append(
                TimelineScore.of(
                    stamp_ns / 1e9,
                    scores,
                    static,
                    metrics.unknown_away_from_movers(
                        occupancy,
                        truth.occupied,
                        self.seen,
                        truth.header.objects,
                        self.window,
                        self.resolution_m,
                    ),
                )
            )
        return out

    def static_objects(self, truth: Truth) -> list[TruthObject]:
        return object_scores.blocking_static(truth.header.objects, self.floor_size_m)

    def objects(self, occupancy_map: OccupancyMap, truth: Truth) -> list[metrics.ObjectSize]:
        occupied = metrics.occupancy_on(occupancy_map, self.window) >= OCCUPIED_MIN
        return [
            metrics.measure_object(occupied, self.window, self.resolution_m, obj)
            for obj in self.static_objects(truth)
        ]

    def tracked_objects(self, truth: Truth) -> dict[str, Any]:
        """``map/objects`` scored: static objects' sizes from their tracks (found once, no splits,
        no merges)."""
        try:
            tracks: list[TrackedObject] = list(query_objects(self.session, self.timeout_s).objects)
        except MapUnavailable:
            return {"length_error_mean_pct": math.nan, "length_error_max_pct": math.nan}
        static = [t for t in tracks if t.object_class == "static"]
        matches = object_scores.match_static(static, self.static_objects(truth))
        return {
            **object_scores.size_errors(matches, self.in_view),
            "tracked_objects": [
                {
                    "name": m.name,
                    "true_length_m": m.true_length_m,
                    "true_width_m": m.true_width_m,
                    "length_m": m.length_m if m.tracks else None,
                    "width_m": m.width_m if m.tracks else None,
                    "length_error_pct": m.errors_pct[0] if m.tracks else None,
                    "width_error_pct": m.errors_pct[1] if m.tracks else None,
                    "tracks": m.tracks,
                    "partial": m.partial,
                    "size_unsure": m.unsure,
                    "merged": m.merged,
                }
                for m in matches
            ],
            "objects_found_once": sum(1 for m in matches if m.tracks == 1 and not m.merged),
            "objects_static_truth": len(matches),
            "objects_split": [m.name for m in matches if m.tracks > 1],
            "objects_merged": [m.name for m in matches if m.merged],
            "objects_not_tracked": [m.name for m in matches if m.tracks == 0],
            "tracks_static": len(static),
            "tracks_moving": len(tracks) - len(static),
        }

    def mover_scores(self, object_lists: list[ObjectsHeader]) -> dict[str, Any]:
        """Movers' velocities and identities over every ``map/objects`` put recorded."""
        history = [
            (
                h.objects,
                query_truth(self.session, h.stamp_ns, MOVER_TRUTH_RESOLUTION_M).header.objects,
            )
            for h in object_lists
        ]
        scores = object_scores.score_movers(history)
        return {
            "velocity_error_mps": metrics.percentiles(scores.velocity_error_mps),
            "id_switches": per_minute(scores.id_switches, object_lists),
            "movers_tracked_share": scores.tracked_share,
            "phantom_movers_share": scores.phantom_share,
        }

    def ticks(self, camera_s: dict[int, npt.NDArray[np.float32]]) -> list[metrics.Tick]:
        ticks = []
        for stamp_ns in sorted(camera_s):
            movers = np.zeros(self.window.shape, np.bool_)
            for obj in self.truth(stamp_ns).header.objects:
                if obj.moving:
                    movers |= footprint_mask(obj, self.window, self.resolution_m)
            ticks.append(metrics.Tick(stamp_ns / 1e9, movers, camera_s[stamp_ns]))
        return ticks


def _capture_to_map_s(
    samples: list[tuple[metrics.MapSample, int]], tiles: list[tuple[float, TileHeader]]
) -> tuple[list[float], list[float]]:
    """Per tile: capture → the first map version at or after its arrival that includes its stamp;
    the same less the tile's camera time."""
    visible = np.array([s.visible_s for s, _ in samples])
    stamps = np.array([stamp for _, stamp in samples])
    total, excluding_camera = [], []
    for arrival_s, h in tiles:
        later = np.nonzero((visible >= arrival_s) & (stamps >= h.stamp_ns))[0]
        if later.size:
            latency = float(visible[later[0]]) - h.stamp_ns / 1e9
            total.append(latency)
            excluding_camera.append(latency - h.stage_ms.get("camera", 0.0) / 1e3)
    return total, excluding_camera


def _mean(values: Sequence[float]) -> float:
    return float(np.mean(values)) if values else math.nan


def map_summary(occupancy_map: OccupancyMap) -> dict[str, Any]:
    return {
        "version": occupancy_map.version,
        "stamp_ns": occupancy_map.stamp_ns,
        "resolution_m": occupancy_map.resolution_m,
        "origin_m": list(occupancy_map.origin_m),
        "cols": occupancy_map.window.cols,
        "rows": occupancy_map.window.rows,
        "pairs": occupancy_map.pairs,
    }


def report(
    evaluator: Evaluator, recorder: Recorder | None, occupancy_map: OccupancyMap | None = None
) -> dict[str, Any]:
    """Everything ``overgrid eval --json`` prints and ``report.json`` holds; scores
    ``occupancy_map`` if given, else the current map."""
    if occupancy_map is None:
        occupancy_map = latest(evaluator.session, timeout_s=evaluator.timeout_s)
    if occupancy_map.resolution_m != evaluator.resolution_m:
        raise MapUnavailable(
            f"map resolution {occupancy_map.resolution_m} m ≠ {evaluator.resolution_m} m"
        )
    scores, truth = evaluator.scores(occupancy_map)
    sizes = evaluator.objects(occupancy_map, truth)
    found = [s for s in sizes if s.found]
    errors_pct = [e for s in found for e in s.errors_pct]
    errors_m = [
        abs(a - b)
        for s in found
        for a, b in ((s.length_m, s.true_length_m), (s.width_m, s.true_width_m))
    ]
    out: dict[str, Any] = {
        "map": map_summary(occupancy_map),
        "iou": scores.iou,
        "precision": scores.precision,
        "recall": scores.recall,
        "false_free_rate": scores.false_free_rate,
        "false_free_rate_static": evaluator.static_false_free_rate(occupancy_map),
        "static_cells": evaluator.static_cells(occupancy_map),
        "unknown_fraction": scores.unknown_fraction,
        "seen_cells": int(evaluator.seen.sum()),
        "rig_coverage": evaluator.rig_coverage,
        "raster_length_error_mean_pct": _mean(errors_pct),
        "raster_length_error_max_pct": max(errors_pct, default=math.nan),
        "raster_length_error_mean_m": _mean(errors_m),
        "objects": [
            {
                "name": s.name,
                "true_length_m": s.true_length_m,
                "true_width_m": s.true_width_m,
                "length_m": s.length_m,
                "width_m": s.width_m,
                "length_error_pct": s.errors_pct[0] if s.found else None,
                "width_error_pct": s.errors_pct[1] if s.found else None,
            }
            for s in sizes
        ],
        "objects_missed": [s.name for s in sizes if not s.found],
        "error_breakdown": evaluator.error_breakdown(occupancy_map, truth),
        **evaluator.tracked_objects(truth),
    }
    if recorder is not None:
        samples, tiles, camera_s = recorder.snapshot()
        latencies = metrics.moving_latencies(evaluator.ticks(camera_s), [s for s, _ in samples])
        total, excluding_camera = _capture_to_map_s(samples, tiles)
        stages = sorted({name for _, h in tiles for name in h.stage_ms})
        appear, clear = (
            metrics.percentiles(latencies.appear_s),
            metrics.percentiles(latencies.clear_s),
        )
        out |= {
            "watched_s": round(time.time() - recorder.started_s, 1),
            "moving_appear_s": appear["p50"],
            "moving_clear_s": clear["p50"],
            "moving": {
                "appear_s": appear,
                "clear_s": clear,
                "missed_appear_cells": latencies.missed_appear,
                "missed_clear_cells": latencies.missed_clear,
            },
            "capture_to_map_ms": _ms(metrics.percentiles(total)),
            "capture_to_map_excl_camera_ms": _ms(metrics.percentiles(excluding_camera)),
            "stage_ms": {
                name: metrics.percentiles(
                    [h.stage_ms[name] for _, h in tiles if name in h.stage_ms]
                )
                for name in stages
            },
        }
        out["capture_to_map_p50_ms"] = out["capture_to_map_excl_camera_ms"]["p50"]
        # The recorder keeps the last MAX_RECORD_S: what it scores, a long run's end.
        out["scored_s"] = round(min(out["watched_s"], MAX_RECORD_S), 1)
        out |= evaluator.mover_scores(recorder.objects_snapshot())
        timeline = evaluator.timeline_scores(recorder.timeline_snapshot())
        out["over_run"] = over_run(timeline)
        if truth.header.light_steps_ns:
            steps_s = [t / 1e9 for t in truth.header.light_steps_ns]
            out["lighting_steps"] = step_phases(steps_s, timeline)
    out["targets"] = {
        name: {"value": out[name], "target": f"{op} {bound:g}", "met": _meets(out[name], op, bound)}
        for name, (op, bound) in TARGETS.items()
        if name in out
    }
    return out


def _ms(row: dict[str, float]) -> dict[str, float]:
    return {k: (v * 1e3 if k != "n" else v) for k, v in row.items()}


def _meets(value: float, op: str, bound: float) -> bool:
    if value is None or math.isnan(value):
        return False
    return value >= bound if op == ">=" else value <= bound


def table(result: dict[str, Any]) -> str:
    """The report as a person reads it."""
    lines = [
        f"map v{result['map']['version']}  {result['map']['cols']}×{result['map']['rows']} cells "
        f"@ {result['map']['resolution_m']} m  pairs {','.join(result['map']['pairs'])}",
        "",
        f"{'metric':<28}{'value':>12}  target",
    ]
    for name, row in result["targets"].items():
        mark = "ok" if row["met"] else "MISSED"
        lines.append(f"{name:<28}{row['value']:>12.4g}  {row['target']:<8} {mark}")
    lines.append(f"{'precision':<28}{result['precision']:>12.4g}")
    lines.append(f"{'recall':<28}{result['recall']:>12.4g}")
    lines.append(f"{'false_free_rate_static':<28}{result['false_free_rate_static']:>12.4g}")
    for name in ("raster_length_error_mean_pct", "raster_length_error_max_pct"):
        lines.append(f"{name:<28}{result[name]:>12.4g}")
    if "objects_measured_sure" in result:
        lines.append(
            f"{'length error, sure objects':<28}{result['length_error_mean_pct_complete']:>6.2f}"
            f"/{result['length_error_max_pct_complete']:<5.2f} % mean/max over "
            f"{result['objects_measured_sure']} (neither partial nor size unsure)"
        )
        lines.append(
            f"{'length error, in view':<28}{result['length_error_mean_pct_in_view']:>6.2f}"
            f"/{result['length_error_max_pct_in_view']:<5.2f} % mean/max over "
            f"{result['objects_in_view']} (tops wholly in the cameras' view)"
        )
    coverage = result["rig_coverage"]
    lines.append(
        f"{'rig sees, share of floor':<28}"
        + ", ".join(f"{share:.0%} at {height} m" for height, share in coverage.items())
    )
    if "over_run" in result:
        run = result["over_run"]
        lines += [
            "",
            f"over the run ({run['maps']} maps after the first third; the figures above are the "
            "last map's)",
            f"{'':<4}IoU {run['iou']:.4f}  precision {run['precision']:.4f}  recall "
            f"{run['recall']:.4f}  false-free {run['false_free_rate']:.4f} (static "
            f"{run['false_free_rate_static']:.4f})  unknown {run['unknown_fraction']:.4f}",
        ]
    if "velocity_error_mps" in result:
        v = result["velocity_error_mps"]
        switches = ", ".join(f"{k} {n:.1f}" for k, n in result["id_switches"].items())
        lines.append(f"{'velocity_error_mps p50/p99':<28}{v['p50']:>6.2f}/{v['p99']:<5.2f}")
        lines.append(f"{'id_switches per minute':<28}  {switches}")
        lines.append(
            f"{'lists with a phantom mover':<28}{result['phantom_movers_share']:>6.1%}"
            "  (a moving track on no mover)"
        )
    for title, key, where in (
        ("object (map/objects)", "tracked_objects", "not tracked"),
        ("object (raster)", "objects", "not found in the map"),
    ):
        lines += ["", f"{title:<22}{'length m':>18}{'width m':>18}{'err %':>14}"]
        for row in result.get(key, []):
            if row["length_error_pct"] is None:
                lines.append(f"{row['name']:<22}  {where}")
                continue
            notes = (
                ("  partial" if row.get("partial") else "")
                + ("  size unsure" if row.get("size_unsure") else "")
                + (f"  {row['tracks']} tracks" if row.get("tracks", 1) > 1 else "")
            )
            lines.append(
                f"{row['name']:<22}{row['true_length_m']:>9.3f}→{row['length_m']:<8.3f}"
                f"{row['true_width_m']:>9.3f}→{row['width_m']:<8.3f}"
                f"{row['length_error_pct']:>6.1f} {row['width_error_pct']:>6.1f}{notes}"
            )
    if "stage_ms" in result:
        lines += ["", f"{'stage (ms)':<16}{'p50':>8}{'p99':>8}"]
        for name, row in result["stage_ms"].items():
            lines.append(f"{name:<16}{row['p50']:>8.1f}{row['p99']:>8.1f}")
        c = result["capture_to_map_ms"]
        lines.append(f"{'capture→map':<16}{c['p50']:>8.1f}{c['p99']:>8.1f}  (camera time included)")
    for step in result.get("lighting_steps", []):
        lines += [
            "",
            f"lighting step at {step['step_s']:.1f} s: {'phase':<8}{'IoU':>8}{'ff static':>11}"
            f"{'unknown':>9}{'away from movers':>18}",
        ]
        for phase in ("before", "during", "after"):
            row = step[phase]
            lines.append(
                f"{'':<33}{phase:<8}{row['iou']:>8.3f}{row['false_free_rate_static']:>11.4f}"
                f"{row['unknown_fraction']:>9.3f}{row['unknown_fraction_still']:>18.3f}"
            )
        lines.append(
            f"{'':<33}IoU drop {step['iou_drop']:.3f} (target ≤ {LIGHTING_IOU_DROP_MAX:g}); "
            f"floor away from movers unknown for {step['unknown_excess_s']:.1f} s"
        )
    return "\n".join(lines)


def main(settings: EvalSettings) -> None:
    stop = stop_on_signals()
    with open_session(settings) as session:
        try:
            current = latest(session, timeout_s=settings.timeout_s)
            evaluator = Evaluator(session, current.resolution_m, settings.timeout_s)
        except (MapUnavailable, CodecError) as error:
            raise SystemExit(f"overgrid eval: {error}") from None
        recorder = None
        if settings.watch_s > 0:
            recorder = Recorder(session, evaluator.window, evaluator.resolution_m)
            # On stderr: standard output is the report alone (``--json`` parses as JSON).
            print(f"watching the stream for {settings.watch_s:g} s …", file=sys.stderr, flush=True)
            stop.wait(settings.watch_s)
        try:
            result = report(evaluator, recorder)
        finally:
            if recorder is not None:
                recorder.close()
    print(json.dumps(result, indent=2) if settings.json_output else table(result))


def cli(argv: Sequence[str] | None = None) -> None:
    main(
        parse_settings(
            EvalSettings,
            argv,
            "overgrid eval",
            "Score the running system's map against the simulator's ground truth.",
        )
    )
