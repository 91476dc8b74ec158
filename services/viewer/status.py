"""What the page shows beside the map: each pair's state and the tracked objects, from the answers
of ``map/health``, ``depth/*/health``, the calibrations and ``map/objects``. Pure."""

from __future__ import annotations

import json
from collections import deque
from typing import Any

from common.messages import ObjectsHeader
from services.viewer.footprints import Polygon

RATE_WINDOW_S = 3.0
"""Frame rates are averaged over this long: steady to read, still quick to show a stall."""
OBJECT_FIELDS = frozenset(
    {
        "id",
        "class",
        "center_m",
        "size_m",
        "yaw_rad",
        "top_m",
        "velocity_mps",
        "partial",
        "size_unsure",
        "round",
    }
)
"""What the page shows of a tracked object; the rest (covariance, stamps, pairs) stays out."""


class TileRates:
    """Tiles per second per pair from map/health's running counts (a depth process sends one tile
    per frame it processes, so this is the pair's frame rate as fusion receives it)."""

    def __init__(self, window_s: float = RATE_WINDOW_S) -> None:
        self.window_s = window_s
        self._history: dict[str, deque[tuple[float, int]]] = {}

    def update(self, pair: str, tiles: int, now_s: float) -> float | None:
        history = self._history.setdefault(pair, deque())
        if history and tiles < history[-1][1]:  # fusion restarted: counts begin again
            history.clear()
        history.append((now_s, tiles))
        while len(history) > 2 and history[1][0] <= now_s - self.window_s:
            history.popleft()
        (t0, n0), (t1, n1) = history[0], history[-1]
        return (n1 - n0) / (t1 - t0) if t1 - t0 >= 0.5 else None


def _floor_model(*rows: dict[str, Any]) -> str | None:
    """The floor model's state, from whichever health answer carries one (a string, or an object
    with a ``state``)."""
    for row in rows:
        value = row.get("floor_model")
        if isinstance(value, dict):
            value = value.get("state", json.dumps(value, sort_keys=True))
        if value is not None:
            return str(value)
    return None


def fusion_status(
    answered_s: float | None, fusion_ok: bool, now_s: float, stale_after_s: float
) -> dict[str, Any]:
    """Whether the page's map is stale: fusion silent for longer than ``stale_after_s`` (or never
    heard). One unanswered health query is not enough: a query lost on a busy link must not flash
    the warning; ``fusion_ok`` (the last query's outcome) goes along as information."""
    silent_s = None if answered_s is None else max(now_s - answered_s, 0.0)
    return {
        "fusion_ok": fusion_ok,
        "fusion_silent_s": None if silent_s is None else round(silent_s, 2),
        "stale": silent_s is None or silent_s > stale_after_s,
    }


def pair_states(
    health: dict[str, Any] | None,
    rates: TileRates,
    now_s: float,
    depth_health: dict[str, dict[str, Any]],
    footprints: dict[str, Polygon],
) -> list[dict[str, Any]]:
    """One row per pair that fusion knows or that has a calibration (a camera with no depth
    process shows up too, as not alive)."""
    fused: dict[str, dict[str, Any]] = (health or {}).get("pairs", {})
    rows = []
    for pair in sorted(set(fused) | set(footprints)):
        row = fused.get(pair, {})
        tiles = row.get("tiles")
        rate = rates.update(pair, int(tiles), now_s) if isinstance(tiles, int) else None
        rows.append(
            {
                "pair": pair,
                "alive": bool(row.get("alive", False)),
                "known_to_fusion": pair in fused,
                "frame_rate_hz": None if rate is None else round(rate, 2),
                "capture_to_map_ms": row.get("capture_to_fused_ms"),
                "last_tile_age_s": row.get("last_tile_age_s"),
                "tiles": tiles,
                "floor_model": _floor_model(depth_health.get(pair, {}), row),
                "footprint_m": footprints.get(pair),
            }
        )
    return rows


def objects_for_page(header: ObjectsHeader) -> list[dict[str, Any]]:
    """The tracked objects of ``map/objects`` with what the page draws: outline, label, arrow."""
    return [
        {k: v for k, v in o.model_dump(mode="json", by_alias=True).items() if k in OBJECT_FIELDS}
        for o in header.objects
    ]
