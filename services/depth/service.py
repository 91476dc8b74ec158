"""Depth process of one stereo pair: frames in (Zenoh or recordings), tiles out on depth/{pair}/tile."""

from __future__ import annotations

import json
import logging
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import zenoh

from common import keys
from common.camera import StereoCalibration
from common.codec import WIRE_ENCODING, CodecError, decode, encode, pack_arrays
from common.lifecycle import stop_on_signals
from common.logs import RateLimitedLog, setup_logging
from common.messages import (
    CALIB_KIND,
    DETECTIONS_KIND,
    STEREO_KIND,
    TILE_KIND,
    StereoFrameHeader,
    TileHeader,
)
from common.settings import parse_settings, startup_error
from common.zenoh_session import open_session
from services.depth.objects import PixelGrid, detect_objects, detections_header
from services.depth.pipeline import DepthPipeline, to_gray
from services.depth.settings import DepthSettings
from services.depth.sources import (
    InputError,
    LatestSlot,
    check_recording,
    load_calibration,
    recorded_frames,
)

log = logging.getLogger("depth")

StopWait = Callable[[float], bool]
"""Waits up to the given seconds; True once the process is asked to stop."""


def fetch_calibration(
    session: zenoh.Session, settings: DepthSettings, stop_wait: StopWait
) -> StereoCalibration | None:
    """Ask cam/{pair}/calib until a valid answer arrives; a bad answer is logged, not fatal."""
    started = time.monotonic()
    while True:
        for reply in session.get(keys.calib(settings.pair), timeout=2.0):
            if reply.ok is None:
                continue
            try:
                return decode(reply.ok.payload.to_bytes(), CALIB_KIND, StereoCalibration).header
            except CodecError as error:
                log.error(
                    "calibration rejected", extra={"pair": settings.pair, "error": str(error)}
                )
        if settings.calib_timeout_s and time.monotonic() - started > settings.calib_timeout_s:
            raise SystemExit(
                f"no calibration on {keys.calib(settings.pair)} within {settings.calib_timeout_s} s"
            )
        log.info("waiting for calibration", extra={"key": keys.calib(settings.pair)})
        if stop_wait(1.0):
            return None


@dataclass(frozen=True)
class Frame:
    header: StereoFrameHeader
    left: np.ndarray
    right: np.ndarray
    received_ns: int


class TilePublisher:
    """Encodes and publishes tiles; keeps the counters the summary log reports."""

    def __init__(self, session: zenoh.Session, pair: str) -> None:
        # BLOCK: tiles are evidence; a dropped tile is a silent hole in the map.
        self._publisher = session.declare_publisher(
            keys.tile(pair),
            encoding=WIRE_ENCODING,
            congestion_control=zenoh.CongestionControl.BLOCK,
        )
        self._objects = session.declare_publisher(
            keys.objects(pair),
            encoding=WIRE_ENCODING,
            congestion_control=zenoh.CongestionControl.BLOCK,
        )
        self.pair = pair
        self.published = 0
        self.stage_ms_sum: Counter[str] = Counter()

    def publish(
        self,
        pipeline: DepthPipeline,
        left: np.ndarray,
        right: np.ndarray,
        seq: int,
        stamp_ns: int,
        upstream_ms: dict[str, float] | None = None,
    ) -> None:
        """``upstream_ms``: times before processing began (camera, queue), reported with the stages."""
        result = pipeline.process(left, right)
        started = time.perf_counter()
        packed = pack_arrays(result.tile.arrays())
        stage_ms = {
            **(upstream_ms or {}),
            **result.stage_ms,
            "encode": (time.perf_counter() - started) * 1e3,
        }
        window = result.tile.window
        header = TileHeader(
            pair=self.pair,
            seq=seq,
            stamp_ns=stamp_ns,
            resolution_m=result.tile.resolution_m,
            i0=window.i0,
            j0=window.j0,
            cols=window.cols,
            rows=window.rows,
            stage_ms=stage_ms,
        )
        self._publisher.put(encode(TILE_KIND, header, packed_arrays=packed))
        self.published += 1
        # After the tile: measuring objects must not delay the map's evidence.
        started = time.perf_counter()
        rectifier = pipeline.rectifier
        detections = detect_objects(
            result.points,
            PixelGrid.from_valid(np.isfinite(result.evidence_disparity_px)),
            camera_height_m=float(rectifier.C_world[2]),
            pixel_angle_rad=1.0 / float(rectifier.focal_px),
            left_margin_px=pipeline.min_disparity + pipeline.num_disparities,
            params=pipeline.config.model,
        )
        header = detections_header(detections, self.pair, seq, stamp_ns)
        self._objects.put(encode(DETECTIONS_KIND, header))
        stage_ms["objects"] = (time.perf_counter() - started) * 1e3
        self.stage_ms_sum.update(stage_ms)


def _recorded_loop(
    settings: DepthSettings, pipeline: DepthPipeline, publisher: TilePublisher, stop_wait: StopWait
) -> None:
    period_s = 1.0 / settings.rate_hz if settings.rate_hz else 0.0
    assert settings.images is not None
    frames: Iterator[tuple[np.ndarray, np.ndarray]] = recorded_frames(settings.images)
    for seq, (left, right) in enumerate(frames):
        try:
            publisher.publish(pipeline, left, right, seq, time.time_ns())
        except ValueError as error:
            log.error("frame rejected", extra={"seq": seq, "error": str(error)})
        if stop_wait(period_s):
            return


class FrameIntake:
    """Subscriber side: every message is decoded and checked on arrival, so each bad one is counted
    and logged; good frames go to a one-deep slot (the worker takes the newest)."""

    def __init__(self, pipeline: DepthPipeline, max_bytes: int) -> None:
        self._pipeline = pipeline
        self._max_bytes = max_bytes
        self._lock = threading.Lock()
        self._warn = RateLimitedLog(log)
        self.rejected: Counter[str] = Counter()
        self.slot: LatestSlot[Frame] = LatestSlot()

    def on_sample(self, sample: zenoh.Sample) -> None:
        try:
            self.slot.put(self._parse(sample.payload.to_bytes()))
        except (CodecError, KeyError) as error:
            self.reject("malformed", error)
        except (ValueError, cv2.error) as error:
            self.reject("bad_image", error)

    def _parse(self, payload: bytes) -> Frame:
        message = decode(payload, STEREO_KIND, StereoFrameHeader, self._max_bytes)
        if message.header.encoding == "raw":
            left, right = message.arrays["left"], message.arrays["right"]
        else:
            left, right = (
                cv2.imdecode(np.frombuffer(message.blobs[side], np.uint8), cv2.IMREAD_GRAYSCALE)
                for side in ("left", "right")
            )
            if left is None or right is None:
                raise ValueError(f"{message.header.encoding} images do not decode")
        # Gray 8-bit (or RGB, converted here) of the calibration's size, checked on arrival: a
        # 16-bit or 4-channel camera driver is rejected and counted, never crashes the worker.
        left, right = to_gray(left), to_gray(right)
        self._pipeline.check_frame(left, right)
        return Frame(message.header, left, right, time.time_ns())

    def reject(self, reason: str, error: Exception) -> None:
        with self._lock:
            self.rejected[reason] += 1
            total = sum(self.rejected.values())
        self._warn.warning(
            reason, "frame rejected", reason=reason, error=str(error)[:200], rejected=total
        )


def check_search_band(pipeline: DepthPipeline) -> None:
    """A calibration can pass validation and still describe no stereo pair this service can match
    (a 1000 m baseline, a principal point far off the image): its disparity band would not fit the
    image, and SGBM would try to allocate it at the first frame."""
    width = pipeline.rectifier.size[0]
    low, count = pipeline.min_disparity, pipeline.num_disparities
    if low + count > width // 2:
        raise ValueError(
            f"the floor-to-obstacle disparities {low}…{low + count} px do not fit an image "
            f"{width} px wide: check the baseline, focal length and poses"
        )


def main(settings: DepthSettings) -> None:
    setup_logging(f"depth.{settings.pair}", settings.log_level)
    if settings.threads:
        cv2.setNumThreads(settings.threads)
    stop = stop_on_signals()
    try:
        calib_file = load_calibration(settings.calib) if settings.calib else None
        if settings.images is not None:
            check_recording(settings.images)
    except InputError as error:
        startup_error(str(error))
    with open_session(settings) as session:
        calib = calib_file or fetch_calibration(session, settings, stop.wait)
        if calib is None:
            return
        if calib.pair != settings.pair:
            log.warning(
                "calibration names another pair",
                extra={"calib_pair": calib.pair, "pair": settings.pair},
            )
        try:
            pipeline = DepthPipeline(calib, settings.pipeline_config())
            check_search_band(pipeline)
        except (ValueError, cv2.error, MemoryError) as error:
            startup_error(f"calibration of pair {settings.pair} is unusable: {error}")
        publisher = TilePublisher(session, settings.pair)
        intake = FrameIntake(pipeline, int(settings.max_message_mb * 1024 * 1024))

        def health() -> dict[str, Any]:
            n = max(publisher.published, 1)
            return {
                "pair": settings.pair,
                "tiles": publisher.published,
                "skipped": intake.slot.replaced,
                "rejected": dict(intake.rejected),
                "stage_ms_mean": {k: v / n for k, v in publisher.stage_ms_sum.items()},
                "floor_model": pipeline.floor_health(),
            }

        token = session.liveliness().declare_token(
            keys.depth_alive(settings.pair, str(session.zid()))
        )
        health_queryable = session.declare_queryable(
            keys.depth_health(settings.pair),
            # On its own key: a wildcard query (depth/*/health) gets one answer per pair.
            lambda q: q.reply(
                keys.depth_health(settings.pair), json.dumps(health()), encoding="application/json"
            ),
        )
        log.info(
            "started",
            extra={
                "pair": settings.pair,
                "disparities": f"{pipeline.min_disparity}+{pipeline.num_disparities}",
                "baseline_m": calib.baseline_m,
                "input": str(settings.images or keys.stereo(settings.pair)),
            },
        )
        if settings.images is not None:
            _recorded_loop(settings, pipeline, publisher, stop.wait)
        else:
            subscriber = session.declare_subscriber(keys.stereo(settings.pair), intake.on_sample)
            last_summary = time.monotonic()
            while not stop.is_set():
                frame = intake.slot.take(0.5)
                if frame is not None:
                    # camera: capture → arrival here (exposure/readout, or the sim's render, and
                    # transport); queue: waiting here for the worker.
                    upstream_ms = {
                        "camera": (frame.received_ns - frame.header.stamp_ns) / 1e6,
                        "queue": (time.time_ns() - frame.received_ns) / 1e6,
                    }
                    try:
                        publisher.publish(
                            pipeline,
                            frame.left,
                            frame.right,
                            frame.header.seq,
                            frame.header.stamp_ns,
                            upstream_ms,
                        )
                    except (ValueError, cv2.error) as error:  # one bad frame never ends the loop
                        intake.reject("processing_failed", error)
                if time.monotonic() - last_summary >= settings.summary_s:
                    last_summary = time.monotonic()
                    counters = health()
                    stage_ms = counters.pop("stage_ms_mean")
                    log.info(
                        "summary", extra={**counters, **{f"{k}_ms": v for k, v in stage_ms.items()}}
                    )
            subscriber.undeclare()
        health_queryable.undeclare()
        token.undeclare()
    log.info("stopped", extra={"tiles": publisher.published, "rejected": dict(intake.rejected)})


def cli(argv: Sequence[str] | None = None) -> None:
    main(
        parse_settings(
            DepthSettings,
            argv,
            "overgrid depth",
            "Depth process of one stereo pair: images → occupancy tiles.",
        )
    )
