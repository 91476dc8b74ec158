"""camera_sim process: render each pair at a fixed rate, publish frames, answer calib and truth."""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import zenoh

from common import keys
from common.codec import WIRE_ENCODING, encode
from common.lattice import Window, check_resolution
from common.lifecycle import stop_on_signals
from common.logs import setup_logging
from common.messages import CALIB_KIND, STEREO_KIND, TRUTH_KIND, StereoFrameHeader, TruthHeader
from common.settings import parse_settings, startup_error
from common.zenoh_session import open_session
from services.camera_sim import truth
from services.camera_sim.capture import StereoCapture
from services.camera_sim.lighting import Lighting
from services.camera_sim.rig import layout_pairs
from services.camera_sim.scene import SceneSpec
from services.camera_sim.settings import CameraSimSettings

log = logging.getLogger("camera_sim")


def jpeg_encoder(quality: int) -> Callable[[np.ndarray], bytes] | None:
    """JPEG through OpenCV (the depth extra has it); None for raw frames. Checked at start-up."""
    if quality == 0:
        return None
    try:
        import cv2
    except ImportError:
        startup_error("--jpeg-quality needs OpenCV: pip install 'overgrid[depth]' (or [all])")

    def encode_jpeg(image: np.ndarray) -> bytes:
        ok, buffer = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, quality])
        if not ok:
            raise ValueError("JPEG encoding failed")
        return bytes(buffer.tobytes())

    return encode_jpeg


def frame_payload(
    header_fields: dict[str, Any],
    left: np.ndarray,
    right: np.ndarray,
    encode_jpeg: Callable[[np.ndarray], bytes] | None,
) -> bytes:
    if encode_jpeg is None:
        header = StereoFrameHeader(**header_fields, encoding="raw")
        return encode(STEREO_KIND, header, {"left": left, "right": right})
    header = StereoFrameHeader(**header_fields, encoding="jpeg")
    return encode(
        STEREO_KIND, header, blobs={"left": encode_jpeg(left), "right": encode_jpeg(right)}
    )


def _answer(key: str, payload: bytes) -> Callable[[zenoh.Query], None]:
    """Reply on the queryable's own key, so a ``cam/*/calib`` query gets one answer per pair
    (replies on the query's wildcard key would be consolidated into one)."""

    def reply(query: zenoh.Query) -> None:
        query.reply(key, payload, encoding=WIRE_ENCODING)

    return reply


TRUTH_LIGHT_HISTORY_S = 120.0


def _truth_reply(scene: SceneSpec, lighting: Lighting, query: zenoh.Query) -> bytes:
    """Parameters: ``t`` (s since epoch) or ``stamp_ns``; ``resolution`` (m); ``band`` (h_min,h_max)."""
    params = dict(query.parameters)
    stamp_ns = (
        int(params["stamp_ns"])
        if "stamp_ns" in params
        else int(float(params.get("t", time.time())) * 1e9)  # inf, nan: OverflowError, ValueError
    )
    if not 0 <= stamp_ns < 2**63:
        raise ValueError(f"stamp_ns {stamp_ns} is outside 0 … 2^63")
    resolution_m = check_resolution(float(params.get("resolution", 0.05)))
    band = tuple(float(v) for v in params.get("band", "0.1,2.0").split(","))
    if len(band) != 2 or not all(math.isfinite(v) for v in band) or band[0] >= band[1]:
        raise ValueError(f"band must be h_min,h_max with h_min < h_max, got {params.get('band')}")
    objects = scene.truth_objects(stamp_ns / 1e9)
    margin = scene.wall_thickness_m
    window = Window.covering(
        -margin,
        -margin,
        scene.floor_size_m[0] + margin,
        scene.floor_size_m[1] + margin,
        resolution_m,
    )
    if window.cols * window.rows > 25_000_000:
        raise ValueError(
            f"resolution {resolution_m} m gives a grid of {window.cols}×{window.rows}: too large"
        )
    occupied = truth.occupancy(objects, window, resolution_m, (band[0], band[1]))
    header = TruthHeader(
        stamp_ns=stamp_ns,
        resolution_m=resolution_m,
        height_band_m=(band[0], band[1]),
        i0=window.i0,
        j0=window.j0,
        cols=window.cols,
        rows=window.rows,
        floor_size_m=scene.floor_size_m,
        objects=objects,
        light_level=lighting.level(stamp_ns / 1e9),
        light_steps_ns=[
            int(t_s * 1e9)
            for t_s in lighting.steps_s(
                stamp_ns / 1e9 - TRUTH_LIGHT_HISTORY_S, stamp_ns / 1e9 + 1.0
            )
        ],
    )
    return encode(TRUTH_KIND, header, {"occupied": occupied})


def main(settings: CameraSimSettings) -> None:
    from services.camera_sim.render import SceneRenderer  # mujoco only where rendering happens

    setup_logging("camera_sim", settings.log_level)
    stop = stop_on_signals()
    scene = settings.scene_spec()
    encode_jpeg = jpeg_encoder(0 if settings.ideal_cameras else settings.jpeg_quality)
    true_calibrations = layout_pairs(settings.rig, scene.floor_size_m)
    if settings.pairs:
        true_calibrations = [c for c in true_calibrations if c.pair in settings.pairs]
    renderer = SceneRenderer(scene, true_calibrations, settings.shadows, settings.lighting())
    model = settings.camera_model()
    captures = [StereoCapture(renderer, c, model, settings.seed) for c in true_calibrations]
    calibrations = [capture.calibration for capture in captures]
    period_s = 1.0 / settings.rate_hz
    stats = {"published": 0, "skipped": 0, "render_ms": 0.0}

    with open_session(settings) as session:
        publishers = {
            # BLOCK: a frame is never dropped by Zenoh on the way; depth keeps only the latest, so the
            # queue behind a slow consumer is one frame deep, not unbounded.
            c.pair: session.declare_publisher(
                keys.stereo(c.pair),
                encoding=WIRE_ENCODING,
                congestion_control=zenoh.CongestionControl.BLOCK,
            )
            for c in calibrations
        }
        calib_payloads = {c.pair: encode(CALIB_KIND, c) for c in calibrations}
        queryables = [
            session.declare_queryable(keys.calib(c.pair), _answer(keys.calib(c.pair), payload))
            for c, payload in zip(calibrations, calib_payloads.values(), strict=True)
        ]

        def on_truth(query: zenoh.Query) -> None:
            try:
                query.reply(
                    query.key_expr,
                    _truth_reply(scene, renderer.lighting, query),
                    encoding=WIRE_ENCODING,
                )
            except (ValueError, KeyError, OverflowError) as error:
                query.reply_err(
                    f"sim/truth: {error}; parameters: t or stamp_ns, resolution, band=h_min,h_max"
                )

        if settings.serve_truth:
            queryables.append(session.declare_queryable(keys.SIM_TRUTH, on_truth))
        log.info(
            "started",
            extra={
                "pairs": ",".join(publishers),
                "rate_hz": settings.rate_hz,
                "objects": len(scene.objects),
                "movers": len(scene.movers),
                "floor": scene.floor,
                "cameras": "ideal" if model.sensor is None else "realistic",
            },
        )
        seq = 0
        next_tick = time.monotonic()
        last_summary = time.monotonic()
        while not stop.is_set() and (settings.frames == 0 or seq < settings.frames):
            stamp_ns = time.time_ns()
            started = time.perf_counter()
            renderer.set_time(stamp_ns / 1e9)
            for capture in captures:
                pair = capture.calibration.pair
                left, right = capture.capture(stamp_ns)
                fields = {"pair": pair, "seq": seq, "stamp_ns": stamp_ns}
                publishers[pair].put(frame_payload(fields, left, right, encode_jpeg))
                stats["published"] += 1
            stats["render_ms"] += (time.perf_counter() - started) * 1e3
            seq += 1
            next_tick += period_s
            now = time.monotonic()
            if now > next_tick:  # fell behind: skip the ticks we missed rather than queue them
                missed = int((now - next_tick) // period_s) + 1
                stats["skipped"] += missed * len(calibrations)
                next_tick += missed * period_s
            if now - last_summary >= 10.0:
                log.info(
                    "summary",
                    extra={
                        "frames": stats["published"],
                        "skipped": stats["skipped"],
                        "render_ms_per_round": stats["render_ms"] / max(seq, 1),
                    },
                )
                last_summary = now
            stop.wait(max(0.0, next_tick - time.monotonic()))
        for queryable in queryables:
            queryable.undeclare()
    renderer.close()
    log.info("stopped", extra={"frames": stats["published"], "skipped": stats["skipped"]})


def cli(argv: Sequence[str] | None = None) -> None:
    main(
        parse_settings(
            CameraSimSettings,
            argv,
            "overgrid camera-sim",
            "Simulated overhead stereo pairs (MuJoCo), published over Zenoh.",
        )
    )
