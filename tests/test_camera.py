import numpy as np
import pytest
from pydantic import ValidationError

from common.camera import PinholeCamera, StereoCalibration, intrinsics_from_hfov, look_down_pose


def _camera(x: float, width: int = 640) -> PinholeCamera:
    return PinholeCamera(
        width=width,
        height=480,
        K=intrinsics_from_hfov(width, 480, 60).tolist(),
        T_world_cam=look_down_pose(x, 0.0, 6.0).tolist(),
    )


def test_look_down_camera_projects_the_point_below_to_the_principal_point() -> None:
    camera = _camera(1.0)
    u, v, z = camera.project([(1.0, 0.0, 0.0)])[0]
    assert (u, v, z) == pytest.approx((319.5, 239.5, 6.0))
    # +x world is image right, +y world is image up (v decreases).
    u2, v2, _ = camera.project([(1.5, 0.5, 0.0)])[0]
    assert u2 > u and v2 < v


def test_baseline_and_relative_pose() -> None:
    calib = StereoCalibration(pair="p0", left=_camera(0.0), right=_camera(0.5))
    assert calib.baseline_m == pytest.approx(0.5)
    # OpenCV's T of stereoRectify: left origin seen from the right camera is at x = -b.
    np.testing.assert_allclose(calib.T_right_left[:3, 3], [-0.5, 0, 0], atol=1e-12)


def test_zero_baseline_and_size_mismatch_are_clear_errors() -> None:
    with pytest.raises(ValidationError, match="baseline"):
        StereoCalibration(pair="p0", left=_camera(0.0), right=_camera(0.0))
    with pytest.raises(ValidationError, match="differ in size"):
        StereoCalibration(pair="p0", left=_camera(0.0), right=_camera(0.5, width=320))


def test_non_rotation_pose_is_rejected() -> None:
    pose = np.eye(4)
    pose[0, 0] = 2.0
    with pytest.raises(ValidationError, match="rotation"):
        PinholeCamera(width=4, height=4, K=np.eye(3).tolist(), T_world_cam=pose.tolist())


@pytest.mark.parametrize(
    ("row", "col", "value", "message"),
    [
        (2, 2, 0.0, r"K must be \[\[fx, s, cx\], \[0, fy, cy\], \[0, 0, 1\]\]"),
        (2, 0, 0.01, r"K must be"),
        (1, 0, 3.0, r"K must be"),
        (0, 1, 5000.0, "skew 5000 px"),
    ],
)
def test_an_intrinsic_matrix_of_no_pinhole_camera_is_rejected(
    row: int, col: int, value: float, message: str
) -> None:
    """Accepted before, it made tiles: a third row [0, 0, 0], or a skew of 5000 px."""
    k = intrinsics_from_hfov(640, 480, 60)
    _camera(0.0)  # as made, it is fine
    k[row, col] = value
    with pytest.raises(ValidationError, match=message):
        PinholeCamera(
            width=640, height=480, K=k.tolist(), T_world_cam=look_down_pose(0, 0, 6).tolist()
        )


def test_a_rotation_typed_to_four_decimals_is_taken_as_the_nearest_rotation() -> None:
    """A 10° tilt written to four decimals was refused (tolerance 1e-5, no residual named)."""
    tilt = np.radians(10.0)
    pose = look_down_pose(1.0, 2.0, 6.0) @ np.array(
        [
            [1, 0, 0, 0],
            [0, np.cos(tilt), -np.sin(tilt), 0],
            [0, np.sin(tilt), np.cos(tilt), 0],
            [0, 0, 0, 1],
        ]
    )
    camera = PinholeCamera(
        width=640,
        height=480,
        K=intrinsics_from_hfov(640, 480, 60).tolist(),
        T_world_cam=np.round(pose, 4).tolist(),
    )
    rotation = camera.T_world_cam_array[:3, :3]
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(rotation, pose[:3, :3], atol=1e-4)
    skewed = pose.copy()
    skewed[0, 1] += 0.01
    with pytest.raises(ValidationError, match=r"R·Rᵀ − I\| 0\.0098, at most 0\.001"):
        PinholeCamera(width=640, height=480, K=camera.K, T_world_cam=skewed.tolist())


def test_a_calibration_key_overgrid_does_not_know_is_refused() -> None:
    """``distortion:`` for ``dist:`` ran with no distortion at all, silently."""
    camera = _camera(0.0).model_dump(mode="json")
    with pytest.raises(ValidationError, match="distortion"):
        PinholeCamera.model_validate(camera | {"distortion": [-0.3, 0.1, 0, 0, 0]})
    with pytest.raises(ValidationError, match=r"R\n  Extra inputs are not permitted"):
        StereoCalibration.model_validate(
            {"pair": "p0", "left": camera, "right": _camera(0.5).model_dump(), "R": np.eye(3)}
        )
