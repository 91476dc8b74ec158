"""Query benchmark: 50 concurrent clients on ``map/latest`` of a 2000×2000 map while tiles stream.

Real processes on loopback, isolated by namespace and port: a Zenoh router (this process), the fusion
service, a tile streamer (real rendered tiles, placed over the map, fresh stamps, paced), and a client
process with one thread per client querying ``map/latest``. Phase 1 streams alone (idle ingest rate),
phase 2 streams with the clients. Printed: reply time p50/p99, replies, and ingest held = phase-2 rate
/ phase-1 rate. The last line is a JSON object with the figures.

Load model: each client asks ``--rate-hz`` times a second on its own schedule (random phase), and a
reply time runs from the scheduled send, so a late reply also delays the next query's clock: queueing
counts, nothing is hidden by a client that waits. ``--rate-hz 0`` runs closed loops instead (each
client asks again the moment its reply lands): that measures saturated throughput, replies per
second, and its reply times are just clients / throughput (Little's law).

    .venv/bin/python -m bench.query [--clients 50] [--rate-hz 10] [--seconds 10]
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
from typing import cast

import numpy as np
import zenoh

from common import keys
from common.client import health
from common.codec import WIRE_ENCODING, encode
from common.messages import TILE_KIND, TileHeader
from common.settings import ZenohSettings
from common.zenoh_session import open_session

MAP_SIZE_M = 100.0  # 2000 × 2000 cells at 5 cm
RESOLUTION_M = 0.05


def _flags(endpoint: str, namespace: str) -> list[str]:
    return ["--connect", endpoint, "--no-multicast-scouting", "--namespace", namespace]


def _settings(endpoint: str, namespace: str) -> ZenohSettings:
    return ZenohSettings(connect=[endpoint], no_multicast_scouting=True, namespace=namespace)


def stream(endpoint: str, namespace: str, seconds: float) -> None:
    """Publish real tiles at random places over the map, as fast as the blocking put allows."""
    from bench.tiles import rendered_tiles

    tiles = [tile for _, tile in rendered_tiles(instants=1)]
    rng = np.random.default_rng(0)
    cells = int(MAP_SIZE_M / RESOLUTION_M)
    with open_session(_settings(endpoint, namespace)) as session:
        publishers = {
            p: session.declare_publisher(
                keys.tile(p),
                encoding=WIRE_ENCODING,
                congestion_control=zenoh.CongestionControl.BLOCK,
            )
            for p in ("s0", "s1", "s2", "s3")
        }
        print("ready", flush=True)
        deadline = time.monotonic() + seconds
        seq = 0
        while time.monotonic() < deadline:
            tile = tiles[seq % len(tiles)]
            w = tile.window
            i0 = int(rng.integers(0, cells - w.cols))
            j0 = int(rng.integers(0, cells - w.rows))
            pair = f"s{seq % 4}"
            header = TileHeader(
                pair=pair,
                seq=seq,
                stamp_ns=time.time_ns(),
                resolution_m=RESOLUTION_M,
                i0=i0,
                j0=j0,
                cols=w.cols,
                rows=w.rows,
            )
            publishers[pair].put(encode(TILE_KIND, header, tile.arrays()))
            seq += 1
            time.sleep(0.001)  # a streamer, not a flood: leaves fusion room to serve queries


def clients(endpoint: str, namespace: str, count: int, seconds: float, rate_hz: float) -> None:
    """``count`` threads on map/latest (``rate_hz`` each, 0: closed loops); prints the reply times
    (ms, from each query's scheduled send) as JSON."""
    times: list[float] = []
    failures = [0]
    lock = threading.Lock()
    rng = np.random.default_rng(1)
    with open_session(_settings(endpoint, namespace)) as session:
        health(session, timeout_s=20)
        deadline = time.monotonic() + seconds

        def loop(phase: float) -> None:
            scheduled = time.monotonic() + phase
            while scheduled < deadline:
                if rate_hz:
                    time.sleep(max(0.0, scheduled - time.monotonic()))
                else:
                    scheduled = time.monotonic()
                ok = any(r.ok is not None for r in session.get(keys.MAP_LATEST, timeout=5.0))
                elapsed = (time.monotonic() - scheduled) * 1e3
                with lock:
                    if ok:
                        times.append(elapsed)
                    else:
                        failures[0] += 1
                if rate_hz:
                    scheduled += 1.0 / rate_hz

        period = 1.0 / rate_hz if rate_hz else 0.0
        threads = [
            threading.Thread(target=loop, args=(float(rng.uniform(0, period)),))
            for _ in range(count)
        ]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
    print(json.dumps({"times_ms": times, "failures": failures[0], "seconds": seconds}), flush=True)


def _ingest_rate(session: zenoh.Session, seconds: float) -> float:
    start = health(session, timeout_s=10)["tiles_accepted"]
    time.sleep(seconds)
    return cast(float, (health(session, timeout_s=10)["tiles_accepted"] - start) / seconds)


def orchestrate(client_count: int, seconds: float, rate_hz: float) -> None:
    from tests.conftest import free_port, open_router

    port, namespace = free_port(), f"bench-{uuid.uuid4().hex[:8]}"
    endpoint = f"tcp/127.0.0.1:{port}"
    router = open_router(namespace, port)
    me = [sys.executable, "-m", "bench.query"]
    with tempfile.TemporaryDirectory() as state_dir:
        fusion = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "services.cli",
                "fusion",
                "--bounds",
                f"0,0,{MAP_SIZE_M},{MAP_SIZE_M}",
                "--state-dir",
                state_dir,
                "--max-tile-age-s",
                "5",
                "--log-level",
                "warning",
                *_flags(endpoint, namespace),
            ]
        )
        try:
            health(router, timeout_s=30)
            streamer = subprocess.Popen(
                [
                    *me,
                    "--role",
                    "stream",
                    "--endpoint",
                    endpoint,
                    "--namespace",
                    namespace,
                    "--seconds",
                    str(3 * seconds + 30),
                ],
                stdout=subprocess.PIPE,
                text=True,
            )
            assert streamer.stdout is not None
            streamer.stdout.readline()  # "ready"
            time.sleep(2.0)
            idle = _ingest_rate(router, seconds)
            print(f"idle ingest: {idle:.0f} tiles/s", file=sys.stderr)
            querying = subprocess.Popen(
                [
                    *me,
                    "--role",
                    "clients",
                    "--endpoint",
                    endpoint,
                    "--namespace",
                    namespace,
                    "--clients",
                    str(client_count),
                    "--rate-hz",
                    str(rate_hz),
                    "--seconds",
                    str(seconds + 4),
                ],
                stdout=subprocess.PIPE,
                text=True,
            )
            time.sleep(2.0)
            loaded = _ingest_rate(router, seconds)
            out, _ = querying.communicate(timeout=seconds + 60)
            streamer.terminate()
            streamer.wait(10)
        finally:
            fusion.send_signal(signal.SIGINT)
            fusion.wait(30)
            router.close()  # type: ignore[no-untyped-call]
    answer = json.loads(out.strip().splitlines()[-1])
    times = np.array(answer["times_ms"])
    result = {
        "clients": client_count,
        "rate_hz": rate_hz,
        "replies_per_s": round(times.size / answer["seconds"], 1),
        "map_cells": int((MAP_SIZE_M / RESOLUTION_M) ** 2),
        "replies": int(times.size),
        "failures": answer["failures"],
        "p50_ms": round(float(np.percentile(times, 50)), 2),
        "p99_ms": round(float(np.percentile(times, 99)), 2),
        "idle_ingest_tiles_per_s": round(idle, 1),
        "loaded_ingest_tiles_per_s": round(loaded, 1),
        "ingest_held": round(loaded / idle, 3) if idle else 0.0,
    }
    load = f"{rate_hz:g} Hz each" if rate_hz else "closed loops"
    print(
        f"{client_count} clients ({load}), {result['replies']} replies of a {result['map_cells']}-cell map "
        f"({result['replies_per_s']:.0f}/s): "
        f"p50 {result['p50_ms']} ms, p99 {result['p99_ms']} ms, failures {result['failures']}"
    )
    print(
        f"ingest: idle {idle:.0f} tiles/s, with clients {loaded:.0f} tiles/s, held {result['ingest_held']:.2f}"
    )
    print(json.dumps(result))


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--role", choices=("orchestrate", "stream", "clients"), default="orchestrate"
    )
    parser.add_argument("--endpoint", default="")
    parser.add_argument("--namespace", default="")
    parser.add_argument("--clients", type=int, default=50)
    parser.add_argument(
        "--rate-hz",
        type=float,
        default=10.0,
        help="queries per second per client (0: closed loops)",
    )
    parser.add_argument("--seconds", type=float, default=10.0)
    args = parser.parse_args()
    if args.role == "stream":
        stream(args.endpoint, args.namespace, args.seconds)
    elif args.role == "clients":
        clients(args.endpoint, args.namespace, args.clients, args.seconds, args.rate_hz)
    else:
        orchestrate(args.clients, args.seconds, args.rate_hz)


if __name__ == "__main__":
    main()
