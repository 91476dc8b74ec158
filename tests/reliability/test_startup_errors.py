"""Bad settings and files stop start-up with one line that names them (exit 2), never a traceback;
bad queries to the simulator get an error reply, never silence."""

import os
import socket
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import yaml
import zenoh

from common import keys
from services.camera_sim.rig import RigSpec, layout_pairs
from tests.conftest import Bus, assert_one_line_exit_2, free_port, run_overgrid

pytestmark = pytest.mark.process


@pytest.mark.parametrize(
    ("text", "says"),
    [
        ('{ mode: "bogus" }', "bogus"),
        ("{ mode: ", "expected"),
        ("{ connect: 7 }", ""),
        # A comma missing: the parser's pointer came as "--> 2:9 2 | mode: \"client\" expected …".
        ('{\n  mode: "client"\n  scouting: {}\n}', "not valid JSON5 at line 2, column 9"),
    ],
)
def test_a_bad_zenoh_config_file_is_named(tmp_path: Path, text: str, says: str) -> None:
    config = tmp_path / "zenoh.json5"
    config.write_text(text)
    assert_one_line_exit_2(run_overgrid("health", "--config", str(config)), str(config), says)


SERVICES = [("depth", "--pair", "p0"), ("camera-sim", "--frames", "1")]


@pytest.mark.parametrize("service", SERVICES, ids=lambda s: s[0])
@pytest.mark.parametrize(
    ("text", "says"), [('{ mode: "bogus" }', "bogus"), ("{ mode: ", "expected")]
)
def test_the_services_name_a_bad_zenoh_config_file(
    tmp_path: Path, service: tuple[str, ...], text: str, says: str
) -> None:
    config = tmp_path / "zenoh.json5"
    config.write_text(text)
    assert_one_line_exit_2(run_overgrid(*service, "--config", str(config)), str(config), says)


@pytest.mark.parametrize("service", SERVICES, ids=lambda s: s[0])
def test_the_services_name_a_bad_mode_and_a_port_in_use(service: tuple[str, ...]) -> None:
    assert_one_line_exit_2(run_overgrid(*service, "--mode", "bogus"), "--mode", "bogus")
    port = free_port()
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", port))
        taken.listen()
        result = run_overgrid(
            *service, "--listen", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting"
        )
    assert_one_line_exit_2(result, f"127.0.0.1:{port}", "in use")


@pytest.mark.parametrize("resolution", ["0.001", "1e-300", "nan", "inf"])
def test_a_depth_resolution_no_camera_resolves_is_refused(resolution: str) -> None:
    result = run_overgrid("depth", "--pair", "p0", "--resolution-m", resolution)
    assert_one_line_exit_2(result, "resolution", resolution)


def test_a_missing_zenoh_config_file_is_named(tmp_path: Path) -> None:
    missing = tmp_path / "missing.json5"
    assert_one_line_exit_2(
        run_overgrid("health", "--config", str(missing)), str(missing), "no such file"
    )


def test_a_malformed_endpoint_and_a_port_in_use_are_reported() -> None:
    assert_one_line_exit_2(run_overgrid("health", "--connect", "nonsense"), "nonsense")
    port = free_port()
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", port))
        taken.listen()
        result = run_overgrid(
            "router", "--listen", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting"
        )
    assert_one_line_exit_2(result, f"127.0.0.1:{port}", "in use")


@pytest.mark.parametrize("text", ["objects: [", "floor: marble", "objects: 3"])
def test_a_bad_scene_file_is_named(tmp_path: Path, text: str) -> None:
    scene = tmp_path / "scene.yaml"
    scene.write_text(text)
    assert_one_line_exit_2(
        run_overgrid("camera-sim", "--scene", str(scene), "--frames", "1"), str(scene)
    )


def test_truth_queries_with_impossible_times_or_bands_get_an_error_reply(bus: Bus) -> None:
    bus.start("camera-sim", "--pair-count", "1", "--rate-hz", "1", "--frames", "60")
    for parameters, names in (
        ("t=inf", "t=inf"),
        ("t=nan", "t=nan"),
        ("t=-1", "t=-1"),
        ("t=garbage", "t='garbage'"),
        ("t=1e300", "t=1e300"),
        ("stamp_ns=-5", "stamp_ns='-5'"),
        ("stamp_ns=1.5", "stamp_ns='1.5'"),
        ("band=nan,1", "band=nan"),
        ("band=2,1", "band=2,1"),
        ("resolution=1e-300", "resolution=1e-300"),
        ("resolution=x", "resolution='x'"),
        ("colour=red", "'colour'"),
    ):
        replies: list[zenoh.Reply] = []
        deadline = time.monotonic() + 60
        while not replies and time.monotonic() < deadline:  # until the simulator is up
            replies = list(bus.session.get(f"{keys.SIM_TRUTH}?{parameters}", timeout=5.0))
            time.sleep(0.2)
        assert len(replies) == 1, parameters
        assert replies[0].err is not None, parameters
        assert "sim/truth" in replies[0].err.payload.to_string()
        assert names in replies[0].err.payload.to_string(), replies[0].err.payload.to_string()
    # Queries on wildcards and with parameters the calibration ignores are answered too.
    for selector in ("sim/*?resolution=0.5", "**?stamp_ns=1;resolution=0.5"):
        replies = [
            r
            for r in bus.session.get(selector, timeout=5.0)
            if str(r.ok and r.ok.key_expr) == "sim/truth"
        ]
        assert len(replies) == 1 and replies[0].ok is not None, selector
    replies = list(bus.session.get("cam/*/calib?t=inf;garbage", timeout=5.0))
    assert [str(r.ok.key_expr) for r in replies if r.ok is not None] == [keys.calib("p0")]


CAMERA = "{width: 640, height: 480, K: [[554, 0, 319.5], [0, 554, 239.5], [0, 0, 1]], T_world_cam: "


@pytest.mark.parametrize(
    ("text", "says"),
    [
        ("pair: p0\nleft: {width: 640", "expected"),
        (
            f"pair: p0\nleft: {CAMERA}[[1,0,0,0],[0,1,0,0],[0,0,1,6],[0,0,0,1]], dist: [.nan, 0, 0, 0, 0]}}\n"
            f"right: {CAMERA}[[1,0,0,0.5],[0,1,0,0],[0,0,1,6],[0,0,0,1]]}}\n",
            "NaN",
        ),
        ("pair: p0\n", "left"),
    ],
)
def test_a_bad_calibration_file_is_named(tmp_path: Path, text: str, says: str) -> None:
    calib = tmp_path / "calib.yaml"
    calib.write_text(text)
    assert_one_line_exit_2(
        run_overgrid("depth", "--pair", "p0", "--calib", str(calib)), str(calib), says
    )
    missing = tmp_path / "missing.yaml"
    assert_one_line_exit_2(
        run_overgrid("depth", "--pair", "p0", "--calib", str(missing)), str(missing)
    )


def test_a_recording_that_is_not_there_is_named(tmp_path: Path) -> None:
    pipe = tmp_path / "pipe"
    os.mkfifo(pipe)  # reading it blocked the start past SIGTERM
    # Missing; a folder without image pairs; a pipe.
    for source in (tmp_path / "nonexistent", tmp_path, pipe):
        result = run_overgrid("depth", "--pair", "p0", "--images", str(source))
        assert_one_line_exit_2(result, f"--images {source}")


def test_a_file_setting_that_is_a_pipe_or_nested_too_deep_is_refused(tmp_path: Path) -> None:
    """A pipe named as a file blocked the start past SIGTERM; YAML 600 levels deep ended in a
    RecursionError's 3000 lines, a Zenoh config's brackets 60,000 deep in a crash (SIGSEGV)."""
    pipe, deep_yaml, deep_json5 = tmp_path / "pipe", tmp_path / "deep.yaml", tmp_path / "z.json5"
    os.mkfifo(pipe)
    deep_yaml.write_text("".join("  " * level + "a:\n" for level in range(600)))
    deep_json5.write_text("[" * 60_000)
    for args, says in [
        (("health", "--config", str(pipe)), "not a regular file"),
        (("health", "--config", str(deep_json5)), "nested 60000 deep"),
        (("health", "--config", str(tmp_path)), "not a regular file"),
        (("depth", "--pair", "p0", "--calib", str(pipe)), "not a regular file"),
        (("depth", "--pair", "p0", "--calib", str(deep_yaml)), "nested too deep"),
        (("camera-sim", "--scene", str(deep_yaml)), "nested too deep"),
        (("camera-sim", "--scene", str(pipe)), "not a regular file"),
    ]:
        assert_one_line_exit_2(run_overgrid(*args), args[-1], says)


@pytest.mark.parametrize(
    ("flag", "value", "says"),
    [
        ("--namespace", "site/*", "wildcard"),
        ("--namespace", "site//a", "empty chunk"),
        ("--connect", "tcp/127.0.0.1:99999", "port"),
        ("--connect", "tcp/[::1", "host"),
        ("--listen", "tcp/", "PROTOCOL/HOST:PORT"),
    ],
)
def test_a_namespace_or_endpoint_zenoh_cannot_use_is_refused(
    flag: str, value: str, says: str
) -> None:
    """Zenoh's own error for a wildcard namespace named neither the flag nor the value; in peer
    mode an endpoint of port 99999 or an open bracket started a service that never connected.
    (An empty namespace is none: a template's NS=${NS:-}.)"""
    assert_one_line_exit_2(run_overgrid("fusion", f"{flag}={value}"), flag, says)


@pytest.mark.parametrize(
    ("change", "says"),
    [
        (lambda d: d["right"]["T_world_cam"][0].__setitem__(3, 1000.0), "disparities"),  # baseline
        (lambda d: d["left"].__setitem__("dist", [0, 0, 0, 0, 100.0]), "disparities"),  # k3
        (lambda d: d["left"].__setitem__("dist", [-100.0, 0, 0, 0, 0]), "not invertible"),  # k1
        (lambda d: d["left"]["K"][0].__setitem__(2, 1e9), "principal point"),
        (lambda d: d["left"]["K"][0].__setitem__(0, 1e-9), "field of view"),  # focal 1e-9 px
        (
            lambda d: [
                d[side].update(
                    width=16384, height=16384, K=[[554, 0, 8191.5], [0, 554, 8191.5], [0, 0, 1]]
                )
                for side in ("left", "right")
            ],
            "pixels",
        ),
        (lambda d: d["left"].__setitem__("width", 1_000_000), "width"),
    ],
)
def test_a_calibration_of_absurd_geometry_is_refused_at_start(
    tmp_path: Path, change: Callable[[dict[str, Any]], None], says: str
) -> None:
    calib = layout_pairs(RigSpec(pair_count=1), (12.0, 10.0))[0].model_dump()
    calib["right"]["dist"] = calib["left"]["dist"] = [0.0] * 5
    change(calib)
    path = tmp_path / "calib.yaml"
    path.write_text(yaml.safe_dump(calib))
    assert_one_line_exit_2(
        run_overgrid("depth", "--pair", "p0", "--calib", str(path)),
        str(path),
        says,
    )


@pytest.mark.parametrize(
    "args",
    [
        ("camera-sim", "--rate-hz", "1e-300"),
        ("camera-sim", "--light-step-period-s", "1e-300"),
        ("depth", "--pair", "p0", "--matcher.speckle-window", "2147483648"),
        ("depth", "--pair", "p0", "--max-message-mb", "inf"),
        ("fusion", "--max-tile-age-s", "inf"),
        ("up", "--fusion.max-tile-age-s", "nan"),
        ("save-frame", "--timeout-s", "1e300"),
        ("depth", "--pair", "p0", "--model.obstacle-max-m", "inf"),  # blamed on the calibration
        ("depth", "--pair", "p0", "--matcher.edge-filter-px", "nan"),
    ],
    ids=lambda args: " ".join(args[-2:]),
)
def test_a_number_setting_no_service_can_run_with_is_refused(args: tuple[str, ...]) -> None:
    """Infinite, NaN and absurd numbers: each ended in an OverflowError or OpenCV's "integer
    won't fit into a C int" traceback (blamed on the calibration file), or, under ``up``, in a
    child's death after the others had started."""
    assert_one_line_exit_2(run_overgrid(*args), args[-2].removeprefix("--fusion."))
