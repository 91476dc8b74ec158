"""``overgrid map get``, ``overgrid health`` and ``overgrid objects``: what a person or a robot's
script runs."""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from pydantic import Field, field_validator

from common.client import MAX_TIMEOUT_S, MapUnavailable, health, latest, objects
from common.mapfiles import map_file_suffix, write_map
from common.occupancy_map import Region, region_of
from common.settings import CommaList, ZenohSettings, parse_settings
from common.zenoh_session import open_session


class FusionQuerySettings(ZenohSettings):
    timeout_s: float = Field(
        5.0, gt=0.0, le=MAX_TIMEOUT_S, description="how long to wait for the fusion service"
    )


class MapGetSettings(FusionQuerySettings):
    out: Path = Field(
        Path("map.yaml"), description="output: .yaml (+.pgm, nav2 map_server), .png or .npz"
    )
    region: CommaList = Field(
        default_factory=list, description="x0,y0,x1,y1 in metres (default: whole map)"
    )

    @field_validator("out")
    @classmethod
    def _known_suffix(cls, out: Path) -> Path:
        map_file_suffix(out)
        return out

    @field_validator("region")
    @classmethod
    def _valid_region(cls, values: list[str]) -> list[str]:
        if values:
            region_of(values)
        return values

    @property
    def region_m(self) -> Region | None:
        return region_of(self.region) if self.region else None


MAP_USAGE = (
    "usage: overgrid map get -o FILE [--region x0,y0,x1,y1] [zenoh options]\n"
    "(overgrid map get --help lists every setting)"
)


def map_cli(argv: Sequence[str] | None = None) -> None:
    args = list(argv or [])
    if args[:1] in (["-h"], ["--help"]):
        print(MAP_USAGE)
        raise SystemExit(0)
    if not args or args[0] != "get":
        print(MAP_USAGE, file=sys.stderr)
        raise SystemExit(2)
    args = ["--out" if a == "-o" else a for a in args[1:]]
    settings = parse_settings(MapGetSettings, args, "overgrid map get", "Save the current map.")
    with open_session(settings) as session:
        try:
            occupancy_map = latest(
                session, settings.region_m, ("height", "logodds"), settings.timeout_s
            )
        except MapUnavailable as error:
            raise SystemExit(f"map unavailable: {error}") from None
    try:
        written = write_map(occupancy_map, settings.out)
    except (ValueError, OSError) as error:
        raise SystemExit(f"{settings.out}: {error}") from None
    for path in written:
        print(path)


def health_cli(argv: Sequence[str] | None = None) -> None:
    settings = parse_settings(
        FusionQuerySettings, argv, "overgrid health", "Show the fusion service's health."
    )
    with open_session(settings) as session:
        try:
            answer = health(session, settings.timeout_s)
        except MapUnavailable as error:
            raise SystemExit(f"fusion unavailable: {error}") from None
    try:
        lines = health_lines(answer)
    except (LookupError, TypeError, ValueError, AttributeError) as error:
        raise SystemExit(
            f"fusion's health answer lacks what this client reads ({type(error).__name__}: "
            f"{str(error)[:200]}): a fusion of another version?"
        ) from None
    print("\n".join(lines))


STALE_S = 5.0
"""A map, or a pair alive, with no capture newer than this is said STALE / NO TILE in ``overgrid
health`` (with every camera gone, each pair read "alive yes" and a person had to read the ages):
what fusion's health says (``stale_after_s``, its ``decay_after_s``, after which the map forgets
what it saw), this from a fusion that does not say."""


def health_lines(answer: dict[str, Any]) -> list[str]:
    """The table ``overgrid health`` prints; built whole before any is printed, so an answer
    without a field it reads (no schema: a JSON object) ends in one line, not half a table."""
    m = answer["map"]
    age_s, stale_s = m.get("capture_age_s"), float(m.get("stale_after_s", STALE_S))
    newest = (
        "no capture yet"
        if age_s is None
        else f"newest capture {age_s:.1f} s ago" + ("  STALE" if age_s > stale_s else "")
    )
    lines = [
        f"map v{m['version']}  {m['cols']}×{m['rows']} cells @ {m['resolution_m']} m  "
        f"origin {m['origin_m']}  known {m['known_cells']}  {newest}",
        f"tiles accepted {answer['tiles_accepted']}  rejected {answer['tiles_rejected'] or 0}",
    ]
    saved = answer.get("state") or {}
    if saved:
        errors = saved["save_errors"]
        lines.append(
            f"state saved v{saved['saved_version']}"
            + (f"  SAVE ERRORS {errors}" if errors else "  no save errors")
        )
    lines.append(
        f"{'pair':<10}{'alive':<7}{'tiles':>8}{'rejected':>10}{'last tile':>12}"
        f"{'capture→map':>14}  note"
    )
    for pair, row in answer["pairs"].items():
        age = "—" if row["last_tile_age_s"] is None else f"{row['last_tile_age_s']:.1f} s"
        latency = (
            "—" if row["capture_to_fused_ms"] is None else f"{row['capture_to_fused_ms']:.0f} ms"
        )
        notes = [f"CONFLICT: {len(row['processes'])} processes"] if row["conflict"] else []
        stalled = row["alive"] and (row["last_tile_age_s"] or 0.0) > stale_s
        notes += [f"NO TILE FOR {row['last_tile_age_s']:.0f} s"] if stalled else []
        notes += ["LAGGING"] if row["lagging"] else []
        refused = row.get("detections_rejected", 0)
        notes += [f"{refused} detections rejected"] if refused else []
        late = row.get("detections_late", 0)
        notes += [f"{late} detections late"] if late else []
        lines.append(
            f"{pair:<10}{'yes' if row['alive'] else 'NO':<7}{row['tiles']:>8}"
            f"{row.get('rejected', 0):>10}{age:>12}{latency:>14}  {', '.join(notes)}".rstrip()
        )
    return lines


def objects_cli(argv: Sequence[str] | None = None) -> None:
    settings = parse_settings(
        FusionQuerySettings, argv, "overgrid objects", "Show the tracked obstacles (map/objects)."
    )
    with open_session(settings) as session:
        try:
            answer = objects(session, settings.timeout_s)
        except MapUnavailable as error:
            raise SystemExit(f"fusion unavailable: {error}") from None
    print(f"objects v{answer.version}  {len(answer.objects)} tracked")
    print(
        f"{'id':>5} {'class':<7}{'x m':>7}{'y m':>7}{'length':>8}{'width':>7}{'yaw°':>6}"
        f"{'top m':>7}{'vx m/s':>8}{'vy m/s':>8}{'σv':>6}  {'age s':>6}  pairs"
    )
    for o in answer.objects:
        sigma_v = (o.velocity_cov_m2ps2[0][0] + o.velocity_cov_m2ps2[1][1]) ** 0.5
        age_s = (o.last_seen_ns - o.first_seen_ns) / 1e9
        print(
            f"{o.id:>5} {o.object_class:<7}{o.center_m[0]:>7.2f}{o.center_m[1]:>7.2f}"
            f"{o.size_m[0]:>8.3f}{o.size_m[1]:>7.3f}{o.yaw_rad * 57.29578:>6.0f}{o.top_m:>7.2f}"
            f"{o.velocity_mps[0]:>8.2f}{o.velocity_mps[1]:>8.2f}{sigma_v:>6.2f}  {age_s:>6.1f}  "
            f"{','.join(o.pairs)}{'  partial' if o.partial else ''}"
            f"{'  size unsure' if o.size_unsure else ''}{'  round' if o.round else ''}"
            f"{'  settled' if o.settled else ''}"
        )
