"""``overgrid map get``, ``health`` and ``objects`` as a person runs them: a bad flag is one line
naming it (exit 2) before any network; a map the service cannot serve, or an answer that does not
decode, is one line saying why, never a traceback."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import zenoh

from common.lattice import Window
from services.client_cli import health_lines
from tests.conftest import REPO, Bus, assert_one_line_exit_2, run_overgrid
from tests.test_ros2_native import start_fusion_with_a_tile


def map_get(*args: str, cwd: Path = REPO) -> subprocess.CompletedProcess[str]:
    return run_overgrid("map", "get", *args, cwd=cwd)


@pytest.mark.parametrize(
    ("args", "flag", "reason"),
    [
        (("--region", "a,b,c,d"), "--region", "four numbers"),
        (("--region", "1,2,3"), "--region", "four numbers"),
        (("--region", "0,0,inf,1"), "--region", "finite"),
        (("--region", "nan,0,1,1"), "--region", "finite"),
        (("--region", "1,0,0,1"), "--region", "x1 > x0"),
        (("-o", "m.txt"), "--out", "unknown map file type '.txt'"),
    ],
)
def test_a_bad_flag_is_one_line_naming_it(
    tmp_path: Path, args: tuple[str, ...], flag: str, reason: str
) -> None:
    done = map_get(*args, "--no-multicast-scouting", "--timeout-s", "0.5", cwd=tmp_path)
    assert_one_line_exit_2(done, flag, reason)
    assert done.stderr.count("got ") <= 1  # the value once ("got '0,0,1' (got '0,0,1')")
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize(
    "command", [("health",), ("objects",), ("map", "get"), ("eval",)], ids=" ".join
)
@pytest.mark.parametrize("timeout", ["inf", "1e300"])
def test_a_timeout_zenoh_refuses_is_one_line_naming_it(
    command: tuple[str, ...], timeout: str
) -> None:
    """Zenoh's "negative timeout" ValueError traceback, once a query was made."""
    done = run_overgrid(*command, "--timeout-s", timeout, "--no-multicast-scouting")
    assert_one_line_exit_2(done, "--timeout-s")


ODD_ANSWERS: dict[str, list[str | bytes]] = {
    "map/health": ["[1, 2]", '"text"', "NaN", '{"pairs": 5}', '{"map": null}', "[" * 100_000],
    "map/latest": [b"\x81\xa1v\x02"],
}


@pytest.mark.process
def test_an_answer_that_does_not_decode_is_one_line(bus: Bus, tmp_path: Path) -> None:
    """A forged or other-version fusion: ``health`` ended in JSONDecodeError, KeyError,
    TypeError or RecursionError tracebacks, ``map get`` in a CodecError one."""
    answer: list[str | bytes] = [""]

    def reply(query: zenoh.Query) -> None:
        query.reply(str(query.key_expr), answer[0])

    queryables = [bus.session.declare_queryable(key, reply) for key in ODD_ANSWERS]
    for key, answers in ODD_ANSWERS.items():
        command = (
            ("health",) if key == "map/health" else ("map", "get", "-o", str(tmp_path / "m.png"))
        )
        for answer[0] in answers:
            done = run_overgrid(*command, "--timeout-s", "5", *bus.flags())
            lines = done.stderr.strip().splitlines()
            assert done.returncode == 1 and len(lines) == 1, (answer[0][:20], done.stderr[-2000:])
            assert "Traceback" not in done.stderr and not done.stdout
    for queryable in queryables:
        queryable.undeclare()  # type: ignore[no-untyped-call]


@pytest.mark.process
def test_a_region_off_the_map_is_one_line_saying_so(bus: Bus, tmp_path: Path) -> None:
    start_fusion_with_a_tile(bus, tmp_path, Window(0, 0, 20, 20))
    out = tmp_path / "part.png"
    done = map_get("-o", str(out), "--region", "100,100,101,101", *bus.flags())
    assert done.returncode != 0 and not out.exists()
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "does not overlap the map" in lines[0], done.stderr
    done = map_get("-o", str(out), "--region=-1,-1,0.5,0.5", *bus.flags())
    assert done.returncode == 0, done.stderr
    assert out.read_bytes().startswith(b"\x89PNG")


def test_map_help_is_its_usage_on_standard_output() -> None:
    done = run_overgrid("map", "--help")
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("usage: overgrid map get -o FILE") and not done.stderr
    done = run_overgrid("map")
    assert done.returncode == 2 and done.stderr.startswith("usage: overgrid map get")


def test_a_reader_that_leaves_ends_the_command_without_a_traceback() -> None:
    """``overgrid objects | head``: the pipe closes before the command has written."""
    command = subprocess.Popen(
        [sys.executable, "-m", "services.cli", "map", "--help"],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert command.stdout is not None and command.stderr is not None
    command.stdout.close()
    assert command.wait(timeout=60) == 1
    assert command.stderr.read() == ""


def _health_answer(
    capture_age_s: float | None, tile_age_s: float, alive: bool, stale_after_s: float = 5.0
) -> dict[str, Any]:
    row = {
        "alive": alive,
        "processes": ["a"] if alive else [],
        "conflict": False,
        "tiles": 40,
        "last_tile_age_s": tile_age_s,
        "capture_to_fused_ms": 90.0,
        "lagging": False,
        "rejected": 0,
        "detections_rejected": 0,
        "detections_late": 2,
    }
    return {
        "pairs": {"p0": row},
        "tiles_accepted": 40,
        "tiles_rejected": {},
        "map": {
            "epoch": 1,
            "version": 9,
            "cols": 8,
            "rows": 8,
            "resolution_m": 0.05,
            "origin_m": [0.0, 0.0],
            "known_cells": 64,
            "chunks": 1,
            "capture_age_s": capture_age_s,
            "stale_after_s": stale_after_s,
        },
        "state": {},
    }


def test_health_says_a_stale_map_and_a_live_pair_without_tiles() -> None:
    """Every camera gone: each pair read "alive yes" with nothing in its note, and a person had
    to read the ages to see the map was stale."""
    stale = "\n".join(health_lines(_health_answer(15.7, 15.7, alive=True)))
    assert "newest capture 15.7 s ago  STALE" in stale
    assert "NO TILE FOR 16 s" in stale and "2 detections late" in stale
    fresh = "\n".join(health_lines(_health_answer(0.4, 0.4, alive=True)))
    assert "STALE" not in fresh and "NO TILE" not in fresh
    gone = "\n".join(health_lines(_health_answer(15.7, 15.7, alive=False)))
    assert "NO TILE" not in gone and "p0        NO" in gone  # a dead pair says so already
    assert "no capture yet" in "\n".join(health_lines(_health_answer(None, 0.0, alive=True)))
    patient = "\n".join(health_lines(_health_answer(15.7, 15.7, True, stale_after_s=30.0)))
    assert "STALE" not in patient and "NO TILE" not in patient  # fusion's --decay-after-s 30
