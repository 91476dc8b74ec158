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
