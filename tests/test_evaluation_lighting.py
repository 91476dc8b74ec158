"""Scoring around a lighting step: phases, IoU drop, how long the floor stayed unknown."""

import math

import pytest

from services.camera_sim.lighting import Lighting
from services.evaluation.lighting import DURING_S, TimelineScore, over_run, step_phases


def _timeline(step_s: float, dip_iou: float, unknown_for_s: float) -> list[TimelineScore]:
    out = []
    for k in range(-20, 40):
        t = step_s + 0.5 * k
        after = t - step_s >= 0
        iou = dip_iou if after and t - step_s < DURING_S else 0.9
        unknown = 0.2 if after and t - step_s < unknown_for_s else 0.03
        out.append(TimelineScore(t, iou, 0.001, unknown, 0.95, 0.95, 0.002))
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
        TimelineScore(float(k), iou, 0.001, 0.04, 0.9, 0.9, 0.01 * k) for k, iou in enumerate(ious)
    ][::-1]  # in any order
    run = over_run(timeline)
    assert run["maps"] == 4
    assert run["iou"] == pytest.approx(0.8)
    assert run["false_free_rate"] == pytest.approx(0.035)
    assert math.isnan(over_run([])["iou"]) and over_run([])["maps"] == 0
