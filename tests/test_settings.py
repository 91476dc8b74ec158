import subprocess
import sys

import pytest

from common.settings import load_settings
from services.camera_sim.service import CameraSimSettings


def test_bad_value_names_the_flag_and_env_var(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as stopped:
        load_settings(CameraSimSettings, rate_hz="-1")
    assert stopped.value.code == 2
    err = capsys.readouterr().err
    assert "--rate-hz" in err and "OVERGRID_RATE_HZ" in err and "greater than 0" in err


def test_env_var_is_read_and_validated(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv("OVERGRID_PAIR_COUNT", "6")
    monkeypatch.setenv("OVERGRID_PAIRS", "p1,p5")
    settings = load_settings(CameraSimSettings)
    assert settings.pair_count == 6 and settings.pairs == ["p1", "p5"]
    monkeypatch.setenv("OVERGRID_MODE", "satellite")
    with pytest.raises(SystemExit):
        load_settings(CameraSimSettings)
    assert "--mode" in capsys.readouterr().err


def test_cross_setting_check_names_both_settings(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        load_settings(CameraSimSettings, pair_count=2, pairs=["p3"])
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
    assert "--width-px" in result.stderr
