"""``overgrid up`` runs the whole system as real processes and leaves nothing behind."""

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from common.mapfiles import read_map_server
from common.png import decode_png
from tests.conftest import REPO, Bus, wait_for

pytestmark = pytest.mark.process


def _up(bus: Bus, out: Path, *args: str) -> subprocess.Popen[str]:
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
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


def _children_of(namespace: str) -> list[str]:
    result = subprocess.run(
        ["pgrep", "-f", f"--namespace {namespace}"], capture_output=True, text=True
    )
    return result.stdout.split()


def test_up_for_a_duration_writes_the_map_and_stops_every_child(bus: Bus, tmp_path: Path) -> None:
    up = _up(bus, tmp_path / "run", "--duration-s", "12")
    out, _ = up.communicate(timeout=180)
    assert up.returncode == 0, out
    assert "map v" in out and "p0" in out and "p1" in out  # progress lines
    meta, image = read_map_server(tmp_path / "run" / "map.yaml")
    assert meta["resolution"] == 0.05 and image.size > 10_000
    assert (image == 254).mean() > 0.2  # a real map: much free floor
    assert decode_png((tmp_path / "run" / "map.png").read_bytes()).shape[1] >= 800
    assert (tmp_path / "run" / "report.json").exists()
    assert _children_of(bus.namespace) == []


def test_sigint_during_up_still_saves_the_map(bus: Bus, tmp_path: Path) -> None:
    up = _up(bus, tmp_path / "run")
    wait_for(
        lambda: (tmp_path / "run" / "logs" / "fusion.log").exists(), 30, "up to start its children"
    )
    time.sleep(10)
    up.send_signal(signal.SIGINT)
    out, _ = up.communicate(timeout=60)
    assert up.returncode == 0, out
    assert (tmp_path / "run" / "map.pgm").exists() and (tmp_path / "run" / "map.png").exists()
    assert _children_of(bus.namespace) == []


def test_a_dying_child_is_reported_by_name(bus: Bus, tmp_path: Path) -> None:
    up = _up(bus, tmp_path / "run", "--scene", str(tmp_path / "missing.yaml"))
    out, _ = up.communicate(timeout=120)
    assert up.returncode == 1
    assert "camera_sim died" in out and "missing.yaml" in out
    assert _children_of(bus.namespace) == []
