"""``overgrid map get`` and ``overgrid health``: what a person or a robot's script runs."""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path

from pydantic import Field

from common.client import MapUnavailable, health, latest
from common.mapfiles import write_map
from common.settings import CommaList, ZenohSettings, parse_settings
from common.zenoh_session import open_session


class MapGetSettings(ZenohSettings):
    out: Path = Field(
        Path("map.yaml"), description="output: .yaml (+.pgm, nav2 map_server), .png or .npz"
    )
    region: CommaList = Field(
        default_factory=list, description="x0,y0,x1,y1 in metres (default: whole map)"
    )
    timeout_s: float = Field(5.0, gt=0.0, description="how long to wait for the fusion service")


class HealthSettings(ZenohSettings):
    timeout_s: float = Field(5.0, gt=0.0, description="how long to wait for the fusion service")


def map_cli(argv: Sequence[str] | None = None) -> None:
    args = list(argv or [])
    if not args or args[0] != "get":
        print(
            "usage: overgrid map get -o FILE [--region x0,y0,x1,y1] [zenoh options]",
            file=sys.stderr,
        )
        raise SystemExit(2)
    args = ["--out" if a == "-o" else a for a in args[1:]]
    settings = parse_settings(MapGetSettings, args, "overgrid map get", "Save the current map.")
    region = tuple(float(v) for v in settings.region) if settings.region else None
    if region is not None and len(region) != 4:
        raise SystemExit("--region takes four numbers: x0,y0,x1,y1")
    with open_session(settings) as session:
        try:
            occupancy_map = latest(session, region, ("height", "logodds"), settings.timeout_s)  # type: ignore[arg-type]
        except MapUnavailable as error:
            raise SystemExit(f"map unavailable: {error}") from None
    for path in write_map(occupancy_map, settings.out):
        print(path)


def health_cli(argv: Sequence[str] | None = None) -> None:
    settings = parse_settings(
        HealthSettings, argv, "overgrid health", "Show the fusion service's health."
    )
    with open_session(settings) as session:
        try:
            answer = health(session, settings.timeout_s)
        except MapUnavailable as error:
            raise SystemExit(f"fusion unavailable: {error}") from None
    m = answer["map"]
    print(
        f"map v{m['version']}  {m['cols']}×{m['rows']} cells @ {m['resolution_m']} m  origin {m['origin_m']}  "
        f"known {m['known_cells']}"
    )
    print(f"tiles accepted {answer['tiles_accepted']}  rejected {answer['tiles_rejected'] or 0}")
    print(f"{'pair':<10}{'alive':<7}{'tiles':>8}{'last tile':>12}{'capture→map':>14}")
    for pair, row in answer["pairs"].items():
        age = "—" if row["last_tile_age_s"] is None else f"{row['last_tile_age_s']:.1f} s"
        latency = (
            "—" if row["capture_to_fused_ms"] is None else f"{row['capture_to_fused_ms']:.0f} ms"
        )
        print(
            f"{pair:<10}{'yes' if row['alive'] else 'NO':<7}{row['tiles']:>8}{age:>12}{latency:>14}"
        )
