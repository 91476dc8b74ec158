"""``overgrid up``: the whole system on this box — camera_sim, one depth process per pair, fusion —
as separate OS processes that find each other by scouting; progress while it runs; map files at the
end; every child stopped, none left behind."""

from __future__ import annotations

import importlib.util
import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np
import numpy.typing as npt
import zenoh
from pydantic import BaseModel, Field, model_validator
from pydantic_settings import CliApp, SettingsConfigDict

from common.client import MapUnavailable, health, latest
from common.codec import CodecError
from common.lattice import reframe
from common.lifecycle import stop_on_signals
from common.mapfiles import write_map
from common.occupancy_map import OccupancyMap
from common.settings import ENV_PREFIX, ZenohSettings, parse_settings
from common.zenoh_session import open_session, zenoh_config
from services.camera_sim.settings import CameraSimParams
from services.depth.settings import DepthParams
from services.evaluation.service import Evaluator, Recorder, map_summary
from services.evaluation.service import report as evaluation_report
from services.evaluation.service import table as evaluation_table
from services.fusion.settings import FusionParams
from services.viewer.address import DEFAULT_HTTP_HOST, DEFAULT_HTTP_PORT, available_port, page_url

STOP_TIMEOUT_S = 10.0
LOG_TAIL_LINES = 15
ESSENTIAL_CHILDREN = frozenset({"fusion", "camera_sim"})
"""Children ``up`` cannot run on without: the map's owner and the scene every frame comes from.
Any other that dies is started again, as the deploy's units restart it (a soak's depth process
killed left its pair's floor unknown, IoU 0.57, until started by hand); one that keeps dying is
left out, and the map goes on without it (fusion marks a pair not alive and maps on from the
rest)."""
RESTARTS_PER_MINUTE = 3
"""A child that dies more often than this within a minute is left out: it dies of itself."""


class UpSettings(ZenohSettings):
    """``up``'s own settings, and its children's parameters nested: each child is handed the very
    values validated here (flags serialised from the nested models), so no child setting is
    declared twice. Flat flags (``--seed``, ``--floor``, ``--p-hit``, …) work where unique."""

    model_config = SettingsConfigDict(cli_shortcuts={"camera-sim.rig.pair-count": "pairs"})

    duration_s: float = Field(0.0, ge=0.0, description="stop after this long (0: run until Ctrl-C)")
    out: Path = Field(Path("out"), description="where the map, report and logs go")
    progress_s: float = Field(2.0, gt=0.0, description="period of the progress line")
    view: bool = Field(True, description="serve the live map page (overgrid view) on loopback")
    view_port: int = Field(
        DEFAULT_HTTP_PORT, ge=1, le=65535, description="its port (if taken: any free one)"
    )
    ros2: bool = Field(
        False, description="also run the ROS 2 node (overgrid ros2: /map to DDS; the [ros2] extra)"
    )
    rmw_zenoh: bool = Field(
        False,
        description="also publish natively for rmw_zenoh robots (overgrid rmw-zenoh: no ROS needed)",
    )
    camera_sim: CameraSimParams = Field(
        default_factory=CameraSimParams, description="the simulator (overgrid camera-sim)"
    )
    depth: DepthParams = Field(
        default_factory=DepthParams, description="every depth process (overgrid depth)"
    )
    fusion: FusionParams = Field(
        default_factory=FusionParams, description="the fusion process (overgrid fusion)"
    )

    @model_validator(mode="after")
    def _one_lattice(self) -> UpSettings:
        if self.depth.resolution_m != self.fusion.grid.resolution_m:
            raise ValueError(
                f"--depth.resolution-m {self.depth.resolution_m} must equal "
                f"--fusion.grid.resolution-m {self.fusion.grid.resolution_m}: tiles must match the map"
            )
        return self


@dataclass
class Child:
    name: str
    args: list[str]
    process: subprocess.Popen[bytes]
    log_path: Path
    log_file: IO[bytes]
    deaths_s: list[float] = field(default_factory=list)
    """When it died (monotonic), within the last minute."""

    def tail(self) -> str:
        lines = self.log_path.read_text(errors="replace").splitlines()
        return "\n".join(lines[-LOG_TAIL_LINES:])


def flags_of(values: BaseModel) -> list[str]:
    """The flags that give a child exactly these values (those that differ from the defaults)."""
    return CliApp.serialize(values, list_style="argparse")


def session_flags(settings: ZenohSettings) -> list[str]:
    """The children join the same Zenoh network as ``up``; ``--listen`` stays with ``up`` itself:
    children would fight over the same endpoints."""
    session = {name: getattr(settings, name) for name in ZenohSettings.model_fields}
    return flags_of(ZenohSettings.model_construct(**{**session, "listen": []}))


def child_commands(settings: UpSettings) -> list[tuple[str, list[str]]]:
    """(name, ``overgrid`` arguments) of every child."""
    commands = [
        (
            "fusion",
            ["fusion", *flags_of(settings.fusion), "--state-dir", str(settings.out / "state")],
        ),
        ("camera_sim", ["camera-sim", *flags_of(settings.camera_sim)]),
    ]
    depth = flags_of(settings.depth)
    commands += [
        (f"depth_{pair}", ["depth", "--pair", pair, *depth])
        for pair in settings.camera_sim.rendered_pairs()
    ]
    if settings.view:
        commands.append(("viewer", ["view", "--http-port", str(settings.view_port)]))
    if settings.ros2:
        commands.append(("ros2", ["ros2"]))
    if settings.rmw_zenoh:
        commands.append(("rmw_zenoh", ["rmw-zenoh"]))
    return [(name, [*args, *session_flags(settings)]) for name, args in commands]


NESTED_CHILDREN = ("camera-sim", "depth", "fusion")
"""The commands whose parameters ``up`` nests: their values come as flags only."""


def child_environment(command: str) -> dict[str, str]:
    """A nested child inherits no ``OVERGRID_*`` variable: ``up`` read its own (the nested names)
    and hands the values over as flags, and one the child would read itself (``OVERGRID_RATE_HZ``)
    would quietly override what ``up`` validated. Other children read theirs."""
    if command not in NESTED_CHILDREN:
        return dict(os.environ)
    return {name: value for name, value in os.environ.items() if not name.startswith(ENV_PREFIX)}


def start_children(settings: UpSettings) -> list[Child]:
    logs = settings.out / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    children = []
    for name, args in child_commands(settings):
        log_path = logs / f"{name}.log"
        log_file = open(log_path, "wb")  # noqa: SIM115 - closed in stop_children
        children.append(Child(name, args, _spawn(args, log_file), log_path, log_file))
    return children


def _spawn(args: list[str], log_file: IO[bytes]) -> subprocess.Popen[bytes]:
    # A new session: the terminal's Ctrl-C reaches `up` alone, which saves the map first.
    return subprocess.Popen(
        [sys.executable, "-m", "services.cli", *args],
        env=child_environment(args[0]),
        stdout=log_file,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )


def without_unservable_viewer(settings: UpSettings) -> UpSettings:
    """The viewer needs aiohttp (the [view] extra): without it, one line and no page, not a
    child that dies at once."""
    if not settings.view or importlib.util.find_spec("aiohttp") is not None:
        return settings
    print(
        "overgrid up: no live map page: `overgrid view` needs aiohttp "
        "(pip install 'overgrid[view]'); --no-view silences this",
        file=sys.stderr,
        flush=True,
    )
    return settings.model_copy(update={"view": False})


def viewer_token() -> str | None:
    """The token the viewer child reads from the environment (``up`` hands it none of its own):
    the printed URL must carry it, or it answers 401."""
    return os.environ.get(f"{ENV_PREFIX}TOKEN") or None


def first_failure(children: list[Child], reported: set[str]) -> Child | None:
    """The first essential child that ended (it ends ``up`` with it); any other that ended is
    started again, or, dying more than RESTARTS_PER_MINUTE times a minute, reported once (its
    name added to ``reported``) and left out."""
    now = time.monotonic()
    for child in children:
        if child.process.poll() is None or child.name in reported:
            continue
        if child.name in ESSENTIAL_CHILDREN:
            return child
        child.deaths_s = [t for t in child.deaths_s if now - t < 60.0] + [now]
        died = f"{child.name} died (exit {child.process.returncode})"
        if len(child.deaths_s) > RESTARTS_PER_MINUTE:
            reported.add(child.name)
            print(
                f"{died} {len(child.deaths_s)} times in a minute; the map goes on without it. "
                f"Its last log lines:\n{child.tail()}",
                file=sys.stderr,
                flush=True,
            )
            continue
        print(f"{died}; started again", file=sys.stderr, flush=True)
        child.log_file.write(f"--- {died}; started again ---\n".encode())
        child.log_file.flush()
        child.process = _spawn(child.args, child.log_file)
    return None


def stop_children(children: list[Child]) -> list[str]:
    """SIGINT, then SIGKILL after a grace period; returns the names of those that had to be killed."""
    for child in children:
        if child.process.poll() is None:
            child.process.send_signal(signal.SIGINT)
    killed = []
    deadline = time.monotonic() + STOP_TIMEOUT_S
    for child in children:
        try:
            child.process.wait(max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            child.process.kill()
            child.process.wait()
            killed.append(child.name)
        child.log_file.close()
    return killed


def progress_line(
    answer: dict[str, Any],
    previous: dict[str, int],
    elapsed_s: float,
    period_s: float,
    iou: float | None = None,
) -> str:
    """One line of ``overgrid up``'s progress from fusion's health ``answer``. The known share is of
    the map's cells (its window runs past the floor the cameras see), not of the seen floor, which
    the report's ``unknown_fraction`` is of."""
    m = answer["map"]
    rates = []
    for pair, row in sorted(answer["pairs"].items()):
        rate = (row["tiles"] - previous.get(pair, 0)) / period_s
        previous[pair] = row["tiles"]
        rates.append(f"{pair} {rate:.1f}/s" + ("" if row["alive"] else " DEAD"))
    if not m["cols"]:
        return (
            f"[{elapsed_s:6.1f} s] no tile yet: the depth processes start (calibration, first "
            f"frames) | " + ("  ".join(rates) or "no depth process yet")
        )
    known = m["known_cells"] / max(m["cols"] * m["rows"], 1)
    rejected = sum(answer["tiles_rejected"].values())
    return (
        f"[{elapsed_s:6.1f} s] map v{m['version']} {m['cols']}×{m['rows']}, {known:.0%} of its "
        f"cells known, tiles {answer['tiles_accepted']} rejected {rejected}"
        + (f" IoU {iou:.3f}" if iou is not None else "")
        + " | "
        + "  ".join(rates)
    )


class Scoring:
    """The evaluation that runs alongside: made once the map exists, it records the stream from
    then on and scores the map against the simulator's ground truth."""

    def __init__(self, session: zenoh.Session) -> None:
        self.session = session
        self.evaluator: Evaluator | None = None
        self.recorder: Recorder | None = None
        self.error: str | None = None

    def start(self, resolution_m: float) -> None:
        if self.evaluator is not None:
            return
        try:
            self.evaluator = Evaluator(self.session, resolution_m, timeout_s=5.0)
            self.recorder = Recorder(self.session, self.evaluator.window, resolution_m)
        except (MapUnavailable, CodecError) as error:
            self.error = str(error)

    def iou(self) -> float | None:
        if self.evaluator is None:
            return None
        try:
            return self.evaluator.scores(latest(self.session, timeout_s=2.0))[0].iou
        except (MapUnavailable, CodecError):
            return None

    def report(self, occupancy_map: OccupancyMap) -> dict[str, Any]:
        if self.evaluator is None:
            return {"error": self.error or "never started: no map"}
        try:
            return evaluation_report(self.evaluator, self.recorder, occupancy_map)
        except (MapUnavailable, CodecError) as error:
            return {"error": str(error)}

    def truth_on(self, occupancy_map: OccupancyMap) -> npt.NDArray[np.bool_] | None:
        if self.evaluator is None:
            return None
        try:
            truth = self.evaluator.truth(occupancy_map.stamp_ns)
        except (MapUnavailable, CodecError):
            return None
        return reframe(truth.occupied, truth.header.window, occupancy_map.window, False)

    def close(self) -> None:
        if self.recorder is not None:
            self.recorder.close()


def save_outputs(
    settings: UpSettings,
    session: zenoh.Session,
    answer: dict[str, Any] | None,
    scoring: Scoring,
) -> list[Path]:
    occupancy_map = latest(session, layers=("height", "logodds"), timeout_s=10)
    if occupancy_map.window.empty:
        raise MapUnavailable("the map is still empty: no tile has arrived")
    written = write_map(occupancy_map, settings.out / "map.yaml") + write_map(
        occupancy_map, settings.out / "map.png", truth=scoring.truth_on(occupancy_map)
    )
    evaluation = scoring.report(occupancy_map)
    report = {**evaluation, "map": map_summary(occupancy_map), "health": answer}
    (settings.out / "report.json").write_text(json.dumps(report, indent=2))
    if "targets" in evaluation:
        print(evaluation_table(evaluation), flush=True)
    return [*written, settings.out / "report.json"]


def check_inputs(settings: UpSettings) -> None:
    """The files the children and ``up`` itself would read (the scene, the Zenoh config), read
    here first: a bad one is one line naming it and exit 2 before any process starts. Found by a
    child instead, it cost seconds of starting processes and a failed run that saved whatever map
    the state directory held over the previous run's files."""
    settings.camera_sim.scene_spec()
    zenoh_config(settings)


def main(settings: UpSettings) -> None:
    check_inputs(settings)
    stop = stop_on_signals()
    settings.out.mkdir(parents=True, exist_ok=True)
    settings = without_unservable_viewer(settings)
    if settings.view:  # another `up` may hold the port: the URL printed must be this one's
        port = available_port(DEFAULT_HTTP_HOST, settings.view_port)
        settings = settings.model_copy(update={"view_port": port})
    children = start_children(settings)
    try:
        failed, written = _supervise(settings, children, stop)
    finally:  # whatever happened above, no child outlives `up`
        killed = stop_children(children)
    for path in written:
        print(f"wrote {path}")
    if killed:
        print(f"had to kill: {', '.join(killed)}", file=sys.stderr)
    if failed is not None:
        print(
            f"{failed.name} died (exit {failed.process.returncode}); its last log lines:\n{failed.tail()}",
            file=sys.stderr,
        )
        raise SystemExit(1)
    if not written:  # the run's one promise is a map to look at
        raise SystemExit(1)


def _supervise(
    settings: UpSettings, children: list[Child], stop: threading.Event
) -> tuple[Child | None, list[Path]]:
    """Show progress until the duration, Ctrl-C or a child's death; then save the map."""
    print(
        f"overgrid up: {len(children)} processes, logs in {settings.out / 'logs'}; Ctrl-C to stop"
        + (
            f"\nthe live map: {page_url(DEFAULT_HTTP_HOST, settings.view_port, viewer_token())}"
            if settings.view
            else ""
        ),
        flush=True,
    )
    started = time.monotonic()
    failed: Child | None = None
    answer: dict[str, Any] | None = None
    previous: dict[str, int] = {}
    written: list[Path] = []
    reported: set[str] = set()
    with open_session(settings) as session:
        scoring = Scoring(session)
        try:
            while not stop.wait(settings.progress_s):
                failed = first_failure(children, reported)
                if failed is not None:
                    break
                elapsed = time.monotonic() - started
                try:
                    answer = health(session, timeout_s=2.0)
                except MapUnavailable:
                    print(f"[{elapsed:6.1f} s] waiting for fusion …", flush=True)
                else:
                    if answer["map"]["cols"]:
                        scoring.start(answer["map"]["resolution_m"])
                    line = progress_line(
                        answer, previous, elapsed, settings.progress_s, scoring.iou()
                    )
                    print(line, flush=True)
                if settings.duration_s and elapsed >= settings.duration_s:
                    break
            if failed is None or failed.name != "fusion":
                try:
                    written = save_outputs(settings, session, answer, scoring)
                except MapUnavailable as error:
                    print(f"no map to save: {error}", file=sys.stderr)
        finally:
            scoring.close()
    return failed, written


def cli(argv: Sequence[str] | None = None) -> None:
    main(
        parse_settings(
            UpSettings, argv, "overgrid up", "Run the whole system on this box (simulated scene)."
        )
    )
