"""Depth process of one stereo pair: frames in (Zenoh or recordings), tiles out on depth/{pair}/tile."""

from __future__ import annotations

import json
import logging
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import zenoh

from common import client, keys
from common.camera import StereoCalibration
from common.codec import WIRE_ENCODING, encode, pack_arrays
from common.lifecycle import stop_on_signals
from common.logs import RateLimitedLog, Transitions, setup_logging
from common.messages import DETECTIONS_KIND, TILE_KIND, StereoFrameHeader, TileHeader
from common.settings import parse_settings, startup_error
from common.zenoh_session import open_session
from services.depth.intake import (
    LatestSlot,
    Rejection,
    StereoFrame,
    build_pipeline,
    check_images,
    decode_calibration,
    decode_stereo_frame,
)
from services.depth.objects import detections_header
from services.depth.pipeline import DepthPipeline, undersampled
from services.depth.settings import DepthSettings
from services.depth.sources import InputError, check_recording, load_calibration, recorded_frames

log = logging.getLogger("depth")

StopWait = Callable[[float], bool]
"""Waits up to the given seconds; True once the process is asked to stop."""


class Counts:
    """Every message this process receives, counted once by outcome (the health reply): frames
    ``received`` = ``processed`` + ``skipped`` + sum of ``rejected`` + the one or two in hand."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._warn = RateLimitedLog(log)
        self.received = 0
        self.processed = 0
        self.rejected: Counter[str] = Counter()
        self.calibration_rejected: Counter[str] = Counter()

    def arrived(self) -> None:
        with self._lock:
            self.received += 1

    def done(self) -> None:
        with self._lock:
            self.processed += 1

    def reject(self, rejection: Rejection) -> None:
        with self._lock:
            self.rejected[rejection.reason] += 1
            total = sum(self.rejected.values())
        self._warn.warning(
            rejection.reason,
            "frame rejected",
            reason=rejection.reason,
            error=rejection.detail[:200],
            rejected=total,
        )

    def reject_calibration(self, rejection: Rejection) -> None:
        with self._lock:
            self.calibration_rejected[rejection.reason] += 1
        self._warn.warning(
            f"calibration {rejection.reason}",
            "calibration rejected",
            reason=rejection.reason,
            error=rejection.detail[:300],
        )

    def snapshot(self) -> dict[str, Any]:
        with self._lock:
            return {
                "received": self.received,
                "processed": self.processed,
                "rejected": dict(self.rejected),
                "calibration_rejected": dict(self.calibration_rejected),
            }


CALIB_RECHECK_S = 5.0
"""A running depth process asks for its calibration again this often (:func:`_watch_calibration`)."""
CALIB_WAIT_REPORT_S = 10.0
"""While no calibration comes, a warning this often naming the pairs cameras do answer for."""


def _ask_calibration(
    session: zenoh.Session,
    settings: DepthSettings,
    counts: Counts,
    current: StereoCalibration | None = None,
) -> DepthPipeline | None:
    """One ask of cam/{pair}/calib: the pipeline of the first usable answer other than
    ``current``; bad answers are counted by reason."""
    for reply in session.get(keys.calib(settings.pair), timeout=2.0):
        if reply.ok is None:
            error = reply.err.payload.to_string() if reply.err is not None else ""
            counts.reject_calibration(Rejection("error_reply", " ".join(error.split())[:200]))
            continue
        calib = decode_calibration(reply.ok.payload.to_bytes())
        if isinstance(calib, Rejection):
            counts.reject_calibration(calib)
            continue
        if calib.pair != settings.pair:  # a camera answering for another pair: not this one's
            counts.reject_calibration(
                Rejection("wrong_pair", f"calibration of pair {calib.pair!r} on this pair's key")
            )
            continue
        if current is not None and calib.model_dump() == current.model_dump():
            continue  # (not ==: pydantic compares cached numpy properties too, and raises)
        try:
            return build_pipeline(calib, settings.pipeline_config())
        except ValueError as error:
            counts.reject_calibration(Rejection("unusable", str(error)))
    return None


def fetch_calibration(
    session: zenoh.Session, settings: DepthSettings, counts: Counts, stop_wait: StopWait
) -> DepthPipeline | None:
    """Ask cam/{pair}/calib until a usable answer arrives; a bad one is counted and logged and the
    process keeps asking (the camera box may be fixed without restarting this one)."""
    started = time.monotonic()
    waiting, report_at_s = False, CALIB_WAIT_REPORT_S
    while True:
        pipeline = _ask_calibration(session, settings, counts)
        if pipeline is not None:
            return pipeline
        if settings.calib_timeout_s and time.monotonic() - started > settings.calib_timeout_s:
            startup_error(
                f"--calib-timeout-s {settings.calib_timeout_s}: no usable calibration on "
                f"{keys.calib(settings.pair)} (rejected: {dict(counts.calibration_rejected)})"
            )
        waited_s = time.monotonic() - started
        if not waiting:
            log.info("waiting for calibration", extra={"key": keys.calib(settings.pair)})
        elif waited_s >= report_at_s:
            # Which pairs a camera does answer for: a --pair no camera has waited in silence.
            answering = sorted(
                str(reply.ok.key_expr).split("/")[1]  # cam/{pair}/calib, as named (keys.pair_of
                # would raise on a pair id it refuses, and end the wait)
                for reply in session.get(keys.CALIB_ALL, timeout=2.0)
                if reply.ok is not None
            )
            log.warning(
                "no calibration yet",
                extra={
                    "key": keys.calib(settings.pair),
                    "waited_s": round(waited_s),
                    "pairs_answering": ",".join(answering) or "none",
                },
            )
            report_at_s = waited_s + CALIB_WAIT_REPORT_S
        waiting = True
        if stop_wait(1.0):
            return None


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
        detections = pipeline.detect_objects(result)
        self._objects.put(
            encode(
                DETECTIONS_KIND,
                detections_header(detections, self.pair, seq, stamp_ns, pipeline.camera_m),
            )
        )
        stage_ms["objects"] = (time.perf_counter() - started) * 1e3
        self.stage_ms_sum.update(stage_ms)


class FrameIntake:
    """The subscriber's callback: counts each message's arrival, decodes and checks it there
    (intake.decode_stereo_frame), so a bad one is counted by reason and never displaces a good
    one; good frames go to a one-deep slot, where the worker takes the newest."""

    def __init__(self, pipeline: DepthPipeline, pair: str, max_bytes: int, counts: Counts) -> None:
        self.image_size = pipeline.calib.image_size
        """The calibration's (width, height): frames of another size are refused."""
        self._pair = pair
        self._max_bytes = max_bytes
        self._counts = counts
        self.slot: LatestSlot[StereoFrame] = LatestSlot()

    def on_sample(self, sample: zenoh.Sample) -> None:
        self._counts.arrived()
        try:
            frame = decode_stereo_frame(
                sample.payload.to_bytes(), self._pair, self.image_size, self._max_bytes
            )
        except Exception as error:  # a defect in decoding: counted, never kills the callback
            frame = Rejection("malformed", f"{type(error).__name__}: {error}")
        if isinstance(frame, Rejection):
            self._counts.reject(frame)
        else:
            self.slot.put(frame)


class Claims:
    """Who else holds a token on this pair (depth/{pair}/alive/*): a second depth process on the
    same pair doubles its evidence in the map, so both say so in the log and in health."""

    def __init__(self, pair: str, instance: str) -> None:
        self._pair = pair
        self.instance = instance
        self._lock = threading.Lock()
        self._others: set[str] = set()

    def on_token(self, sample: zenoh.Sample) -> None:
        try:
            key = str(sample.key_expr)
            if keys.pair_of(key) != self._pair:
                return
            other = keys.instance_of(key)
        except ValueError:
            return
        if other == self.instance:
            return
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self._others.add(other)
            else:
                self._others.discard(other)
        if sample.kind == zenoh.SampleKind.PUT:
            log.warning(
                "another depth process claims this pair",
                extra={"pair": self._pair, "other_instance": other, "instance": self.instance},
            )
        else:
            log.info(
                "the other depth process of this pair is gone",
                extra={"pair": self._pair, "other_instance": other},
            )

    def others(self) -> list[str]:
        with self._lock:
            return sorted(self._others)


def _pipeline_from_file(settings: DepthSettings) -> DepthPipeline | None:
    """The pipeline of ``--calib``, or one start-up line naming the file and what is wrong."""
    if settings.calib is None:
        return None
    try:
        calib = load_calibration(settings.calib)
        return build_pipeline(calib, settings.pipeline_config())
    except InputError as error:
        startup_error(str(error))
    except ValueError as error:
        startup_error(f"--calib {settings.calib}: unusable: {error}")


@dataclass
class Worker:
    """What exists once the calibration is usable; health reads it, the frame loop uses it.
    ``pipeline`` is replaced whole (:meth:`use`) when the camera publishes another calibration;
    a frame in flight finishes with the one it started with."""

    pipeline: DepthPipeline
    publisher: TilePublisher
    intake: FrameIntake
    recalibrated: int = 0
    swapped: str | None = None
    """Why the camera's left and right look swapped (:meth:`DepthPipeline.swapped`), judged on
    the first frame of each calibration with texture enough to tell; None: they do not, or no
    frame has told yet."""
    swap_tries: int = 0
    """Frames of this calibration asked whether left and right look swapped, until one tells
    (SWAP_TRIES at most: a view without texture never does)."""

    def use(self, pipeline: DepthPipeline) -> None:
        self.intake.image_size = pipeline.calib.image_size
        self.pipeline = pipeline
        self.recalibrated += 1
        self.swap_tries = 0

    def check_swap(self, left: np.ndarray, right: np.ndarray) -> None:
        """Once per calibration: a camera's left and right swapped (its cables, or the
        calibration's cameras) map phantom obstacles everywhere; said loudly and in health."""
        if self.swap_tries >= SWAP_TRIES:
            return
        try:
            verdict = self.pipeline.swapped(left, right)
        except Exception as error:  # a check beside the map: it must not cost the frame
            self.swap_tries = SWAP_TRIES
            log.warning("the left/right check failed", extra={"error": repr(error)[:200]})
            return
        # A dark first frame (auto-exposure settling) tells nothing: the next may.
        self.swap_tries = SWAP_TRIES if verdict is not None else self.swap_tries + 1
        if isinstance(verdict, str):
            self.swapped = verdict
            log.error("left and right look swapped", extra={"why": verdict})


def _watch_calibration(
    session: zenoh.Session,
    settings: DepthSettings,
    worker: Worker,
    counts: Counts,
    stop: threading.Event,
) -> None:
    """Asks the camera's calibration again every CALIB_RECHECK_S and rebuilds the pipeline when
    it changed: a camera box restarted with another calibration (a rig raised by a metre) had the
    floor read as obstacles everywhere (IoU 0.80 → 0.05) until the depth process was restarted."""
    while not stop.wait(CALIB_RECHECK_S):
        try:
            pipeline = _ask_calibration(session, settings, counts, worker.pipeline.calib)
        except Exception as error:  # the session closing at a stop, a defect: the next pass asks
            log.warning("calibration check failed", extra={"error": repr(error)[:200]})
            continue
        if pipeline is not None:
            worker.use(pipeline)
            log.warning(
                "calibration changed: pipeline rebuilt, the floor model learns again",
                extra={"pair": settings.pair, "baseline_m": pipeline.calib.baseline_m},
            )
            _say_if_undersampled(pipeline)


def _say_if_undersampled(pipeline: DepthPipeline) -> None:
    """A warning when the images are too small for the map (:func:`undersampled`)."""
    why = undersampled(pipeline.calib.image_size, pipeline.config.downscale)
    if why is not None:
        log.warning("images too small", extra={"pair": pipeline.calib.pair, "why": why})


def _process(
    worker: Worker,
    counts: Counts,
    left: np.ndarray,
    right: np.ndarray,
    header: StereoFrameHeader,
    upstream_ms: dict[str, float] | None = None,
) -> None:
    """One checked frame through the pipeline; whatever it raises (MemoryError, numpy, OpenCV) is
    counted, and the caller's loop takes the next frame."""
    worker.check_swap(left, right)
    try:
        worker.publisher.publish(
            worker.pipeline, left, right, header.seq, header.stamp_ns, upstream_ms
        )
        counts.done()
    except Exception as error:
        counts.reject(Rejection("processing_failed", f"{type(error).__name__}: {error}"))


def _serve_frames(
    session: zenoh.Session, pair: str, worker: Worker, counts: Counts, stop: threading.Event
) -> None:
    subscriber = session.declare_subscriber(keys.stereo(pair), worker.intake.on_sample)
    try:
        while not stop.is_set():
            frame = worker.intake.slot.take(0.5)
            if frame is None:
                continue
            # camera: capture → arrival here (exposure/readout, or the sim's render, and
            # transport); queue: waiting here for the worker.
            upstream_ms = {
                "camera": (frame.received_ns - frame.header.stamp_ns) / 1e6,
                "queue": (time.time_ns() - frame.received_ns) / 1e6,
            }
            _process(worker, counts, frame.left, frame.right, frame.header, upstream_ms)
    finally:
        subscriber.undeclare()  # type: ignore[no-untyped-call]


def _recorded_loop(
    settings: DepthSettings, worker: Worker, counts: Counts, stop_wait: StopWait
) -> bool:
    """Recorded frames pass the same checks and counts as frames over Zenoh. Returns whether
    the recording played to its end (not stopped)."""
    period_s = 1.0 / settings.rate_hz if settings.rate_hz else 0.0
    assert settings.images is not None
    for seq, recorded in enumerate(recorded_frames(settings.images)):
        counts.arrived()
        images = (
            recorded
            if isinstance(recorded, Rejection)
            else check_images(*recorded, worker.intake.image_size)
        )
        if isinstance(images, Rejection):
            counts.reject(images)
        else:
            header = StereoFrameHeader(pair=settings.pair, seq=seq, stamp_ns=time.time_ns())
            _process(worker, counts, *images, header)
        if stop_wait(period_s):
            return False
    return True


def main(settings: DepthSettings) -> None:
    setup_logging(f"depth.{settings.pair}", settings.log_level)
    if settings.threads:
        cv2.setNumThreads(settings.threads)
    stop = stop_on_signals()
    pipeline = _pipeline_from_file(settings)
    if settings.images is not None:
        try:
            check_recording(settings.images, pipeline)
        except InputError as error:
            startup_error(str(error))
    played = False
    with open_session(settings, wait_for_router=True) as session:
        counts = Counts()
        claims = Claims(settings.pair, str(session.zid()))
        worker: Worker | None = None

        def health() -> dict[str, Any]:
            answer: dict[str, Any] = {
                "pair": settings.pair,
                "instance": claims.instance,
                "conflict": claims.others(),
                "state": "waiting_for_calibration" if worker is None else "running",
                **counts.snapshot(),
            }
            if worker is not None:
                published = worker.publisher.published
                stage_ms_sum = dict(worker.publisher.stage_ms_sum)  # the worker adds to it
                answer |= {
                    "tiles": published,
                    "recalibrated": worker.recalibrated,
                    "skipped": worker.intake.slot.replaced,
                    "stage_ms_mean": {k: v / max(published, 1) for k, v in stage_ms_sum.items()},
                    "floor_model": worker.pipeline.floor_health(),
                    "swapped": worker.swapped,
                }
            return answer

        def on_health(query: zenoh.Query) -> None:
            # On its own key: a wildcard query (depth/*/health) gets one answer per pair.
            try:
                payload = json.dumps(health())
            except Exception as error:  # every query gets a reply
                query.reply_err(f"depth/{settings.pair}/health: {type(error).__name__}: {error}")
                return
            query.reply(keys.depth_health(settings.pair), payload, encoding="application/json")

        health_queryable = session.declare_queryable(keys.depth_health(settings.pair), on_health)
        claims_watch = session.liveliness().declare_subscriber(
            keys.DEPTH_ALIVE_ALL, claims.on_token, history=True
        )
        pipeline = pipeline or fetch_calibration(session, settings, counts, stop.wait)
        if pipeline is None:
            return
        if pipeline.calib.pair != settings.pair:
            log.warning(
                "calibration names another pair",
                extra={"calib_pair": pipeline.calib.pair, "pair": settings.pair},
            )
        max_bytes = int(settings.max_message_mb * 1024 * 1024)
        worker = Worker(
            pipeline,
            TilePublisher(session, settings.pair),
            FrameIntake(pipeline, settings.pair, max_bytes, counts),
        )
        token = session.liveliness().declare_token(keys.depth_alive(settings.pair, claims.instance))
        log.info(
            "started",
            extra={
                "pair": settings.pair,
                "instance": claims.instance,
                "disparities": f"{pipeline.min_disparity}+{pipeline.num_disparities}",
                "baseline_m": pipeline.calib.baseline_m,
                "input": str(settings.images or keys.stereo(settings.pair)),
            },
        )
        _say_if_undersampled(pipeline)

        def fusion_health() -> dict[str, Any] | None:
            try:
                return client.health(session, timeout_s=1.0)
            except Exception:  # no fusion, or an answer that is no health: nothing to compare
                return None

        summary = threading.Thread(
            target=_summaries,
            args=(settings.pair, health, fusion_health, settings.summary_s, stop),
            daemon=True,
        )
        summary.start()
        watch = None
        if settings.calib is None:  # from the camera: it may publish another
            watch = threading.Thread(
                target=_watch_calibration,
                args=(session, settings, worker, counts, stop),
                name="depth-calibration",
                daemon=True,
            )
            watch.start()
        if settings.images is not None:
            played = _recorded_loop(settings, worker, counts, stop.wait)
        else:
            _serve_frames(session, settings.pair, worker, counts, stop)
        stop.set()
        summary.join(2.0)
        if watch is not None:
            watch.join(3.0)
        for declared in (claims_watch, health_queryable, token):
            declared.undeclare()  # type: ignore[no-untyped-call]
    log.info("stopped", extra={"tiles": worker.publisher.published, **counts.snapshot()})
    if played and worker.publisher.published == 0:
        # A recording that gave nothing must not look like one that did (exit 0).
        rejected = counts.snapshot().get("rejected", {})
        print(
            f"--images {settings.images}: no frame became a tile (rejected {rejected})",
            file=sys.stderr,
        )
        raise SystemExit(1)


def _summaries(
    pair: str,
    health: Callable[[], dict[str, Any]],
    fusion_health: Callable[[], dict[str, Any] | None],
    period_s: float,
    stop: threading.Event,
) -> None:
    """One summary log line per period, off the worker's path; a warning when a period brought
    no frame (a camera or a router gone: the process itself is well and would say nothing), and
    one when fusion answers but takes none of the tiles (a router's access rules drop a user's
    puts on keys it may not write without a word to the writer)."""
    frames = Transitions(log, "no frame from the camera in the last summary period", "frames again")
    intake = FusionIntake(pair, max(2 * period_s, FUSION_SILENT_MIN_S))
    received_before, tiles_before, blank_before = 0, 0, 0
    while not stop.wait(period_s):
        try:  # a summary line is not worth the thread
            counters = health()
            stage_ms = counters.pop("stage_ms_mean", {})
            log.info("summary", extra={**counters, **{f"{k}_ms": v for k, v in stage_ms.items()}})
            received, tiles = counters.get("received", 0), counters.get("tiles", 0)
            frames.update(received > received_before, pair=pair, period_s=period_s)
            if tiles > tiles_before:
                intake.check(fusion_health(), time.monotonic())
            received_before, tiles_before = received, tiles
            floor = counters.get("floor_model", {})
            blank = floor.get("blank_frames", 0)
            if blank < blank_before:  # a new pipeline (calibration changed) counts from 0
                blank_before = 0
            if blank > blank_before:  # said each period with such a frame, now or gone since
                log.warning(
                    "the camera's images showed nothing (dark, covered, blinded or stuck): "
                    "nothing is mapped from those frames",
                    extra={"pair": pair, "blank_frames": blank - blank_before},
                )
            blank_before = blank
            if floor.get("state") == "no_floor":
                log.warning(
                    "the floor model finds no floor where the calibration puts it: is the "
                    "calibration this pair's, and are left and right the right way round?",
                    extra={"pair": pair},
                )
        except Exception:
            log.exception("summary failed")


SWAP_TRIES = 20
"""Frames asked at most, per calibration, whether left and right look swapped (two rectifications
and floor tests each, a few milliseconds)."""

FUSION_SILENT_MIN_S = 10.0
"""Fusion taking none of a publishing pair's tiles for this long (or two summary periods, if
longer) is said: it compiles its update at its first tile, and may lag a few seconds."""


class FusionIntake:
    """Whether fusion takes this pair's tiles: its count of them (its health) must grow while
    this process publishes some."""

    def __init__(self, pair: str, silent_after_s: float) -> None:
        self.pair = pair
        self.silent_after_s = silent_after_s
        self.taken_before = -1
        self.grew_s = self.answered_s = time.monotonic()
        self.taking = Transitions(
            log,
            "fusion takes none of this pair's tiles: does fusion refuse them (fusion_rejected: "
            "its log says why; a camera clock seconds off its box's is refused as stale), or "
            "does the router not let this user put on depth/PAIR/**?",
            "fusion takes this pair's tiles again",
        )
        self.answering = Transitions(
            log,
            "no fusion answers: this pair's tiles reach no map (is fusion running, in this "
            "namespace and Zenoh network?)",
            "fusion answers again",
        )

    def check(self, fusion_health: dict[str, Any] | None, now_s: float) -> None:
        """After a period in which this process published tiles; ``fusion_health`` None when
        no fusion answers (a recording replayed with no fusion running gave tiles to nobody and
        exit 0, and said nothing)."""
        if fusion_health is not None:
            self.answered_s = now_s
        self.answering.update(now_s - self.answered_s < self.silent_after_s, pair=self.pair)
        if fusion_health is None:
            return
        seen = fusion_health.get("pairs", {}).get(self.pair, {})
        taken = int(seen.get("tiles", 0))
        if taken != self.taken_before:
            self.taken_before, self.grew_s = taken, now_s
        self.taking.update(
            now_s - self.grew_s < self.silent_after_s,
            pair=self.pair,
            silent_s=round(now_s - self.grew_s, 1),
            fusion_rejected=seen.get("rejected", 0),
        )


def cli(argv: Sequence[str] | None = None) -> None:
    main(
        parse_settings(
            DepthSettings,
            argv,
            "overgrid depth",
            "Depth process of one stereo pair: images → occupancy tiles.",
        )
    )
