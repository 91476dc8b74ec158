import json
import subprocess
import sys
from pathlib import Path

import pytest
import zenoh

from common import zenoh_session
from common.sensor_model import SensorModelParams
from common.settings import ZenohSettings, load_settings, parse_settings
from services.camera_sim.settings import CameraSimSettings
from services.depth.settings import DepthSettings
from services.depth.stereo import MatcherConfig
from services.fusion.params import GridParams
from services.fusion.settings import FusionSettings
from tests.conftest import run_overgrid


def test_bad_value_names_the_flag_and_env_var(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as stopped:
        load_settings(CameraSimSettings, rate_hz="-1")
    assert stopped.value.code == 2
    err = capsys.readouterr().err
    assert (
        "--rate-hz" in err and "OVERGRID_RATE_HZ" in err and "greater than or equal to 0.01" in err
    )


def test_env_var_is_read_and_validated(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv("OVERGRID_RIG__PAIR_COUNT", "6")
    monkeypatch.setenv("OVERGRID_PAIRS", "p1,p5")
    settings = load_settings(CameraSimSettings)
    assert settings.rig.pair_count == 6 and settings.pairs == ["p1", "p5"]
    monkeypatch.setenv("OVERGRID_MODE", "satellite")
    with pytest.raises(SystemExit):
        load_settings(CameraSimSettings)
    assert "--mode" in capsys.readouterr().err


def test_cross_setting_check_names_both_settings(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        load_settings(CameraSimSettings, rig={"pair_count": 2}, pairs=["p3"])
    err = capsys.readouterr().err
    assert "--pairs" in err and "--pair-count" in err


def test_cli_rejects_bad_setting_at_start_up() -> None:
    result = subprocess.run(
        [sys.executable, "-m", "services.cli", "camera-sim", "--width-px", "abc"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 2
    assert "--width-px" in result.stderr and "OVERGRID_RIG__WIDTH_PX" in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1, result.stderr


def test_nested_parameters_take_flat_and_nested_flags_and_env(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The algorithms' own parameter objects come out of the flags: their defaults are theirs."""
    monkeypatch.setenv("OVERGRID_MODEL__P_MISS", "0.2")
    settings = parse_settings(
        DepthSettings,
        [
            "--pair",
            "p1",
            "--p-hit",
            "0.8",
            "--matcher.block-size",
            "5",
            "--no-subpixel",
            "--no-low-band",
        ],
        "overgrid depth",
        "",
    )
    assert settings.model == SensorModelParams(p_hit=0.8, p_miss=0.2)
    assert settings.matcher == MatcherConfig(block_size=5, subpixel=False)
    assert settings.pipeline_config().model is settings.model
    assert not settings.pipeline_config().low_band
    assert parse_settings(DepthSettings, ["--pair", "p1"], "", "").pipeline_config().low_band
    defaults = parse_settings(FusionSettings, [], "overgrid fusion", "")
    assert defaults.grid_params() == GridParams()
    fusion = parse_settings(
        FusionSettings,
        ["--decay-after-s", "3", "--grid.resolution-m", "0.1", "--bounds", "0,0,10,5"],
        "overgrid fusion",
        "",
    )
    params = fusion.grid_params()
    assert params.decay_after_s == 3.0 and params.resolution_m == 0.1
    assert params.bounds is not None and (params.bounds.cols, params.bounds.rows) == (100, 50)


@pytest.mark.parametrize(
    ("args", "names"),
    [
        (["--p-hit", "0.3"], ["--p-hit", "--model.p-hit", "OVERGRID_MODEL__P_HIT"]),
        (
            ["--free-share-max", "1.5"],
            ["--free-share-max", "--model.free-share-max", "OVERGRID_MODEL__FREE_SHARE_MAX"],
        ),
        (["--block-size", "4"], ["--matcher", "OVERGRID_MATCHER", "odd"]),
        (["--obstacle-min-m", "3"], ["--model", "obstacle_min_m"]),
        (["--downscale", "3"], ["--downscale", "OVERGRID_DOWNSCALE"]),
        (["--no-such-flag", "1"], ["--no-such-flag"]),
    ],
)
def test_bad_nested_value_or_unknown_flag_is_one_line(
    capsys: pytest.CaptureFixture[str], args: list[str], names: list[str]
) -> None:
    with pytest.raises(SystemExit) as stopped:
        parse_settings(DepthSettings, ["--pair", "p0", *args], "overgrid depth", "")
    assert stopped.value.code == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1, err
    for name in names:
        assert name in err, err


def test_bounds_over_the_cell_limit_fail_at_start_up(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        parse_settings(FusionSettings, ["--bounds", "0,0,500,500"], "overgrid fusion", "")
    assert "--bounds" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        parse_settings(FusionSettings, ["--bounds", "nan,0,1,1"], "overgrid fusion", "")
    assert "--bounds" in capsys.readouterr().err


def test_undecodable_nested_env_var_is_named(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv("OVERGRID_MODEL", "{p_hit")
    with pytest.raises(SystemExit) as stopped:
        load_settings(DepthSettings, pair="p0")
    assert stopped.value.code == 2
    err = capsys.readouterr().err
    assert "OVERGRID_MODEL" in err and len(err.strip().splitlines()) == 1


def test_a_session_that_times_out_closing_ends_with_a_warning_not_a_traceback(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """zenoh's "close operation timed out!" at the end of a recording ended a depth process with
    a traceback and exit 1, its last log line lost."""
    real_open = zenoh.open
    closed: list[bool] = []

    class TimesOutClosing:
        def __init__(self, session: zenoh.Session) -> None:
            self.session = session

        def close(self) -> None:
            self.session.close()  # type: ignore[no-untyped-call]
            closed.append(True)
            raise zenoh.ZError("close operation timed out!")

    monkeypatch.setattr(zenoh, "open", lambda config: TimesOutClosing(real_open(config)))
    settings = ZenohSettings(no_multicast_scouting=True, namespace="test_close_timeout")
    with caplog.at_level("WARNING"), zenoh_session.open_session(settings):
        pass
    assert closed and "session close failed" in caplog.text


def test_help_names_types_as_a_user_types_them() -> None:
    shown = run_overgrid("fusion", "--help")
    assert shown.returncode == 0, shown.stderr
    assert "--config Path" in shown.stdout and "--mode {peer,client,router}" in shown.stdout
    assert "null" not in shown.stdout.replace("(default: null)", "")
    # A flag that switches something off reads as one: never "--no-no-multicast-scouting".
    assert "--no-multicast-scouting" in shown.stdout and "--no-no-" not in shown.stdout


def test_an_empty_namespace_is_none(monkeypatch: pytest.MonkeyPatch) -> None:
    """A deployment template's NS=${NS:-} gives OVERGRID_NAMESPACE=''; it stays no namespace."""
    monkeypatch.setenv("OVERGRID_NAMESPACE", "")
    assert ZenohSettings().namespace is None
    assert ZenohSettings(namespace="site1/hall_2").namespace == "site1/hall_2"


def test_a_session_tries_its_lost_router_again_within_half_a_second(tmp_path: Path) -> None:
    """Zenoh's own default retried 1, 3, 7 s after the loss: a router restarted by systemd kept
    every box off the map for 7 s. A config file's own ``connect/retry`` is kept."""
    config = zenoh_session.zenoh_config(ZenohSettings())
    retry = json.loads(config.get_json("connect/retry"))
    assert retry["period_init_ms"] <= 100 and retry["period_max_ms"] <= 500
    own = tmp_path / "own.json5"
    own.write_text("{ connect: { retry: { period_init_ms: 2000, period_max_ms: 8000 } } }")
    kept = zenoh_session.zenoh_config(ZenohSettings(config=own))
    assert json.loads(kept.get_json("connect/retry"))["period_init_ms"] == 2000
