"""The simulated cameras behave like real ones: noise statistics, exposure, lighting steps,
calibration error, JPEG — each a pure function of (frame time, camera, seed)."""

import math

import cv2
import numpy as np
import pytest

from common.camera import StereoCalibration
from services.camera_sim.calibration_error import CalibrationError, published_calibration
from services.camera_sim.capture import CameraModel, StereoCapture
from services.camera_sim.lighting import STEP_LEVEL, Lighting, switched_share
from services.camera_sim.render import SceneRenderer
from services.camera_sim.rig import RigSpec, floor_points_xy_m, layout_pairs
from services.camera_sim.scene import SceneSpec
from services.camera_sim.sensor import DN_MAX, CameraSensor, SensorParams, auto_exposure
from services.camera_sim.service import frame_payload, jpeg_encoder
from services.depth.intake import StereoFrame, decode_stereo_frame

FLAT = np.full((240, 320), 0.5, dtype=np.float32)
NO_OPTICS = SensorParams(blur_sigma_px=0.0, vignetting=0.0, prnu_pct=0.0)


def _rotation_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    cos = (np.trace(a[:3, :3].T @ b[:3, :3]) - 1) / 2
    return math.degrees(math.acos(min(1.0, max(-1.0, cos))))


def test_noise_on_a_flat_patch_is_shot_plus_read_noise() -> None:
    sensor = CameraSensor("p0/left", 320, 240, 277.0, NO_OPTICS, seed=1)
    frames = np.stack([sensor.capture(FLAT, stamp_ns=k) for k in range(8)]).astype(np.float64)
    mean_dn = frames.mean()
    assert mean_dn == pytest.approx(NO_OPTICS.ae_target_dn, abs=0.5)  # auto-exposure's target
    electrons = mean_dn / DN_MAX * NO_OPTICS.full_well_e
    expected_dn = math.sqrt(electrons + NO_OPTICS.read_noise_e**2) * DN_MAX / NO_OPTICS.full_well_e
    expected_dn = math.sqrt(expected_dn**2 + 1 / 12)  # 8-bit quantisation
    assert frames.std(axis=0, ddof=1).mean() == pytest.approx(expected_dn, rel=0.1)
    more_read_noise = CameraSensor(
        "p0/left", 320, 240, 277.0, SensorParams(**{**NO_OPTICS.__dict__, "read_noise_e": 150.0}), 1
    )
    noisier = np.stack([more_read_noise.capture(FLAT, k) for k in range(8)]).astype(np.float64)
    assert noisier.std(axis=0, ddof=1).mean() > 1.8 * frames.std(axis=0, ddof=1).mean()


def test_frames_are_a_pure_function_of_time_camera_and_seed() -> None:
    a = CameraSensor("p0/left", 320, 240, 277.0, SensorParams(), seed=3)
    b = CameraSensor("p0/left", 320, 240, 277.0, SensorParams(), seed=3)
    assert np.array_equal(a.capture(FLAT, 42), b.capture(FLAT, 42))
    assert not np.array_equal(a.capture(FLAT, 42), a.capture(FLAT, 43))
    other_camera = CameraSensor("p0/right", 320, 240, 277.0, SensorParams(), seed=3)
    assert not np.array_equal(a.capture(FLAT, 42), other_camera.capture(FLAT, 42))


def test_vignetting_darkens_the_corners_and_blur_softens_edges() -> None:
    sensor = CameraSensor("p0/left", 320, 240, 277.0, SensorParams(vignetting=0.5), seed=0)
    frame = sensor.capture(FLAT, 0).astype(np.float64)
    assert frame[:20, :20].mean() < 0.9 * frame[110:130, 150:170].mean()
    edge = np.zeros((240, 320), np.float32)
    edge[:, 160:] = 0.8
    sharp = CameraSensor("c", 320, 240, 277.0, NO_OPTICS, 0).capture(edge, 0).astype(float)
    blurred_params = SensorParams(**{**NO_OPTICS.__dict__, "blur_sigma_px": 1.5})
    blurred = CameraSensor("c", 320, 240, 277.0, blurred_params, 0).capture(edge, 0).astype(float)
    assert (
        np.abs(np.diff(blurred[:, 150:170], axis=1)).max()
        < 0.6 * np.abs(np.diff(sharp[:, 150:170], axis=1)).max()
    )


def test_auto_exposure_adds_gain_only_past_its_longest_exposure() -> None:
    bright = auto_exposure(0.5, 1.0, SensorParams())
    dark = auto_exposure(0.05, 1.0, SensorParams())
    assert bright.gain == 1.0
    assert dark.gain > 1.0 and dark.electrons_per_radiance == SensorParams().white_e_at_max_exposure


def test_a_lighting_step_darkens_frames_until_auto_exposure_catches_up() -> None:
    lighting = Lighting(step_period_s=20.0)
    (step_s,) = lighting.steps_s(1001.0, 1015.0)  # lights go half off at 1010 s
    assert step_s == 1010.0 and lighting.level(1010.5) == STEP_LEVEL
    tau = SensorParams().ae_time_constant_s
    assert lighting.lag_ratio(step_s - 1.0, tau) == pytest.approx(1.0)
    assert lighting.lag_ratio(step_s + 0.01, tau) == pytest.approx(STEP_LEVEL, abs=0.02)
    assert lighting.lag_ratio(step_s + 10 * tau, tau) == pytest.approx(1.0, abs=1e-3)
    # Rendered: the step reaches the images, then the frame mean recovers.
    calib = layout_pairs(RigSpec(pair_count=1), (12.0, 10.0))[0]
    renderer = SceneRenderer(SceneSpec(floor="concrete"), [calib], lighting=lighting)
    capture = StereoCapture(renderer, calib, CameraModel(), seed=0)
    means = {}
    for label, t_s in (
        ("before", step_s - 1.0),
        ("just after", step_s + 0.05),
        ("later", step_s + 5.0),
    ):
        renderer.set_time(t_s)
        means[label] = float(capture.capture(int(t_s * 1e9))[0].mean())
    renderer.close()
    assert means["just after"] < 0.7 * means["before"]
    assert means["later"] == pytest.approx(means["before"], rel=0.05)


def test_a_step_switches_off_the_luminaires_over_one_half_of_the_hall() -> None:
    floor_m = (12.0, 10.0)
    dark, middle, lit = switched_share(np.array([[1.5, 5.0], [6.0, 5.0], [10.5, 5.0]]), floor_m)
    assert dark < 0.35 < middle < 0.65 < lit
    for size_m in (floor_m, (9.0, 7.0), (10.0, 10.0), (20.0, 15.0), (4.0, 4.0), (1.0, 1.0)):
        grid = np.stack(
            np.meshgrid(np.linspace(0, size_m[0], 61), np.linspace(0, size_m[1], 51)), axis=-1
        )
        share = switched_share(grid, size_m)
        assert float(share.mean()) == pytest.approx(STEP_LEVEL, abs=0.01)  # half the light
        assert np.all((share > 0.0) & (share < 1.0))
    # Rendered: across one pair's view (p0, over the dark half) the floor darkens by a factor
    # that grows toward the lit half (image x runs along world x), not by one factor.
    calib = layout_pairs(RigSpec(pair_count=4), floor_m)[0]
    renderer = SceneRenderer(
        SceneSpec(floor="concrete"), [calib], lighting=Lighting(step_period_s=20.0)
    )
    radiance = []
    for t_s in (1005.0, 1015.0):  # all on, then the half off
        renderer.set_time(t_s)
        radiance.append(renderer.render_radiance("p0_left", 320, 240))
    ratio = radiance[1] / np.maximum(radiance[0], 1e-3)
    far, near = float(np.median(ratio[:, 20:60])), float(np.median(ratio[:, -60:-20]))
    assert 0.2 < far < 0.4 and near > 1.4 * far
    # Auto-exposure's step is the camera's own: p0 keeps about 0.38 of its view's light.
    level = renderer.switched_level("p0_left")
    assert level == pytest.approx(float(np.mean(ratio)), abs=0.03) and level < 0.45
    tau = SensorParams().ae_time_constant_s
    lighting = Lighting(step_period_s=20.0)
    assert lighting.lag_ratio(1010.01, tau, level) == pytest.approx(level, abs=0.02)
    assert lighting.lag_ratio(1010.0 + 10 * tau, tau, level) == pytest.approx(1.0, abs=1e-3)
    renderer.close()


def test_each_pixels_ray_meets_the_floor_where_the_camera_projects_that_point() -> None:
    camera = layout_pairs(RigSpec(pair_count=4), (12.0, 10.0))[1].left
    floor_xy_m = floor_points_xy_m(camera, 64, 48)
    points = np.concatenate([floor_xy_m.reshape(-1, 2), np.zeros((64 * 48, 1))], axis=1)
    pixels = camera.project(points)[:, :2].reshape(48, 64, 2)  # at the camera's resolution
    v, u = np.mgrid[0:48, 0:64]
    assert np.abs(pixels[..., 0] - ((u + 0.5) * camera.width / 64 - 0.5)).max() < 1e-6
    assert np.abs(pixels[..., 1] - ((v + 0.5) * camera.height / 48 - 0.5)).max() < 1e-6


def test_published_calibration_is_off_by_the_seeded_error_and_exact_at_zero() -> None:
    calib = layout_pairs(RigSpec(pair_count=2), (12.0, 10.0))[1]
    error = CalibrationError()
    published = published_calibration(calib, error, seed=5)
    assert published.model_dump() == published_calibration(calib, error, 5).model_dump()
    assert published.model_dump() != published_calibration(calib, error, 6).model_dump()
    for side in ("left", "right"):
        true, off = getattr(calib, side), getattr(published, side)
        angle = _rotation_angle_deg(true.T_world_cam_array, off.T_world_cam_array)
        assert 0.001 < angle < 6 * error.rotation_sigma_deg
        offset_mm = 1000 * np.linalg.norm(true.position_world - off.position_world)
        assert 0.01 < offset_mm < 6 * error.position_sigma_mm
        assert abs(off.focal_px / true.focal_px - 1) < 6 * error.focal_sigma_pct / 100
    assert abs(published.baseline_m - calib.baseline_m) < 0.005
    exact = published_calibration(calib, CalibrationError(0.0, 0.0, 0.0, 0.0), seed=5)
    assert exact.model_dump() == calib.model_dump()
    assert CameraModel.ideal().calibration_error.exact


def test_jpeg_frames_decode_where_the_depth_service_takes_them() -> None:
    calib = layout_pairs(RigSpec(pair_count=1), (12.0, 10.0))[0]
    renderer = SceneRenderer(SceneSpec(), [calib])
    renderer.set_time(0.0)
    left, right = StereoCapture(renderer, calib, CameraModel(), 0).capture(0)
    renderer.close()
    encode_jpeg = jpeg_encoder(85)
    assert encode_jpeg is not None and jpeg_encoder(0) is None
    payload = frame_payload({"pair": "p0", "seq": 0, "stamp_ns": 1}, left, right, encode_jpeg)
    assert len(payload) < left.nbytes  # compressed
    decoded = cv2.imdecode(np.frombuffer(encode_jpeg(left), np.uint8), cv2.IMREAD_GRAYSCALE)
    assert decoded is not None and decoded.shape == left.shape
    assert np.abs(decoded.astype(int) - left.astype(int)).mean() < 3.0


def test_depth_intake_accepts_the_sims_jpeg_frames() -> None:
    calib: StereoCalibration = layout_pairs(RigSpec(pair_count=1), (12.0, 10.0))[0]
    renderer = SceneRenderer(SceneSpec(), [calib])
    renderer.set_time(0.0)
    left, right = StereoCapture(renderer, calib, CameraModel(), 0).capture(0)
    renderer.close()
    payload = frame_payload({"pair": "p0", "seq": 3, "stamp_ns": 1}, left, right, jpeg_encoder(90))
    frame = decode_stereo_frame(payload, "p0", calib.image_size, 32 << 20)
    assert isinstance(frame, StereoFrame)
    assert frame.header.encoding == "jpeg" and frame.left.shape == (480, 640)
