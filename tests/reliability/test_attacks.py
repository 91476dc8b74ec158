"""Attacks of issue 14 that no other reliability test covers, each against a real process."""

import pytest

from tests.conftest import assert_one_line_exit_2, run_overgrid

pytestmark = pytest.mark.process


@pytest.mark.parametrize("bounds", ["0,0,1e300,1e300", "1e19,0,1.00001e19,1", "-1e300,-1e300,0,0"])
def test_bounds_past_the_lattice_are_a_start_up_error(bounds: str) -> None:
    """1e300 m wrapped the int64 cell indices into a 0×0 window that passed the cell limit: fusion
    started with a map no tile could land in."""
    result = run_overgrid(
        "fusion",
        f"--bounds={bounds}",
        "--no-multicast-scouting",
        *("--namespace", "attacks-bounds", "--connect", "tcp/127.0.0.1:9"),
    )
    assert_one_line_exit_2(result, "--bounds")
