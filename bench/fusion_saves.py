"""Saves off the intake path: capture → ``map/updates`` latency on a 5000×5000 map while the state
is saved every ``--save-interval-s``, against the same run with saves off (the baseline).

Real processes on loopback, isolated by namespace and port: a Zenoh router and a ``map/updates``
subscriber (this process), the fusion service (``--bounds`` 250 m × 250 m at 5 cm: 25 M cells,
filled wall to wall before timing, so a save has a whole map to write: the first save after a start
writes every chunk), and a tile streamer process (4 pairs × ``--rate-hz``, tiles of 160×120 cells at
random places, fresh stamps). Latency of a tile: from its capture stamp to the arrival of the first
update whose stamp covers it. Decay is set long, as on a site whose cameras see all of it.

    .venv/bin/python -m bench.fusion_saves [--seconds 20] [--rate-hz 10] [--save-interval-s 0.5]
                                           [--rounds 3]
"""

from __future__ import annotations

import argparse
import json
import signal
import subprocess
import sys
import tempfile
import threading
import time
import uuid

import numpy as np
import zenoh

from common import keys
from common.client import health
from common.codec import WIRE_ENCODING, decode, encode
from common.messages import MAP_UPDATE_KIND, TILE_KIND, MapUpdateHeader, TileHeader
from common.settings import ZenohSettings
from common.zenoh_session import open_session

RESOLUTION_M = 0.05
MAP_CELLS = 5000
FILL_TILE_CELLS = 500
TILE_SHAPE = (120, 160)
PAIRS = ("s0", "s1", "s2", "s3")


def _tile(pair: str, seq: int, i0: int, j0: int, rows: int, cols: int, value: float) -> bytes:
    header = TileHeader(
        pair=pair,
        seq=seq,
        stamp_ns=time.time_ns(),
        resolution_m=RESOLUTION_M,
        i0=i0,
        j0=j0,
        cols=cols,
        rows=rows,
    )
    rng = np.random.default_rng(seq)
    arrays: dict[str, np.ndarray] = {
        "logodds": rng.uniform(value - 0.5, value + 0.5, (rows, cols)).astype(np.float32),
        "height_m": rng.uniform(0.0, 1.0, (rows, cols)).astype(np.float32),
        "count": np.full((rows, cols), 3, np.uint16),
    }
    return encode(TILE_KIND, header, arrays)


def stream(endpoint: str, namespace: str, seconds: float, rate_hz: float) -> None:
    """Every pair's tiles at ``rate_hz``; prints the capture stamps sent, as JSON."""
    settings = ZenohSettings(connect=[endpoint], no_multicast_scouting=True, namespace=namespace)
    rng = np.random.default_rng(0)
    rows, cols = TILE_SHAPE
    stamps: list[int] = []
    with open_session(settings) as session:
        publishers = {
            p: session.declare_publisher(
                keys.tile(p),
                encoding=WIRE_ENCODING,
                congestion_control=zenoh.CongestionControl.BLOCK,
            )
            for p in PAIRS
        }
        print("ready", flush=True)
        period_s = 1.0 / (rate_hz * len(PAIRS))
        start = time.monotonic()
        seq = 0
        while time.monotonic() - start < seconds:
            pair = PAIRS[seq % len(PAIRS)]
            i0 = int(rng.integers(0, MAP_CELLS - cols))
            j0 = int(rng.integers(0, MAP_CELLS - rows))
            payload = _tile(pair, seq, i0, j0, rows, cols, 0.5)
            stamps.append(decode(payload, TILE_KIND, TileHeader).header.stamp_ns)
            publishers[pair].put(payload)
            seq += 1
            time.sleep(max(0.0, start + seq * period_s - time.monotonic()))
    print(json.dumps({"stamps_ns": stamps}), flush=True)


def run_once(save_interval_s: float, seconds: float, rate_hz: float) -> dict[str, float]:
    """One fusion process, filled, then streamed at while updates are timed."""
    from tests.conftest import free_port, open_router

    port, namespace = free_port(), f"bench-{uuid.uuid4().hex[:8]}"
    endpoint = f"tcp/127.0.0.1:{port}"
    flags = ["--connect", endpoint, "--no-multicast-scouting", "--namespace", namespace]
    router = open_router(namespace, port)
    arrivals: list[tuple[int, int]] = []
    lock = threading.Lock()

    def on_update(sample: zenoh.Sample) -> None:
        arrival_ns = time.time_ns()
        h = decode(sample.payload.to_bytes(), MAP_UPDATE_KIND, MapUpdateHeader).header
        with lock:
            arrivals.append((h.stamp_ns, arrival_ns))

    size_m = MAP_CELLS * RESOLUTION_M
    with tempfile.TemporaryDirectory() as state_dir:
        fusion = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "services.cli",
                "fusion",
                "--bounds",
                f"0,0,{size_m},{size_m}",
                "--state-dir",
                state_dir,
                "--save-interval-s",
                str(save_interval_s),
                "--decay-after-s",
                "3600",
                "--log-level",
                "warning",
                *flags,
            ]
        )
        try:
            health(router, timeout_s=60)
            filler = router.declare_publisher(
                keys.tile("fill"),
                encoding=WIRE_ENCODING,
                congestion_control=zenoh.CongestionControl.BLOCK,
            )
            n = FILL_TILE_CELLS
            fills = [(i, j) for j in range(0, MAP_CELLS, n) for i in range(0, MAP_CELLS, n)]
            for seq, (i0, j0) in enumerate(fills):
                filler.put(_tile("fill", seq, i0, j0, n, n, -0.4))
            deadline = time.monotonic() + 120
            while health(router, timeout_s=10)["tiles_accepted"] < len(fills):
                if time.monotonic() > deadline:
                    raise RuntimeError("the map was not filled in time")
                time.sleep(0.2)
            subscriber = router.declare_subscriber(keys.MAP_UPDATES, on_update)
            streamer = subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    "bench.fusion_saves",
                    "--role",
                    "stream",
                    "--endpoint",
                    endpoint,
                    "--namespace",
                    namespace,
                    "--seconds",
                    str(seconds),
                    "--rate-hz",
                    str(rate_hz),
                ],
                stdout=subprocess.PIPE,
                text=True,
            )
            assert streamer.stdout is not None
            streamer.stdout.readline()  # "ready"
            sent = json.loads(streamer.stdout.readline())["stamps_ns"]
            streamer.wait(30)
            time.sleep(1.0)  # the last updates land
            answer = health(router, timeout_s=10)
            subscriber.undeclare()  # type: ignore[no-untyped-call]
        finally:
            fusion.send_signal(signal.SIGINT)
            fusion.wait(120)
    router.close()  # type: ignore[no-untyped-call]
    with lock:
        updates = sorted(arrivals)
    update_stamps = np.array([s for s, _ in updates], np.int64)
    # An update's arrival can come before a later-stamped one's: take, per stamp, the first
    # arrival at or after it.
    first_arrival = np.minimum.accumulate(np.array([a for _, a in updates], np.int64)[::-1])[::-1]
    latencies_ms = []
    for stamp in sent:
        k = int(np.searchsorted(update_stamps, stamp))
        if k < len(updates):
            latencies_ms.append((first_arrival[k] - stamp) / 1e6)
    values = np.array(latencies_ms)
    slow = [
        f"{(stamp - sent[0]) / 1e9:.1f}s:{ms:.0f}ms"
        for stamp, ms in zip(sent, latencies_ms, strict=False)
        if ms > 50
    ]
    print(f"tiles over 50 ms (time into the stream: latency): {slow[:40]}", file=sys.stderr)
    return {
        "p50_ms": round(float(np.percentile(values, 50)), 2),
        "p99_ms": round(float(np.percentile(values, 99)), 2),
        "max_ms": round(float(values.max()), 2),
        "tiles": len(sent),
        "timed": len(values),
        "accepted": answer["tiles_accepted"] - len(fills),
        "saved_version": answer["state"].get("saved_version", -1),
        "save_errors": answer["state"].get("save_errors", 0),
    }


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--role", choices=("bench", "stream"), default="bench")
    parser.add_argument("--endpoint", default="")
    parser.add_argument("--namespace", default="")
    parser.add_argument("--seconds", type=float, default=20.0, help="streaming time per run")
    parser.add_argument("--rate-hz", type=float, default=10.0, help="tiles per second per pair")
    parser.add_argument("--save-interval-s", type=float, default=0.5, help="saves-on runs")
    parser.add_argument("--rounds", type=int, default=3, help="alternating rounds of each")
    args = parser.parse_args()
    if args.role == "stream":
        stream(args.endpoint, args.namespace, args.seconds, args.rate_hz)
        return
    baselines, savings = [], []
    for round_index in range(args.rounds):  # alternate, so machine noise hits both alike
        baselines.append(run_once(1e9, args.seconds, args.rate_hz))  # saves off (only the last)
        print(f"round {round_index + 1}, saves off: {baselines[-1]}", file=sys.stderr)
        savings.append(run_once(args.save_interval_s, args.seconds, args.rate_hz))
        print(
            f"round {round_index + 1}, saves every {args.save_interval_s} s: {savings[-1]}",
            file=sys.stderr,
        )

    def median(runs: list[dict[str, float]], name: str) -> float:
        return round(float(np.median([run[name] for run in runs])), 2)

    result = {
        "map_cells": MAP_CELLS * MAP_CELLS,
        "save_interval_s": args.save_interval_s,
        "rounds": args.rounds,
        "p50_ms": median(savings, "p50_ms"),
        "p99_ms": median(savings, "p99_ms"),
        "p99_ms_rounds": [run["p99_ms"] for run in savings],
        "max_ms": max(run["max_ms"] for run in savings),
        "baseline_p50_ms": median(baselines, "p50_ms"),
        "baseline_p99_ms": median(baselines, "p99_ms"),
        "baseline_p99_ms_rounds": [run["p99_ms"] for run in baselines],
        "tiles_per_run": savings[0]["tiles"],
        "saves_written": all(run["saved_version"] > 0 for run in savings),
        "save_errors": sum(run["save_errors"] for run in savings),
        "target_p99_ms": 50.0,
    }
    result["p99_ratio"] = round(result["p99_ms"] / result["baseline_p99_ms"], 2)
    print(f"capture → map/updates with saves: p50 {result['p50_ms']} ms, p99 {result['p99_ms']} ms")
    print(
        f"same without saves:              p50 {result['baseline_p50_ms']} ms, p99 {result['baseline_p99_ms']} ms"
    )
    print(f"p99 ratio (saves / none, medians of {args.rounds} rounds) {result['p99_ratio']}")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
