"""Projection agrees with OpenCV to 1e-6 px; analytic Jacobians agree with finite differences."""

import cv2
import numpy as np
import pytest

from graph.camera import FISHEYE, PINHOLE, Camera
from graph.solve.kernels import project_point


def _points_in_front(cam, n=200, seed=0):
    rng = np.random.default_rng(seed)
    # spread over a wide field of view, 1 to 15 m in front of the camera
    d = rng.uniform(1, 15, n)
    xy = rng.uniform(-1.2, 1.2, (n, 2))
    Xc = np.column_stack([xy * d[:, None], d])
    return (Xc - cam.t) @ cam.R  # camera -> world


def _pinhole(cam):
    return Camera(cam.K, [0.08, -0.04, 0.002, -0.001, 0.005], cam.R, cam.t, PINHOLE, cam.size)


def test_fisheye_projection_matches_opencv(rig):
    for cam in rig.cameras:
        X = _points_in_front(cam)
        rvec, _ = cv2.Rodrigues(cam.R)
        ref = cv2.fisheye.projectPoints(X.reshape(-1, 1, 3), rvec, cam.t, cam.K, cam.dist)[0].reshape(-1, 2)
        assert np.abs(cam.project(X) - ref).max() < 1e-6


def test_pinhole_projection_matches_opencv(rig):
    for cam in map(_pinhole, rig.cameras):
        X = _points_in_front(cam, seed=1)
        rvec, _ = cv2.Rodrigues(cam.R)
        ref = cv2.projectPoints(X.reshape(-1, 1, 3), rvec, cam.t, cam.K, cam.dist)[0].reshape(-1, 2)
        assert np.abs(cam.project(X) - ref).max() < 1e-6


@pytest.mark.parametrize("model", [FISHEYE, PINHOLE])
def test_jacobians_match_finite_differences_and_kernel(rig, model):
    cam = rig.cameras[1] if model == FISHEYE else _pinhole(rig.cameras[1])
    X = _points_in_front(cam, 50, seed=2)
    uv, J = cam.project_with_jacobian(X)
    eps = 1e-6
    num = np.stack([(cam.project(X + eps * e) - cam.project(X - eps * e)) / (2 * eps) for e in np.eye(3)], -1)
    assert np.abs(J - num).max() < 1e-4 * np.abs(J).max()
    packed = cam.packed()
    kuv, kJ = np.zeros(2), np.zeros((2, 3))
    for i in range(len(X)):
        ok = project_point(packed, cam.R, cam.t, X[i], kuv, kJ)
        assert ok
        assert np.allclose(kuv, uv[i], atol=1e-9)
        assert np.allclose(kJ, J[i], rtol=1e-9, atol=1e-9)


def test_point_behind_camera_is_nan(rig):
    cam = rig.cameras[0]
    behind = cam.center - 2.0 * cam.R[2]
    assert np.isnan(cam.project(behind[None])).all()
    uv = np.zeros(2)
    assert not project_point(cam.packed(), cam.R, cam.t, behind, uv, np.zeros((2, 3)))
    assert np.isnan(uv).all()
