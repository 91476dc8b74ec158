"""``overgrid`` command: one subcommand per service or tool; heavy imports happen only when chosen."""

from __future__ import annotations

import importlib
import os
import sys
from collections.abc import Sequence

from common.lifecycle import catch_stop_signals

COMMANDS = {
    "up": ("services.up", "run everything on this box on the simulated scene; save the map"),
    "camera-sim": ("services.camera_sim.service", "simulated overhead stereo pairs (MuJoCo)"),
    "depth": ("services.depth.service", "depth process of one stereo pair: images → tiles"),
    "fusion": (
        "services.fusion.service",
        "fuses every pair's tiles into one map; serves map/latest",
    ),
    "map": (
        "services.client_cli",
        "map get -o FILE: save the current map (.yaml+.pgm, .png, .npz)",
    ),
    "eval": (
        "services.evaluation.service",
        "score the running map against the simulator's ground truth",
    ),
    "health": ("services.client_cli", "show the fusion service's health"),
    "objects": ("services.client_cli", "show the tracked obstacles (map/objects) as a table"),
    "view": ("services.viewer.server", "the live map in a browser (http://127.0.0.1:8470/)"),
    "router": ("services.router", "a Zenoh router for boxes that multicast scouting cannot reach"),
    "ros2": ("services.ros2.node", "a ROS 2 node (rclpy) publishing /map, /map_updates, height"),
    "rmw-zenoh": (
        "services.ros2.native",
        "/map and /map_updates on rmw_zenoh's Zenoh keys: ROS 2 robots need no node",
    ),
    "save-frame": ("services.camera_sim.save_frame", "save one stereo frame of a pair as PNG"),
}


EXTRAS = {
    "cv2": "depth",
    "numba": "depth,fusion",
    "scipy": "fusion",
    "mujoco": "sim",
    "aiohttp": "view",
    "rclpy": "ros2",
    "rosbags": "rmw-zenoh",
    "xxhash": "rmw-zenoh",
}
"""The extra (pyproject's optional dependencies) that installs each module a command may need: a
robot's base install ran ``overgrid eval`` into a ModuleNotFoundError traceback."""


def main(argv: Sequence[str] | None = None) -> None:
    args = list(sys.argv[1:] if argv is None else argv)
    if args and args[0] not in COMMANDS and args[0] not in ("-h", "--help"):
        print(f"overgrid: no command {args[0]!r} (overgrid --help lists them)", file=sys.stderr)
        raise SystemExit(2)
    if not args or args[0] in ("-h", "--help"):
        width = max(len(name) for name in COMMANDS)
        lines = [f"  {name:<{width}}  {help_text}" for name, (_, help_text) in COMMANDS.items()]
        print("usage: overgrid COMMAND [options]\n\ncommands:\n" + "\n".join(lines))
        raise SystemExit(0 if args and args[0] in ("-h", "--help") else 2)
    catch_stop_signals()  # before the heavy imports: a stop while starting is a clean exit
    try:
        module = importlib.import_module(COMMANDS[args[0]][0])
    except ModuleNotFoundError as error:
        missing = (error.name or "").split(".")[0]
        extra = EXTRAS.get(missing)
        if extra is None:
            raise
        print(
            f"overgrid {args[0]} needs {missing}, which this install lacks: "
            f"pip install 'overgrid[{extra}]'",
            file=sys.stderr,
        )
        raise SystemExit(2) from None
    entry = {"map": "map_cli", "health": "health_cli", "objects": "objects_cli"}.get(args[0], "cli")
    try:
        try:
            getattr(module, entry)(args[1:])
        finally:
            sys.stdout.flush()  # here, not at exit: a reader that left is handled below
    except BrokenPipeError:
        # The reader left (``overgrid objects | head``): nothing more to say to anyone. Standard
        # output goes to /dev/null so that the interpreter's own flush at exit fails silently too.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        raise SystemExit(1) from None


if __name__ == "__main__":
    main()
