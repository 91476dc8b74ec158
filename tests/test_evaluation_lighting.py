"""Scoring around a lighting step: phases, IoU drop, how long the floor stayed unknown."""

import math
from dataclasses import replace

import numpy as np
import pytest

from common.lattice import Window
from common.messages import TruthObject
from common.occupancy_map import UNKNOWN
from services.camera_sim.lighting import Lighting
from services.evaluation.lighting import DURING_S, TimelineScore, over_run, step_phases
from services.evaluation.metrics import unknown_away_from_movers


def _timeline(step_s: float, dip_iou: float, unknown_for_s: float) -> list[TimelineScore]:
    out = []
    for k in range(-20, 40):
        t = step_s + 0.5 * k
        after = t - step_s >= 0
        iou = dip_iou if after and t - step_s < DURING_S else 0.9
        unknown = 0.2 if after and t - step_s < unknown_for_s else 0.03
        out.append(TimelineScore(t, iou, 0.001, unknown, 0.95, 0.95, 0.002, unknown))
    return out


def test_phases_measure_the_dip_and_the_unknown_time() -> None:
    (step,) = step_phases([100.0], _timeline(100.0, dip_iou=0.8, unknown_for_s=1.6))
    assert step["before"]["iou"] == pytest.approx(0.9)
    assert step["during"]["iou"] == pytest.approx(0.8)
    assert step["after"]["iou"] == pytest.approx(0.9)
    assert step["iou_drop"] == pytest.approx(0.1)
    assert step["unknown_excess_s"] == pytest.approx(1.5)  # last sample still unknown: +1.5 s
    assert step["before"]["false_free_rate_static"] == pytest.approx(0.001)


def test_a_step_without_samples_before_it_is_not_scored() -> None:
    assert step_phases([100.0], _timeline(100.0, 0.8, 1.0)[20:]) == []
    (steady,) = step_phases([100.0], _timeline(100.0, dip_iou=0.9, unknown_for_s=0.0))
    assert steady["iou_drop"] == pytest.approx(0.0) and steady["unknown_excess_s"] == 0.0


def test_light_steps_are_listed_in_a_window_and_level_is_periodic() -> None:
    lighting = Lighting(step_period_s=40.0)
    assert lighting.steps_s(0.0, 100.0) == [0.0, 20.0, 40.0, 60.0, 80.0]
    assert lighting.level(25.0) == 0.5 and lighting.level(45.0) == 1.0
    assert Lighting().steps_s(0.0, 100.0) == [] and Lighting().lag_ratio(5.0, 0.6) == 1.0
    assert math.isclose(Lighting(drift=True).level(10.0), 1.0)  # sin peak at a quarter period


def test_over_the_run_leaves_out_start_up_and_averages_the_rest() -> None:
    """Six maps: the first two (start-up) read half the map wrong; the rest alternate between a
    snapshot that caught a mover free and one that did not."""
    ious = [0.5, 0.5, 0.9, 0.7, 0.9, 0.7]
    timeline = [
        TimelineScore(float(k), iou, 0.001, 0.04, 0.9, 0.9, 0.01 * k, 0.04)
        for k, iou in enumerate(ious)
    ][::-1]  # in any order
    run = over_run(timeline)
    assert run["maps"] == 4
    assert run["iou"] == pytest.approx(0.8)
    assert run["false_free_rate"] == pytest.approx(0.035)
    assert math.isnan(over_run([])["iou"]) and over_run([])["maps"] == 0


def test_a_movers_shadow_after_a_step_is_not_unknown_floor_of_the_light() -> None:
    """The whole floor's unknown share rises 4 s after the step (a mover's occlusion shadow,
    two pairs): the step's unknown time counts the floor away from the movers alone."""
    timeline = [
        replace(s, unknown_fraction=0.2 if 4.0 <= s.stamp_s - 100.0 < 5.0 else 0.03)
        for s in _timeline(100.0, dip_iou=0.9, unknown_for_s=0.0)
    ]
    (step,) = step_phases([100.0], timeline)
    assert step["unknown_excess_s"] == 0.0  # before: 4.5 s
    (lit,) = step_phases([100.0], _timeline(100.0, dip_iou=0.9, unknown_for_s=1.0))
    assert lit["unknown_excess_s"] == pytest.approx(0.5)


def test_unknown_away_from_movers_leaves_out_the_floor_around_them() -> None:
    """A 10 × 10 m floor, all seen, a mover of 1 × 1 m at (2, 2): unknown cells within 2.5 m of
    its footprint do not count; a strip of unknown floor far from it counts as its share of all
    the floor."""
    resolution_m = 0.1
    window = Window(0, 0, 100, 100)
    x_m, y_m = window.cell_centers(resolution_m)
    seen = np.ones(window.shape, np.bool_)
    truth = np.zeros(window.shape, np.bool_)
    mover = TruthObject(
        name="mover",
        shape="box",
        moving=True,
        center_m=(2.0, 2.0, 0.5),
        yaw_rad=0.0,
        size_m=(1.0, 1.0, 1.0),
    )
    occupancy = np.zeros(window.shape, np.int8)  # free
    occupancy[np.hypot(x_m - 2.0, y_m - 2.0) < 2.5] = UNKNOWN  # its shadow, and about
    assert unknown_away_from_movers(occupancy, truth, seen, [mover], window, resolution_m) == 0.0
    assert unknown_away_from_movers(occupancy, truth, seen, [], window, resolution_m) > 0.15
    occupancy[x_m > 9.0] = UNKNOWN  # a strip of floor far from it
    away = unknown_away_from_movers(occupancy, truth, seen, [mover], window, resolution_m)
    assert away == pytest.approx(0.1)  # of all the floor: where the mover is changes nothing
    # Moving at 2 m/s towards +y, it was at (2, -2) 2 s ago: the map may still show it there.
    came = mover.model_copy(update={"center_m": (2.0, 6.0, 0.5), "velocity_mps": (0.0, 2.0)})
    assert unknown_away_from_movers(occupancy, truth, seen, [came], window, resolution_m) == (
        pytest.approx(0.1)
    )
