"""The shipped deploy files stay in step with the code: unit commands parse, configs load."""

import shlex
from pathlib import Path

import pytest
import zenoh

from common.settings import parse_settings
from services.camera_sim.service import CameraSimSettings
from services.depth.service import DepthSettings
from services.fusion.service import FusionSettings
from services.router import RouterSettings
from tests.conftest import REPO

SETTINGS = {
    "router": RouterSettings,
    "fusion": FusionSettings,
    "depth": DepthSettings,
    "camera-sim": CameraSimSettings,
}


@pytest.mark.parametrize("unit", sorted((REPO / "deploy" / "systemd").glob("*.service")))
def test_systemd_units_run_commands_that_parse(unit: Path, tmp_path: Path) -> None:
    exec_start = next(
        line.split("=", 1)[1]
        for line in unit.read_text().splitlines()
        if line.startswith("ExecStart=")
    )
    words = shlex.split(exec_start.replace("%i", "p0").replace("${STATE_DIRECTORY}", str(tmp_path)))
    assert words[0].endswith("/overgrid")
    command, args = words[1], words[2:]
    settings_cls = SETTINGS[command]
    settings = parse_settings(settings_cls, args, command, "")
    assert settings.config is not None and settings.config.name.endswith(".json5")


@pytest.mark.parametrize("name", ["router.json5", "client.json5"])
def test_zenoh_configs_load(name: str) -> None:
    zenoh.Config.from_file(str(REPO / "deploy" / "zenoh" / name))
