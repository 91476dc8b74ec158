"""A state directory fusion cannot use stops it at start-up with one line naming it (exit 2), never
"serves, then dies at the first save"; a corrupt state in a usable one is set aside, the map
starts empty and the error is logged."""

import os
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

from common.client import health, latest
from common.codec import WIRE_ENCODING
from common.lattice import Window
from services.fusion.persistence import CHUNK_LOG
from tests.conftest import Bus, assert_one_line_exit_2, fusion_answers, run_overgrid, wait_for
from tests.tiles import tile_payload

pytestmark = pytest.mark.process


def _fusion(*args: str) -> subprocess.CompletedProcess[str]:
    return run_overgrid("fusion", "--no-multicast-scouting", *args)


@pytest.fixture
def read_only(tmp_path: Path) -> Iterator[Path]:
    """A directory nobody can write to, root included (root ignores modes: the immutable flag)."""
    directory = tmp_path / "read-only"
    directory.mkdir()
    (directory / CHUNK_LOG).write_bytes(b"a corrupt state log")
    if os.geteuid() == 0:
        if subprocess.run(["chattr", "+i", str(directory)], capture_output=True).returncode:
            pytest.skip("cannot make a directory read-only for root here (chattr)")
        try:
            yield directory
        finally:
            subprocess.run(["chattr", "-i", str(directory)], check=True)
    else:
        directory.chmod(0o555)
        try:
            yield directory
        finally:
            directory.chmod(0o755)


def test_a_state_dir_that_is_a_file_is_named(tmp_path: Path) -> None:
    path = tmp_path / "state"
    path.write_text("not a directory")
    assert_one_line_exit_2(
        _fusion("--state-dir", str(path)), f"--state-dir {path}", "not a directory"
    )
    assert_one_line_exit_2(
        _fusion("--state-dir", str(path / "below")), f"--state-dir {path / 'below'}"
    )


def test_a_read_only_state_dir_with_a_corrupt_state_is_named(read_only: Path) -> None:
    assert_one_line_exit_2(
        _fusion("--state-dir", str(read_only)), f"--state-dir {read_only}", "writable"
    )


def test_bounds_over_the_cell_limit_are_a_start_up_error(tmp_path: Path) -> None:
    result = _fusion("--state-dir", str(tmp_path), "--bounds", "0,0,500,500")  # 10⁸ cells
    assert_one_line_exit_2(result, "--bounds", "--max-cells")


def test_a_corrupt_state_is_set_aside_and_the_map_starts_empty(bus: Bus, tmp_path: Path) -> None:
    state = tmp_path / "state"
    state.mkdir()
    (state / CHUNK_LOG).write_bytes(b"\x00garbage" * 100)
    log_path = tmp_path / "fusion.log"
    bus.start("fusion", "--state-dir", str(state), "--save-interval-s", "0.2", log_path=log_path)
    wait_for(lambda: fusion_answers(bus), 60, "fusion up")
    assert health(bus.session)["map"]["known_cells"] == 0
    assert "state unusable, set aside" in log_path.read_text()
    assert len(list(state.glob(f"{CHUNK_LOG}.corrupt-*"))) == 1
    publisher = bus.session.declare_publisher("depth/p0/tile", encoding=WIRE_ENCODING)
    publisher.put(tile_payload("p0", Window(0, 0, 8, 8), 1.0))
    wait_for(lambda: latest(bus.session).version == 1, 10, "a tile after the bad state")
    wait_for(
        lambda: health(bus.session)["state"]["saved_version"] == 1, 10, "it is saved: the dir works"
    )
