"""``overgrid up`` runs the whole system as real processes and leaves nothing behind."""

import json
import os
import re
import signal
import subprocess
import sys
import urllib.request
from pathlib import Path

import pytest

from common.client import MapUnavailable, health
from common.mapfiles import PICTURE_COLORS, read_map_server
from common.png import decode_png
from common.settings import OvergridParams, ZenohSettings, parse_settings
from services.camera_sim.settings import CameraSimParams, CameraSimSettings
from services.depth.settings import DepthParams, DepthSettings
from services.evaluation.metrics import COVERAGE_HEIGHTS_M
from services.fusion.settings import FusionParams, FusionSettings
from services.ros2.settings import RmwZenohSettings
from services.up import (
    UpSettings,
    child_commands,
    child_environment,
    progress_line,
    without_unservable_viewer,
)
from tests.conftest import REPO, Bus, run_overgrid, wait_for

pytestmark = pytest.mark.process


def _up(
    bus: Bus, out: Path, *args: str, env: dict[str, str] | None = None
) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "services.cli",
            "up",
            "--pairs",
            "2",
            "--out",
            str(out),
            "--progress-s",
            "1",
            *args,
            *bus.flags(),
        ],
        cwd=REPO,
        env=None if env is None else {**os.environ, **env},
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


CHILDREN: dict[str, tuple[type[ZenohSettings], type[OvergridParams], str]] = {
    "camera-sim": (CameraSimSettings, CameraSimParams, "camera_sim"),
    "depth": (DepthSettings, DepthParams, "depth"),
    "fusion": (FusionSettings, FusionParams, "fusion"),
}


def test_children_are_handed_the_values_up_validated() -> None:
    """Flat, nested and list values, negative numbers: each child parses back exactly ``up``'s."""
    args = ["--pairs", "3", "--seed", "4", "--camera-sim.pairs", "p0,p2", "--rate-hz", "1.5"]
    args += ["--p-hit", "0.8", "--depth.matcher.block-size", "5", "--no-subpixel"]
    args += ["--decay-after-s", "3", "--logodds-min", "-1", "--bounds=-2,-2,14,12"]
    args += ["--no-view", "--namespace", "site-a", "--listen", "tcp/127.0.0.1:7999"]
    settings = parse_settings(UpSettings, args, "overgrid up", "")
    commands = dict(child_commands(settings))
    assert sorted(commands) == ["camera_sim", "depth_p0", "depth_p2", "fusion"]  # rendered pairs
    for name, (command, *child_args) in commands.items():
        settings_cls, params_cls, field = CHILDREN[command]
        child = parse_settings(settings_cls, child_args, command, "")
        assert child.namespace == "site-a" and child.listen == []  # `up` alone listens
        for param in params_cls.model_fields:
            assert getattr(child, param) == getattr(getattr(settings, field), param), (name, param)
    assert settings.camera_sim.rig.pair_count == 3 and settings.depth.model.p_hit == 0.8
    assert settings.fusion.grid.logodds_min == -1.0


def test_nested_children_read_no_settings_of_their_own(monkeypatch: pytest.MonkeyPatch) -> None:
    """``up`` reads the nested variable; the child's flat one must not override what it hands over."""
    monkeypatch.setenv("OVERGRID_CAMERA_SIM__RATE_HZ", "3")
    monkeypatch.setenv("OVERGRID_RATE_HZ", "9")
    settings = parse_settings(UpSettings, [], "overgrid up", "")
    assert settings.camera_sim.rate_hz == 3.0
    (args,) = [args for name, args in child_commands(settings) if name == "camera_sim"]
    assert "3.0" in args and not any(k.startswith("OVERGRID_") for k in child_environment(args[0]))
    assert child_environment("view")["OVERGRID_RATE_HZ"] == "9"  # not nested: reads its own


def test_rmw_zenoh_runs_beside_the_rest_on_the_same_network() -> None:
    args = ["--rmw-zenoh", "--no-view", "--namespace", "site-a", "--listen", "tcp/127.0.0.1:7999"]
    commands = dict(child_commands(parse_settings(UpSettings, args, "overgrid up", "")))
    command, *child_args = commands["rmw_zenoh"]
    assert command == "rmw-zenoh"
    child = parse_settings(RmwZenohSettings, child_args, command, "")
    assert child.namespace == "site-a" and child.listen == []  # `up` alone listens
    assert "rmw_zenoh" not in dict(child_commands(parse_settings(UpSettings, [], "up", "")))


def test_depth_and_fusion_must_share_the_lattice(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as stopped:
        parse_settings(UpSettings, ["--depth.resolution-m", "0.1"], "overgrid up", "")
    assert stopped.value.code == 2
    err = capsys.readouterr().err
    assert "--depth.resolution-m" in err and "--fusion.grid.resolution-m" in err


def test_up_runs_without_the_page_when_aiohttp_is_missing(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setitem(sys.modules, "aiohttp", None)  # as if not installed
    settings = without_unservable_viewer(parse_settings(UpSettings, [], "overgrid up", ""))
    assert not settings.view and "viewer" not in dict(child_commands(settings))
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert "aiohttp" in line and "overgrid[view]" in line


def _children_of(namespace: str, command: str = "") -> list[str]:
    pattern = f"services.cli {command}.*--namespace {namespace}"
    result = subprocess.run(["pgrep", "-f", pattern], capture_output=True, text=True)
    return result.stdout.split()


def _page_url(up: subprocess.Popen[str]) -> str:
    """The live map's URL from ``up``'s first lines."""
    assert up.stdout is not None
    lines = [up.stdout.readline() for _ in range(2)]
    found = re.search(
        r"^the live map: (http://127\.0\.0\.1:\d+/(\?token=\w+)?)$", lines[1].rstrip("\n")
    )
    assert found, lines
    return found.group(1)


def _serves(url: str) -> bool:
    """Whether ``url`` answers 200 (the viewer says 503 while it has no map)."""
    try:
        with urllib.request.urlopen(url, timeout=5) as answer:
            return bool(answer.status == 200)
    except OSError:
        return False


def test_up_for_a_duration_writes_the_map_and_stops_every_child(bus: Bus, tmp_path: Path) -> None:
    # Nested flags reach the children: each would refuse to start on a flag it does not know.
    ros2 = ("--ros2", "--rmw-zenoh")
    up = _up(bus, tmp_path / "run", "--duration-s", "12", "--depth.summary-s", "5", *ros2)
    out, _ = up.communicate(timeout=180)
    assert up.returncode == 0, out
    assert "map v" in out and "p0" in out and "p1" in out  # progress lines
    meta, image = read_map_server(tmp_path / "run" / "map.yaml")
    assert meta["resolution"] == 0.05 and image.size > 10_000
    assert (image == 254).mean() > 0.2  # a real map: much free floor
    picture = decode_png((tmp_path / "run" / "map.png").read_bytes())
    assert picture.shape[1] >= 800
    assert (picture == PICTURE_COLORS["truth"]).all(axis=2).sum() > 1000  # truth outlines drawn
    report = json.loads((tmp_path / "run" / "report.json").read_text())
    # A sanity bound, not the targets (README): movers at 1.2–2 m/s seen at 2 Hz by two loaded
    # pairs leave a large overall false-free share; objects that stand still must read occupied.
    assert 0.2 < report["iou"] <= 1 and report["false_free_rate_static"] < 0.2, report
    assert report["false_free_rate"] < 0.5, report
    for key in (
        "precision",
        "recall",
        "false_free_rate_static",
        "unknown_fraction",
        "length_error_mean_pct",
    ):
        assert 0 <= report[key] < 100, key
    assert {"name", "true_length_m", "length_m", "width_m"} <= set(report["objects"][0])
    assert set(report["error_breakdown"]["false_occupied_cells"]) == {"edge", "near", "far"}
    assert report["capture_to_map_ms"]["n"] > 5 and report["capture_to_map_ms"]["p50"] > 0
    assert {"camera", "disparity", "model"} <= set(report["stage_ms"])
    assert "moving_appear_s" in report and "moving_clear_s" in report
    coverage = report["rig_coverage"]  # the floor the pairs see at heights over the band
    shares = list(coverage.values())
    assert list(coverage) == [f"{height:g}" for height in COVERAGE_HEIGHTS_M], coverage
    assert shares == sorted(shares, reverse=True) and 0 < shares[-1] < shares[0] <= 1, coverage
    run = report["over_run"]  # the maps recorded along the run, after its first third
    assert run["maps"] >= 3 and 0.2 < run["iou"] <= 1 and run["false_free_rate"] < 0.5, run
    ros2_log = (tmp_path / "run" / "logs" / "ros2.log").read_text()
    assert "msg=started" in ros2_log and "msg=stopped" in ros2_log, ros2_log  # --ros2 ran
    assert "terminate" not in ros2_log, ros2_log  # and stopped cleanly
    rmw_zenoh_log = (tmp_path / "run" / "logs" / "rmw_zenoh.log").read_text()
    assert "first map published" in rmw_zenoh_log, rmw_zenoh_log  # --rmw-zenoh ran
    assert "msg=stopped" in rmw_zenoh_log, rmw_zenoh_log
    assert _children_of(bus.namespace) == []


def test_sigint_during_up_still_saves_the_map(bus: Bus, tmp_path: Path) -> None:
    """… and the live map is at the URL ``up`` printed, and the viewer or a depth process dying
    ends nothing; and
    ``overgrid eval --json`` on the running system prints its report alone on standard output."""
    up = _up(bus, tmp_path / "run", env={"OVERGRID_TOKEN": "abcdefgh123"})
    url = _page_url(up)  # with the viewer's token, which it reads from the environment
    assert url.endswith("/?token=abcdefgh123"), url
    wait_for(lambda: _serves(url), 30, "the live map at the URL up printed")
    download = url.replace("/?", "/download/map.png?")
    wait_for(lambda: _serves(download), 60, "a map (the viewer has it)")
    assert not _serves(url.split("?")[0])  # the token is asked for
    scored = run_overgrid("eval", "--json", "--watch-s", "1", *bus.flags())
    assert scored.returncode == 0, scored.stderr
    assert 0 <= json.loads(scored.stdout)["iou"] <= 1
    assert "watching the stream for 1 s" in scored.stderr
    (viewer,) = _children_of(bus.namespace, "view")
    os.kill(int(viewer), signal.SIGKILL)
    (depth_p1,) = _children_of(bus.namespace, "depth --pair p1")
    os.kill(int(depth_p1), signal.SIGKILL)  # a pair gone, as on a site: started again

    def p1_again() -> bool:
        again = _children_of(bus.namespace, "depth --pair p1")
        return bool(again) and again != [depth_p1] and _alive(bus, "p1")

    wait_for(p1_again, 90, "a new depth process of p1, alive in fusion's health")
    wait_for(lambda: _serves(download), 60, "the viewer, started again, to serve the map")
    up.send_signal(signal.SIGINT)
    out, _ = up.communicate(timeout=60)
    assert up.returncode == 0, out
    assert out.count("viewer died (exit -9); started again") == 1, out
    assert out.count("depth_p1 died (exit -9); started again") == 1, out
    assert (tmp_path / "run" / "map.pgm").exists() and (tmp_path / "run" / "map.png").exists()
    assert _children_of(bus.namespace) == []


def _alive(bus: Bus, pair: str) -> bool:
    try:
        return bool(health(bus.session, timeout_s=2)["pairs"].get(pair, {}).get("alive"))
    except MapUnavailable:
        return False


def test_a_dying_child_is_reported_by_name(bus: Bus, tmp_path: Path) -> None:
    up = _up(bus, tmp_path / "run", "--no-view")
    wait_for(lambda: len(_children_of(bus.namespace, "camera-sim")) == 1, 60, "camera_sim")
    (camera_sim,) = _children_of(bus.namespace, "camera-sim")
    os.kill(int(camera_sim), signal.SIGKILL)
    out, _ = up.communicate(timeout=120)
    assert up.returncode == 1
    assert "camera_sim died (exit -9)" in out, out
    assert _children_of(bus.namespace) == []


@pytest.mark.parametrize(
    ("flag", "name"), [("--scene", "missing.yaml"), ("--config", "missing.json5")]
)
def test_a_missing_file_stops_up_before_any_process_starts(
    bus: Bus, tmp_path: Path, flag: str, name: str
) -> None:
    """One line naming the flag and the file, exit 2; no child started, nothing written (a child
    that died of it left ``up`` saving whatever map the state directory held)."""
    up = _up(bus, tmp_path / "run", flag, str(tmp_path / name))
    out, _ = up.communicate(timeout=60)
    assert up.returncode == 2, out
    assert "Traceback" not in out
    lines = out.strip().splitlines()
    assert len(lines) == 1 and flag in lines[0] and name in lines[0], out
    assert not (tmp_path / "run").exists()
    assert _children_of(bus.namespace) == []


def _health(cols: int, pairs: dict[str, int]) -> dict[str, object]:
    """Fusion's health answer as ``progress_line`` reads it: a map of ``cols`` × 10 cells, half
    known, and each pair's tiles so far."""
    return {
        "map": {"version": 3 if cols else 0, "cols": cols, "rows": 10, "known_cells": cols * 5},
        "pairs": {p: {"tiles": tiles, "alive": True} for p, tiles in pairs.items()},
        "tiles_accepted": sum(pairs.values()),
        "tiles_rejected": {},
    }


def test_the_progress_line_says_what_it_waits_for_and_what_its_known_share_is_of() -> None:
    """Before the first tile the line says the depth processes are starting (it read "map v0
    0×0 known 0%" for the first 18 s of a fresh run); then the known share names the map's
    cells, which the report's unknown share of the seen floor is not."""
    previous: dict[str, int] = {}
    waiting = progress_line(_health(0, {}), previous, 2.0, 1.0)
    assert "no tile yet" in waiting and "map v0" not in waiting and "no depth process" in waiting
    running = progress_line(_health(20, {"p0": 4, "p1": 2}), previous, 3.0, 1.0, iou=0.8)
    assert "map v3 20×10, 50% of its cells known" in running
    assert "p0 4.0/s" in running and "p1 2.0/s" in running and "IoU 0.800" in running
