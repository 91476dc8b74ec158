"""Settings of the camera_sim process: flags and OVERGRID_* variables (common.settings)."""

from __future__ import annotations

from pathlib import Path

import yaml
from pydantic import Field, field_validator, model_validator
from pydantic_settings import SettingsConfigDict

from common.settings import CommaList, OvergridParams, ZenohSettings, startup_error
from services.camera_sim.calibration_error import CalibrationError
from services.camera_sim.capture import CameraModel
from services.camera_sim.lighting import Lighting
from services.camera_sim.rig import RigSpec, pair_name
from services.camera_sim.scene import FloorKind, SceneSpec, generate_scene, load_scene
from services.camera_sim.sensor import SensorParams

MIN_LIGHT_STEP_PERIOD_S = 1.0
"""Light steps a second apart at the most (a period of 1e-300 s overflowed the step's count)."""
_SENSOR = SensorParams()
_CALIB_ERROR = CalibrationError()


class CameraSimParams(OvergridParams):
    """What the simulator renders and serves: the settings without the Zenoh session, which
    ``overgrid up`` nests and hands over unchanged."""

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
    rig: RigSpec = Field(default_factory=RigSpec)
    pairs: CommaList = Field(
        default_factory=list, description="render only these pairs (e.g. p0,p2)"
    )
    rate_hz: float = Field(2.0, ge=0.01, le=60.0, description="frames per second per pair")
    vary_lighting: bool = Field(False, description="slowly vary the lighting over time")
    light_step_period_s: float = Field(
        0.0,
        ge=0.0,
        le=1e6,
        description="half the lights off in the second half of every period (0: never, else ≥ 1)",
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
    def _pairs_exist(self) -> CameraSimParams:
        count = self.rig.pair_count
        unknown = sorted(set(self.pairs) - set(self.pair_names()))
        if unknown:
            raise ValueError(
                f"--pairs names {unknown}, but --pair-count {count} has only p0…p{count - 1}"
            )
        return self

    @field_validator("light_step_period_s")
    @classmethod
    def _a_period_or_never(cls, period_s: float) -> float:
        if 0.0 < period_s < MIN_LIGHT_STEP_PERIOD_S:
            raise ValueError(f"0 (never) or at least {MIN_LIGHT_STEP_PERIOD_S:g} s")
        return period_s

    def pair_names(self) -> list[str]:
        """Every pair of the rig."""
        return [pair_name(k) for k in range(self.rig.pair_count)]

    def rendered_pairs(self) -> list[str]:
        """The pairs this simulator renders: ``--pairs``, else all of them."""
        return list(self.pairs) or self.pair_names()

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


class CameraSimSettings(ZenohSettings, CameraSimParams):
    """The camera_sim process: the simulator's parameters on a Zenoh session."""

    model_config = SettingsConfigDict(cli_shortcuts={"rig.height-m": "camera-height-m"})
