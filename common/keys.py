"""Key expressions of DESIGN.md, defined once. A Zenoh ``namespace`` prefixes them all."""

from __future__ import annotations

import re

PAIR_ID = re.compile(r"^[A-Za-z0-9_\-]{1,64}$")

STEREO_ALL = "cam/*/stereo"
CALIB_ALL = "cam/*/calib"
SIM_TRUTH = "sim/truth"
TILES_ALL = "depth/*/tile"
DEPTH_ALIVE_ALL = "depth/*/alive/*"
"""One token per depth process: two processes claiming one pair show as two tokens."""
DEPTH_HEALTH_ALL = "depth/*/health"
"""Every depth process answers on its own key: one query, one answer per pair."""
MAP_LATEST = "map/latest"
MAP_UPDATES = "map/updates"
MAP_HEALTH = "map/health"
MAP_OBJECTS = "map/objects"
OBJECTS_ALL = "depth/*/objects"


def check_pair_id(pair: str) -> str:
    """A pair id becomes one key chunk: no ``/``, ``*`` or other key-expression syntax."""
    if not PAIR_ID.match(pair):
        raise ValueError(f"pair id {pair!r} must be 1-64 letters, digits, '_' or '-'")
    return pair


def stereo(pair: str) -> str:
    return f"cam/{check_pair_id(pair)}/stereo"


def calib(pair: str) -> str:
    return f"cam/{check_pair_id(pair)}/calib"


def tile(pair: str) -> str:
    return f"depth/{check_pair_id(pair)}/tile"


def objects(pair: str) -> str:
    """One pair's object detections per frame (DESIGN.md, Objects)."""
    return f"depth/{check_pair_id(pair)}/objects"


def depth_alive(pair: str, instance: str) -> str:
    """Liveliness token a depth process holds while it runs (DESIGN.md, Presence); ``instance``
    (its Zenoh session id) tells two processes that claim the same pair apart."""
    return f"depth/{check_pair_id(pair)}/alive/{check_pair_id(instance)}"


def depth_health(pair: str) -> str:
    """Queryable: JSON counters of one depth process (tiles, skipped, rejected by reason, stage times)."""
    return f"depth/{check_pair_id(pair)}/health"


def pair_of(key: str) -> str:
    """The pair chunk of ``cam/{pair}/…`` or ``depth/{pair}/…``, namespace already stripped."""
    parts = str(key).split("/")
    if len(parts) < 3 or parts[0] not in ("cam", "depth"):
        raise ValueError(f"key {key!r} has no pair chunk")
    return check_pair_id(parts[1])


def instance_of(alive_key: str) -> str:
    """The process chunk of a ``depth/{pair}/alive/{instance}`` token."""
    parts = str(alive_key).split("/")
    if len(parts) != 4 or parts[2] != "alive":
        raise ValueError(f"key {alive_key!r} is not a depth liveliness token")
    return check_pair_id(parts[3])
