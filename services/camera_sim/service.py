"""camera_sim process: render each pair at a fixed rate, publish frames, answer calib and truth."""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import zenoh

from common import keys
from common.codec import WIRE_ENCODING, encode
from common.lattice import check_resolution
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
TRUTH_MAX_CELLS = 25_000_000
TRUTH_PARAMETERS = "t (s since the epoch) or stamp_ns, resolution (m), band=h_min,h_max (m)"


class TruthQueryError(ValueError):
    """A ``sim/truth`` query this simulator cannot answer; the message names the parameter."""


@dataclass(frozen=True)
class TruthQuery:
    stamp_ns: int
    resolution_m: float
    band_m: tuple[float, float]


def _finite(name: str, text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise TruthQueryError(f"{name}={text!r} is not a number") from None
    if not math.isfinite(value):
        raise TruthQueryError(f"{name}={text} is not finite")
    return value


def parse_truth_query(parameters: dict[str, str], now_ns: int) -> TruthQuery:
    """The query's parameters, each checked and named when wrong; ``now_ns`` without t/stamp_ns.
    Parameters starting with ``_`` are Zenoh's own and ignored."""
    known = ("t", "stamp_ns", "resolution", "band")
    unknown = sorted(k for k in parameters if k not in known and not k.startswith("_"))
    if unknown:
        raise TruthQueryError(f"unknown parameter {unknown[0]!r}")
    if "stamp_ns" in parameters and "t" in parameters:
        raise TruthQueryError("give t or stamp_ns, not both")
    if "stamp_ns" in parameters:
        text = parameters["stamp_ns"]
        digits = text.isascii() and text.isdigit() and len(text) <= 19
        stamp_ns = int(text) if digits else -1
        if not 0 <= stamp_ns < 2**63:
            raise TruthQueryError(f"stamp_ns={text!r} is not an integer in 0 … 2^63 ns")
    elif "t" in parameters:
        t_s = _finite("t", parameters["t"])
        if not 0.0 <= t_s < (2**63 - 1) / 1e9:
            raise TruthQueryError(f"t={parameters['t']} s is outside 0 … 2^63 ns since the epoch")
        stamp_ns = round(t_s * 1e9)
    else:
        stamp_ns = now_ns
    resolution_text = parameters.get("resolution", "0.05")
    resolution_m = _finite("resolution", resolution_text)
    try:
        check_resolution(resolution_m)
    except ValueError as error:
        raise TruthQueryError(f"resolution={resolution_text}: {error}") from None
    band_text = parameters.get("band", "0.1,2.0")
    band = tuple(_finite("band", v) for v in band_text.split(","))
    if len(band) != 2 or band[0] >= band[1]:
        raise TruthQueryError(f"band={band_text} must be h_min,h_max with h_min < h_max")
    return TruthQuery(stamp_ns, resolution_m, (band[0], band[1]))


def truth_payload(scene: SceneSpec, lighting: Lighting, query: TruthQuery) -> bytes:
    stamp_s = query.stamp_ns / 1e9
    objects = scene.truth_objects(stamp_s)
    window = scene.window(query.resolution_m)
    if window.cols * window.rows > TRUTH_MAX_CELLS:
        raise TruthQueryError(
            f"resolution={query.resolution_m:g} gives a grid of {window.cols}×{window.rows}: "
            f"more than {TRUTH_MAX_CELLS} cells"
        )
    occupied = truth.occupancy(objects, window, query.resolution_m, query.band_m)
    header = TruthHeader(
        stamp_ns=query.stamp_ns,
        resolution_m=query.resolution_m,
        height_band_m=query.band_m,
        i0=window.i0,
        j0=window.j0,
        cols=window.cols,
        rows=window.rows,
        floor_size_m=scene.floor_size_m,
        objects=objects,
        light_level=lighting.level(stamp_s),
        light_steps_ns=[
            int(t_s * 1e9)
            for t_s in lighting.steps_s(stamp_s - TRUTH_LIGHT_HISTORY_S, stamp_s + 1.0)
        ],
    )
    return encode(TRUTH_KIND, header, {"occupied": occupied})


def _answer_truth(scene: SceneSpec, lighting: Lighting) -> Callable[[zenoh.Query], None]:
    def on_truth(query: zenoh.Query) -> None:
        """Every query gets a reply: the truth, or an error naming what is wrong."""
        try:
            # zenoh's stub types Parameters.__iter__ as returning the list of pairs it iterates
            parameters = dict(query.parameters.__iter__())
            payload = truth_payload(scene, lighting, parse_truth_query(parameters, time.time_ns()))
        except TruthQueryError as error:
            query.reply_err(f"{keys.SIM_TRUTH}: {error}; parameters: {TRUTH_PARAMETERS}")
            return
        except Exception as error:  # a defect: still a reply, and a log line to find it
            log.exception("sim/truth query failed", extra={"selector": str(query.selector)})
            query.reply_err(f"{keys.SIM_TRUTH}: internal error {type(error).__name__}: {error}")
            return
        # On its own key: a query on a wildcard (sim/*) cannot be answered on the wildcard.
        query.reply(keys.SIM_TRUTH, payload, encoding=WIRE_ENCODING)

    return on_truth


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

    with open_session(settings, wait_for_router=True) as session:
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

        if settings.serve_truth:
            queryables.append(
                session.declare_queryable(keys.SIM_TRUTH, _answer_truth(scene, renderer.lighting))
            )
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
            # Every pair rendered before any is sent: a rig triggered together delivers together
            # (sent as rendered, a capture's last pair came 0.2 s after its first, and fusion,
            # which fuses a capture whole, waited for it).
            frames = [(capture.calibration.pair, capture.capture(stamp_ns)) for capture in captures]
            for pair, (left, right) in frames:
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
            queryable.undeclare()  # type: ignore[no-untyped-call]
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
