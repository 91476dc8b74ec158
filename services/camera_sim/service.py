"""camera_sim process: render each pair at a fixed rate, publish frames, answer calib and truth."""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml
import zenoh
from pydantic import Field, model_validator

from common import keys
from common.codec import WIRE_ENCODING, encode
from common.lattice import Window, check_resolution
from common.lifecycle import stop_on_signals
from common.logs import setup_logging
from common.messages import CALIB_KIND, STEREO_KIND, TRUTH_KIND, StereoFrameHeader, TruthHeader
from common.settings import CommaList, ZenohSettings, parse_settings, startup_error
from common.zenoh_session import open_session
from services.camera_sim import truth
from services.camera_sim.calibration_error import CalibrationError
from services.camera_sim.capture import CameraModel, StereoCapture
from services.camera_sim.lighting import Lighting
from services.camera_sim.rig import RigSpec, layout_pairs, pair_name
from services.camera_sim.scene import FloorKind, SceneSpec, generate_scene, load_scene
from services.camera_sim.sensor import SensorParams

log = logging.getLogger("camera_sim")
_SENSOR = SensorParams()
_CALIB_ERROR = CalibrationError()


class CameraSimSettings(ZenohSettings):
    seed: int = Field(0, description="seed of the generated scene and its texture")
    scene: Path | None = Field(
        None, description="scene file (JSON/YAML SceneSpec) instead of a generated one"
    )
    floor: FloorKind = Field(
        "concrete",
        description="floor: concrete (weak texture, stains, markings), speckle (ideal), plain",
    )
    plain_objects: bool = Field(False, description="every static object one uniform colour")
    floor_x_m: float = Field(12.0, gt=1.0, le=500.0, description="floor length along x")
    floor_y_m: float = Field(10.0, gt=1.0, le=500.0, description="floor length along y")
    pair_count: int = Field(4, ge=1, le=256, description="stereo pairs on the ceiling grid")
    pairs: CommaList = Field(
        default_factory=list, description="render only these pairs (e.g. p0,p2)"
    )
    camera_height_m: float = Field(
        6.0, gt=0.5, le=50.0, description="ceiling height of the cameras"
    )
    baseline_m: float = Field(0.5, gt=0.0, le=5.0, description="stereo baseline")
    width_px: int = Field(640, ge=64, le=4096, description="image width")
    height_px: int = Field(480, ge=48, le=4096, description="image height")
    hfov_deg: float = Field(60.0, gt=5.0, lt=170.0, description="horizontal field of view")
    rate_hz: float = Field(2.0, gt=0.0, le=60.0, description="frames per second per pair")
    vary_lighting: bool = Field(False, description="slowly vary the lighting over time")
    light_step_period_s: float = Field(
        0.0, ge=0.0, description="half the lights off in the second half of every period (0: never)"
    )
    ideal_cameras: bool = Field(
        False, description="noise-free renders and the exact calibration (the ideal world)"
    )
    read_noise_e: float = Field(_SENSOR.read_noise_e, ge=0.0, description="sensor read noise, e-")
    full_well_e: float = Field(_SENSOR.full_well_e, gt=0.0, description="sensor full well, e-")
    blur_sigma_px: float = Field(_SENSOR.blur_sigma_px, ge=0.0, le=10.0, description="lens blur σ")
    vignetting: float = Field(
        _SENSOR.vignetting, ge=0.0, le=1.0, description="share of the cos⁴ fall-off left"
    )
    jpeg_quality: int = Field(
        0, ge=0, le=100, description="stream JPEG at this quality, as IP cameras do (0: raw)"
    )
    calib_rotation_sigma_deg: float = Field(
        _CALIB_ERROR.rotation_sigma_deg, ge=0.0, le=5.0, description="published calib error"
    )
    calib_position_sigma_mm: float = Field(
        _CALIB_ERROR.position_sigma_mm, ge=0.0, le=100.0, description="published calib error"
    )
    calib_focal_sigma_pct: float = Field(
        _CALIB_ERROR.focal_sigma_pct, ge=0.0, le=10.0, description="published calib error"
    )
    calib_principal_point_sigma_px: float = Field(
        _CALIB_ERROR.principal_point_sigma_px, ge=0.0, le=50.0, description="published calib error"
    )
    shadows: bool = Field(False, description="render shadows (slower)")
    serve_truth: bool = Field(True, description="answer sim/truth queries")
    frames: int = Field(
        0, ge=0, description="stop after this many frames per pair (0: run until stopped)"
    )

    @model_validator(mode="after")
    def _pairs_exist(self) -> CameraSimSettings:
        known = {pair_name(k) for k in range(self.pair_count)}
        unknown = sorted(set(self.pairs) - known)
        if unknown:
            raise ValueError(
                f"--pairs names {unknown}, but --pair-count {self.pair_count} has only p0…p{self.pair_count - 1}"
            )
        return self

    def rig(self) -> RigSpec:
        return RigSpec(
            pair_count=self.pair_count,
            height_m=self.camera_height_m,
            baseline_m=self.baseline_m,
            width_px=self.width_px,
            height_px=self.height_px,
            hfov_deg=self.hfov_deg,
        )

    def scene_spec(self) -> SceneSpec:
        if self.scene is not None:
            try:
                return load_scene(self.scene)
            except (OSError, ValueError, yaml.YAMLError) as error:  # ValidationError: ValueError
                reason = " ".join(str(error).split())
                startup_error(f"--scene {self.scene}: {reason}")
        return generate_scene(
            self.seed,
            (self.floor_x_m, self.floor_y_m),
            self.floor,
            plain_objects=self.plain_objects,
        )

    def camera_model(self) -> CameraModel:
        if self.ideal_cameras:
            return CameraModel.ideal()
        return CameraModel(
            sensor=SensorParams(
                full_well_e=self.full_well_e,
                read_noise_e=self.read_noise_e,
                blur_sigma_px=self.blur_sigma_px,
                vignetting=self.vignetting,
            ),
            calibration_error=CalibrationError(
                rotation_sigma_deg=self.calib_rotation_sigma_deg,
                position_sigma_mm=self.calib_position_sigma_mm,
                focal_sigma_pct=self.calib_focal_sigma_pct,
                principal_point_sigma_px=self.calib_principal_point_sigma_px,
            ),
        )

    def lighting(self) -> Lighting:
        return Lighting(drift=self.vary_lighting, step_period_s=self.light_step_period_s)


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
    true_calibrations = layout_pairs(settings.rig(), scene.floor_size_m)
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
