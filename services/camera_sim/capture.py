"""One stereo pair as a site has it: the renderer's light through two real cameras, and the
calibration a calibration procedure would have given (what the pair publishes)."""

from __future__ import annotations

from dataclasses import dataclass, field

from common.arrays import U8
from common.camera import StereoCalibration
from services.camera_sim.calibration_error import CalibrationError, published_calibration
from services.camera_sim.render import SceneRenderer
from services.camera_sim.sensor import CameraSensor, SensorParams


@dataclass(frozen=True)
class CameraModel:
    """How real the cameras are: ``sensor`` None renders ideal frames (the render's own 8 bits)."""

    sensor: SensorParams | None = field(default_factory=SensorParams)
    calibration_error: CalibrationError = field(default_factory=CalibrationError)

    @staticmethod
    def ideal() -> CameraModel:
        return CameraModel(sensor=None, calibration_error=CalibrationError(0.0, 0.0, 0.0, 0.0))


class StereoCapture:
    """Frames of one pair; the caller sets the renderer's time once per round for every pair."""

    def __init__(
        self,
        renderer: SceneRenderer,
        true_calibration: StereoCalibration,
        model: CameraModel,
        seed: int,
    ) -> None:
        self.renderer = renderer
        self.true_calibration = true_calibration
        self.model = model
        self.calibration = published_calibration(true_calibration, model.calibration_error, seed)
        """What the pair publishes on ``cam/{pair}/calib``: the truth, off by the calibration error."""
        pair = true_calibration.pair
        self._sensors = (
            {
                side: CameraSensor(
                    f"{pair}/{side}",
                    camera.width,
                    camera.height,
                    camera.focal_px,
                    model.sensor,
                    seed,
                )
                for side, camera in (
                    ("left", true_calibration.left),
                    ("right", true_calibration.right),
                )
            }
            if model.sensor is not None
            else {}
        )

    def capture(self, stamp_ns: int) -> tuple[U8, U8]:
        """(left, right) 8-bit gray frames at ``stamp_ns`` (the renderer is already at that time)."""
        frames = []
        for side in ("left", "right"):
            camera = getattr(self.true_calibration, side)
            name = f"{self.true_calibration.pair}_{side}"
            sensor = self._sensors.get(side)
            if sensor is None:
                frames.append(self.renderer.render_gray(name, camera.width, camera.height))
                continue
            lag = self.renderer.lighting.lag_ratio(
                stamp_ns / 1e9,
                sensor.params.ae_time_constant_s,
                self.renderer.switched_level(name),
            )
            radiance = self.renderer.render_radiance(name, camera.width, camera.height)
            frames.append(sensor.capture(radiance, stamp_ns, lag))
        return frames[0], frames[1]
