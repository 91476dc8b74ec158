import math

import numpy as np
import pytest

from common.lattice import Window
from common.messages import TruthObject
from services.camera_sim import truth
from services.camera_sim.scene import ObjectSpec, SceneSpec

R = 0.05


def test_box_occupies_exactly_its_footprint() -> None:
    box = TruthObject(
        name="b",
        shape="box",
        moving=False,
        center_m=(2.0, 3.0, 0.5),
        yaw_rad=0.0,
        size_m=(1.0, 0.6, 1.0),
    )
    window = Window.covering(0, 0, 5, 5, R)
    grid = truth.occupancy([box], window, R, (0.1, 2.0))
    assert grid.sum() == 20 * 12  # 1.0 m × 0.6 m of 5 cm cells
    rows, cols = np.nonzero(grid)
    assert (cols.min() * R, (cols.max() + 1) * R) == pytest.approx((1.5, 2.5))
    assert (rows.min() * R, (rows.max() + 1) * R) == pytest.approx((2.7, 3.3))


def test_rotated_box_and_cylinder_areas() -> None:
    box = TruthObject(
        name="b",
        shape="box",
        moving=False,
        center_m=(2.0, 2.0, 0.5),
        yaw_rad=0.6,
        size_m=(1.2, 0.8, 1.0),
    )
    cyl = TruthObject(
        name="c",
        shape="cylinder",
        moving=False,
        center_m=(4.0, 4.0, 0.5),
        yaw_rad=0.0,
        size_m=(0.6, 0.6, 1.0),
    )
    window = Window.covering(0, 0, 6, 6, R)
    assert truth.occupancy([box], window, R, (0.1, 2.0)).sum() * R * R == pytest.approx(
        0.96, rel=0.05
    )
    assert truth.occupancy([cyl], window, R, (0.1, 2.0)).sum() * R * R == pytest.approx(
        math.pi * 0.09, rel=0.05
    )


def test_objects_outside_the_height_band_are_free() -> None:
    low = TruthObject(
        name="mat",
        shape="box",
        moving=False,
        center_m=(1.0, 1.0, 0.025),
        yaw_rad=0.0,
        size_m=(1, 1, 0.05),
    )
    overhead = TruthObject(
        name="beam",
        shape="box",
        moving=False,
        center_m=(3.0, 3.0, 2.5),
        yaw_rad=0.0,
        size_m=(1, 1, 0.2),
    )
    assert (
        truth.occupancy([low, overhead], Window.covering(0, 0, 5, 5, R), R, (0.1, 2.0)).sum() == 0
    )


def test_scene_truth_includes_walls_and_objects() -> None:
    scene = SceneSpec(
        objects=[ObjectSpec(name="s", shape="shelf", center_xy_m=(6, 5), size_m=(2.0, 0.6, 1.8))]
    )
    names = {o.name for o in scene.truth_objects(0.0)}
    assert {"s", "wall_south", "wall_north", "wall_east", "wall_west"} <= names
