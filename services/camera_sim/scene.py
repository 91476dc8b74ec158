"""A warehouse-like scene as data: generated from a seed or loaded from a user's JSON/YAML file.

Moving objects are kinematic: their pose is a pure function of time, so several sim processes
rendering different pairs, and ``sim/truth``, agree without talking to each other.
"""

from __future__ import annotations

import itertools
import math
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, model_validator

from common.lattice import Window
from common.messages import TruthObject
from common.setting_files import load_data_file

ShapeKind = Literal["box", "cylinder", "shelf", "pallet"]


def _floor_alias(value: object) -> object:
    return "speckle" if value == "textured" else value  # the name of speckle before it had one


FloorKind = Annotated[Literal["concrete", "speckle", "plain"], BeforeValidator(_floor_alias)]
"""``concrete``: troweled concrete, weak multi-scale texture, stains (a real site); ``speckle``:
white-noise texture at every scale (the ideal world stereo loves); ``plain``: uniform paint."""


class ObjectSpec(BaseModel):
    """A static object standing on the floor. ``size_m`` is full extents (x, y, z); a cylinder's
    diameter is ``size_m[0]``. A box is a cardboard box (tape and a label on top), a shelf a rack
    (legs, shelves and a top board), a pallet a wooden deck on three stringers. ``plain``: one
    uniform colour, no texture, no tape or label (a painted crate; the hard case for stereo)."""

    model_config = ConfigDict(extra="forbid")

    name: str
    shape: ShapeKind
    center_xy_m: tuple[float, float]
    yaw_rad: float = 0.0
    size_m: tuple[float, float, float] = Field(description="full extents x, y, z in metres")
    rgba: tuple[float, float, float, float] = (0.6, 0.45, 0.3, 1.0)
    plain: bool = False

    @model_validator(mode="after")
    def _positive(self) -> ObjectSpec:
        if min(self.size_m) <= 0:
            raise ValueError(f"object {self.name}: sizes must be positive, got {self.size_m}")
        return self


class MoverSpec(BaseModel):
    """An object that loops along a closed polyline at constant speed (kinematic)."""

    model_config = ConfigDict(extra="forbid")

    name: str
    shape: Literal["box", "cylinder"]
    size_m: tuple[float, float, float]
    path_xy_m: list[tuple[float, float]] = Field(min_length=2)
    speed_mps: float = Field(gt=0)
    rgba: tuple[float, float, float, float] = (0.2, 0.4, 0.8, 1.0)

    def _segments(self) -> tuple[np.ndarray, np.ndarray, float]:
        points = np.asarray([*self.path_xy_m, self.path_xy_m[0]], dtype=np.float64)
        lengths = np.linalg.norm(np.diff(points, axis=0), axis=1)
        return points, lengths, float(lengths.sum())

    def state_at(self, t_s: float) -> tuple[tuple[float, float], tuple[float, float]]:
        """Position and velocity (x, y) at time ``t_s`` (seconds, any epoch)."""
        points, lengths, perimeter = self._segments()
        s = math.fmod(t_s * self.speed_mps, perimeter)
        if s < 0:
            s += perimeter
        k = int(np.searchsorted(np.cumsum(lengths), s, side="right"))
        k = min(k, len(lengths) - 1)
        s_k = s - float(np.sum(lengths[:k]))
        direction = (points[k + 1] - points[k]) / max(lengths[k], 1e-12)
        xy = points[k] + direction * s_k
        v = direction * self.speed_mps
        return (float(xy[0]), float(xy[1])), (float(v[0]), float(v[1]))


class MarkingSpec(BaseModel):
    """Paint on the floor (lane line, zone outline): flat, never an obstacle."""

    model_config = ConfigDict(extra="forbid")

    center_xy_m: tuple[float, float]
    size_m: tuple[float, float]
    yaw_rad: float = 0.0
    rgba: tuple[float, float, float, float] = (0.85, 0.7, 0.1, 1.0)


class SceneSpec(BaseModel):
    """The whole scene; the floor spans x ∈ [0, floor_x_m], y ∈ [0, floor_y_m], walls outside it."""

    model_config = ConfigDict(extra="forbid")

    floor_size_m: tuple[float, float] = (12.0, 10.0)
    floor: FloorKind = "concrete"
    wall_height_m: float = Field(1.2, gt=0)
    wall_thickness_m: float = Field(0.2, gt=0)
    texture_seed: int = 0
    objects: list[ObjectSpec] = Field(default_factory=list)
    movers: list[MoverSpec] = Field(default_factory=list)
    markings: list[MarkingSpec] = Field(default_factory=list)

    def window(self, resolution_m: float) -> Window:
        """The lattice window of the floor and its walls: what ``sim/truth`` rasterises."""
        margin = self.wall_thickness_m
        x_m, y_m = self.floor_size_m
        return Window.covering(-margin, -margin, x_m + margin, y_m + margin, resolution_m)

    def truth_objects(self, t_s: float) -> list[TruthObject]:
        """Every object's box/cylinder at time ``t_s``, walls included."""
        out = [
            TruthObject(
                name=o.name,
                shape="cylinder" if o.shape == "cylinder" else "box",  # shelf, pallet: boxes
                moving=False,
                center_m=(o.center_xy_m[0], o.center_xy_m[1], o.size_m[2] / 2),
                yaw_rad=o.yaw_rad,
                size_m=o.size_m,
            )
            for o in self.objects
        ]
        for m in self.movers:
            (x, y), v = m.state_at(t_s)
            out.append(
                TruthObject(
                    name=m.name,
                    shape=m.shape,
                    moving=True,
                    center_m=(x, y, m.size_m[2] / 2),
                    yaw_rad=0.0,
                    size_m=m.size_m,
                    velocity_mps=v,
                )
            )
        return out + self.walls()

    def walls(self) -> list[TruthObject]:
        fx, fy = self.floor_size_m
        t, h = self.wall_thickness_m, self.wall_height_m
        boxes = {
            "wall_south": ((fx / 2, -t / 2), (fx + 2 * t, t)),
            "wall_north": ((fx / 2, fy + t / 2), (fx + 2 * t, t)),
            "wall_west": ((-t / 2, fy / 2), (t, fy)),
            "wall_east": ((fx + t / 2, fy / 2), (t, fy)),
        }
        return [
            TruthObject(
                name=name,
                shape="box",
                moving=False,
                center_m=(cx, cy, h / 2),
                yaw_rad=0.0,
                size_m=(sx, sy, h),
            )
            for name, ((cx, cy), (sx, sy)) in boxes.items()
        ]


def load_scene(path: Path) -> SceneSpec:
    """A scene written by hand, JSON or YAML, with the fields of :class:`SceneSpec`."""
    return SceneSpec.model_validate(load_data_file(Path(path)))


def _footprint_radius(size_m: tuple[float, float, float]) -> float:
    return 0.5 * math.hypot(size_m[0], size_m[1])


def _distance_to_path(xy: np.ndarray, path: list[tuple[float, float]]) -> float:
    points = np.asarray([*path, path[0]], dtype=np.float64)
    best = math.inf
    for a, b in itertools.pairwise(points):
        ab = b - a
        t = float(np.clip(np.dot(xy - a, ab) / max(np.dot(ab, ab), 1e-12), 0.0, 1.0))
        best = min(best, float(np.linalg.norm(xy - (a + t * ab))))
    return best


CARDBOARD_RGBA = (0.66, 0.5, 0.33, 1.0)
LANE_RGBA = (0.85, 0.7, 0.1, 1.0)
ZONE_RGBA = (0.9, 0.9, 0.88, 1.0)
LINE_WIDTH_M = 0.08


def _line(a: tuple[float, float], b: tuple[float, float], rgba: tuple[float, ...]) -> MarkingSpec:
    (ax, ay), (bx, by) = a, b
    return MarkingSpec(
        center_xy_m=((ax + bx) / 2, (ay + by) / 2),
        size_m=(math.hypot(bx - ax, by - ay), LINE_WIDTH_M),
        yaw_rad=math.atan2(by - ay, bx - ax),
        rgba=(rgba[0], rgba[1], rgba[2], rgba[3]),
    )


def _zone_outline(obj: ObjectSpec, margin_m: float = 0.15) -> list[MarkingSpec]:
    """Painted rectangle around a floor zone (where a pallet stands)."""
    c, s = math.cos(obj.yaw_rad), math.sin(obj.yaw_rad)
    hx, hy = obj.size_m[0] / 2 + margin_m, obj.size_m[1] / 2 + margin_m
    corners = [
        (obj.center_xy_m[0] + c * ox - s * oy, obj.center_xy_m[1] + s * ox + c * oy)
        for ox, oy in ((-hx, -hy), (hx, -hy), (hx, hy), (-hx, hy))
    ]
    return [_line(a, b, ZONE_RGBA) for a, b in itertools.pairwise([*corners, corners[0]])]


def _object_size(
    shape: ShapeKind, rng: np.random.Generator
) -> tuple[tuple[float, float, float], float]:
    """Full extents and yaw of a warehouse object of this kind."""
    if shape == "shelf":
        size = (float(rng.uniform(1.6, 2.4)), 0.6, float(rng.uniform(1.6, 2.0)))
        return size, float(rng.choice([0.0, math.pi / 2]))
    if shape == "pallet":  # EUR pallet: 1.2 × 0.8 m, 144 mm high
        return (1.2, 0.8, 0.144), float(rng.choice([0.0, math.pi / 2]) + rng.uniform(-0.1, 0.1))
    if shape == "box":
        size = (
            float(rng.uniform(0.4, 1.2)),
            float(rng.uniform(0.4, 1.2)),
            float(rng.uniform(0.2, 1.5)),
        )
        return size, float(rng.uniform(0, math.pi))
    diameter = float(rng.uniform(0.4, 0.6))  # people-sized
    return (diameter, diameter, float(rng.uniform(0.9, 1.9))), 0.0


def _object_rgba(shape: ShapeKind, rng: np.random.Generator) -> tuple[float, float, float, float]:
    if shape == "box":
        shade = float(rng.uniform(0.85, 1.05))
        return (
            min(1.0, CARDBOARD_RGBA[0] * shade),
            min(1.0, CARDBOARD_RGBA[1] * shade),
            min(1.0, CARDBOARD_RGBA[2] * shade),
            1.0,
        )
    if shape == "pallet":
        return (0.72, 0.6, 0.45, 1.0)
    if shape == "shelf":
        return (0.2, 0.35, 0.6, 1.0) if rng.random() < 0.5 else (0.85, 0.45, 0.1, 1.0)
    red, green, blue = (float(v) for v in rng.uniform(0.3, 0.9, size=3))
    return (red, green, blue, 1.0)


def generate_scene(
    seed: int = 0,
    floor_size_m: tuple[float, float] = (12.0, 10.0),
    floor: FloorKind = "concrete",
    boxes: int = 5,
    cylinders: int = 3,
    shelves: int = 2,
    pallets: int = 2,
    plain_boxes: int = 1,
    plain_objects: bool = False,
) -> SceneSpec:
    """A warehouse floor: shelving, cardboard boxes, pallets in painted zones, people-sized
    cylinders and ``plain_boxes`` uniform crates, placed without overlap and clear of two movers (a
    forklift at 2 m/s on an aisle loop, a person at 1.2 m/s), whose aisles have lane lines.
    ``plain_objects``: every static object is one uniform colour."""
    rng = np.random.default_rng(seed)
    fx, fy = floor_size_m
    movers = [
        MoverSpec(
            name="mover_forklift",
            shape="box",
            size_m=(1.2, 0.8, 1.1),
            speed_mps=2.0,
            path_xy_m=[(1.2, 1.2), (fx - 1.2, 1.2), (fx - 1.2, 2.2), (1.2, 2.2)],
            rgba=(0.9, 0.65, 0.1, 1.0),
        ),
        MoverSpec(
            name="mover_person",
            shape="cylinder",
            size_m=(0.5, 0.5, 1.75),
            speed_mps=1.2,
            path_xy_m=[(fx / 2, 3.5), (fx / 2, fy - 1.2)],
            rgba=(0.2, 0.3, 0.7, 1.0),
        ),
    ]
    markings = [
        _line((0.5, 0.45), (fx - 0.5, 0.45), LANE_RGBA),
        _line((0.5, 2.95), (fx - 0.5, 2.95), LANE_RGBA),
        _line((fx / 2 - 0.6, 3.1), (fx / 2 - 0.6, fy - 0.5), LANE_RGBA),
        _line((fx / 2 + 0.6, 3.1), (fx / 2 + 0.6, fy - 0.5), LANE_RGBA),
    ]
    wanted: list[tuple[ShapeKind, int, bool]] = [
        ("shelf", shelves, False),
        ("pallet", pallets, False),
        ("box", boxes, False),
        ("box", plain_boxes, True),
        ("cylinder", cylinders, False),
    ]
    objects: list[ObjectSpec] = []
    for shape, count, plain in wanted:
        for k in range(count):
            for _attempt in range(500):
                size, yaw = _object_size(shape, rng)
                radius = _footprint_radius(size)
                xy = np.array(
                    [
                        rng.uniform(radius + 0.4, fx - radius - 0.4),
                        rng.uniform(radius + 0.4, fy - radius - 0.4),
                    ]
                )
                clear_of_objects = all(
                    np.linalg.norm(xy - np.asarray(o.center_xy_m))
                    > radius + _footprint_radius(o.size_m) + 0.5
                    for o in objects
                )
                clear_of_movers = all(
                    _distance_to_path(xy, m.path_xy_m) > radius + _footprint_radius(m.size_m) + 0.3
                    for m in movers
                )
                if clear_of_objects and clear_of_movers:
                    rgba = (0.8, 0.8, 0.78, 1.0) if plain else _object_rgba(shape, rng)
                    objects.append(
                        ObjectSpec(
                            name=f"crate_{k}" if plain else f"{shape}_{k}",
                            shape=shape,
                            center_xy_m=(float(xy[0]), float(xy[1])),
                            yaw_rad=yaw,
                            size_m=size,
                            rgba=rgba,
                            plain=plain or plain_objects,
                        )
                    )
                    if shape == "pallet":
                        markings += _zone_outline(objects[-1])
                    break
    return SceneSpec(
        floor_size_m=floor_size_m,
        floor=floor,
        texture_seed=seed,
        objects=objects,
        movers=movers,
        markings=markings,
    )
