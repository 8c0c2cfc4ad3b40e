"""Every camera model in the registry keeps its contract: its distortion is OpenCV's projection, its
Jacobians are the derivatives, the compiled kernel agrees with numpy, OpenCV's inverse undoes it,
its intrinsic calibration recovers a simulated lens, and it survives an Anipose calibration file."""

import cv2
import numpy as np
import pytest

from graph.calibrate import calibrate_intrinsics, parse_board
from graph.calibrate.model import intrinsics_of, project
from graph.calibrate.views import BoardViews
from graph.camera import CAMERA_MODELS, DISTORTION_SLOTS, Calibration, Camera, camera_model, undistort_points
from graph.io.calibration import load_calibration, write_anipose_toml
from graph.solve.kernels import project_point

MODELS = sorted(CAMERA_MODELS)
K = np.array([[900.0, 0.0, 640.0], [0.0, 910.0, 360.0], [0.0, 0.0, 1.0]])


def _camera(model: str, seed: int = 0) -> Camera:
    """A camera of ``model`` with small random distortion, looking down +z from near the origin."""
    rng = np.random.default_rng(seed)
    n = camera_model(model).n_coefficients
    a = rng.normal(size=3) * 0.1
    R = np.array([[1.0, -a[2], a[1]], [a[2], 1.0, -a[0]], [-a[1], a[0], 1.0]])
    U, _, Vt = np.linalg.svd(R)
    return Camera(K=K, dist=rng.uniform(-0.05, 0.05, n), R=U @ Vt, t=[0.1, -0.05, 0.2], model=model,
                  size=(1280, 720), name=model)


def _points(cam: Camera, n: int = 200, seed: int = 1) -> np.ndarray:
    """World points 1 to 10 m in front of the camera, up to about 40 degrees off its axis."""
    rng = np.random.default_rng(seed)
    z = rng.uniform(1.0, 10.0, n)
    Xc = np.column_stack([rng.uniform(-0.8, 0.8, (n, 2)) * z[:, None], z])
    return (Xc - cam.t) @ cam.R


def test_registry_codes_and_slots():
    codes = [m.code for m in CAMERA_MODELS.values()]
    assert len(set(codes)) == len(codes)
    assert DISTORTION_SLOTS == max(m.n_coefficients for m in CAMERA_MODELS.values())
    assert all(name == m.name and 0 <= m.min_coefficients <= m.n_coefficients for name, m in CAMERA_MODELS.items())
    with pytest.raises(ValueError, match="unknown camera model 'nope'"):
        camera_model("nope")


@pytest.mark.parametrize("model", MODELS)
def test_projection_is_opencvs(model):
    cam = _camera(model)
    X = _points(cam)
    ref = cam.camera_model.opencv_project(X @ cam.R.T + cam.t, cam.K, cam.dist)
    assert np.abs(cam.project(X) - ref).max() < 1e-6


@pytest.mark.parametrize("model", MODELS)
def test_jacobians_and_the_compiled_kernel(model):
    cam = _camera(model, seed=2)
    X = _points(cam, 60, seed=3)
    uv, J = cam.project_with_jacobian(X)
    eps = 1e-6
    num = np.stack([(cam.project(X + eps * e) - cam.project(X - eps * e)) / (2 * eps) for e in np.eye(3)], -1)
    assert np.abs(J - num).max() < 1e-4 * np.abs(J).max()
    packed = cam.packed()
    assert packed.shape == (5 + DISTORTION_SLOTS,) and packed[0] == cam.camera_model.code
    kuv, kJ = np.zeros(2), np.zeros((2, 3))
    for i in range(len(X)):
        assert project_point(packed, cam.R, cam.t, X[i], kuv, kJ)
        np.testing.assert_allclose(kuv, uv[i], rtol=0, atol=1e-9)
        np.testing.assert_allclose(kJ, J[i], rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("model", MODELS)
def test_intrinsics_jacobian_matches_finite_differences(model):
    cam = _camera(model, seed=4)
    Xc = _points(cam, 60, seed=5) @ cam.R.T + cam.t
    theta = intrinsics_of(cam)
    uv, J_X, J_t = project(theta, model, Xc)
    np.testing.assert_allclose(uv, cam.camera_model.opencv_project(Xc, cam.K, cam.dist), atol=1e-6)
    for j in range(len(theta)):
        step = 1e-6 * max(1.0, abs(theta[j]))
        hi, lo = theta.copy(), theta.copy()
        hi[j] += step
        lo[j] -= step
        num = (project(hi, model, Xc, False) - project(lo, model, Xc, False)) / (2 * step)
        assert np.abs(J_t[:, :, j] - num).max() < 1e-5 * max(1.0, np.abs(num).max()), j


@pytest.mark.parametrize("model", MODELS)
def test_undistort_inverts_the_projection(model):
    cam = _camera(model, seed=6)
    X = _points(cam, seed=7)
    Xc = X @ cam.R.T + cam.t
    xy = undistort_points(cam, cam.project(X))
    np.testing.assert_allclose(xy, Xc[:, :2] / Xc[:, 2:], atol=1e-7)


def _board_views(cam: Camera, board, n: int = 30, noise_px: float = 0.2, seed: int = 9) -> BoardViews:
    """``n`` views of ``board`` 0.7 to 1.3 m in front of ``cam``, tilted up to 30 degrees, spread over
    the image, with Gaussian noise; views not wholly inside the image are left out."""
    rng = np.random.default_rng(seed)
    obj = board.object_points()
    corners = []
    while len(corners) < n:
        a = rng.uniform(-0.5, 0.5, 3) * [1.0, 1.0, 0.6]
        Rb = cv2.Rodrigues(a)[0]
        z = rng.uniform(0.6, 1.2)
        t = np.array([rng.uniform(-0.6, 0.6) * z, rng.uniform(-0.35, 0.35) * z, z]) - Rb @ obj.mean(axis=0)
        uv = cam.project((obj @ Rb.T + t - cam.t) @ cam.R)
        if np.all((uv > 5) & (uv < np.array(cam.size) - 5)):
            corners.append(uv + rng.normal(0.0, noise_px, uv.shape))
    return BoardViews(cam.name, cam.size, [str(i) for i in range(n)], np.array(corners),
                      board_shape=board.corner_grid, square=board.square)


@pytest.mark.parametrize("model", MODELS)
def test_intrinsic_calibration_recovers_a_simulated_lens(model):
    board = parse_board("checkerboard:9x6:0.05")
    truth = _camera(model, seed=10)
    result = calibrate_intrinsics(_board_views(truth, board), board, model=model)
    assert result.camera.model == model and result.rms_px < 0.3  # 0.2 px noise on x and y: 0.28 px
    sd = np.sqrt(np.diag(result.covariance))[:4]
    fk = intrinsics_of(result.camera)[:4] - intrinsics_of(truth)[:4]
    assert np.all(np.abs(fk) < 4 * sd) and np.all(sd < 1.5), (fk, sd)  # focal lengths and centre, within 4 sd
    X = _points(truth, seed=8)
    uv = truth.project(X)
    Xc = (X @ truth.R.T + truth.t)[np.all(np.abs(uv - truth.K[:2, 2]) < 0.9 * truth.K[:2, 2], axis=1)]
    err = np.linalg.norm(result.camera.project(Xc) - truth.camera_model.opencv_project(Xc, truth.K, truth.dist), axis=1)
    assert np.median(err) < 1.5, np.median(err)  # points anywhere in the image land within a pixel or so


def test_every_model_survives_an_anipose_file(tmp_path):
    cams = [_camera(model, seed=i) for i, model in enumerate(MODELS)]
    path = tmp_path / "calibration.toml"
    write_anipose_toml(path, Calibration(cams))
    back = load_calibration(path)
    for a, b in zip(cams, back.cameras):
        assert b.model == a.model and b.name == a.name and b.size == a.size
        np.testing.assert_array_equal(b.dist, a.dist)
        np.testing.assert_array_equal(b.K, a.K)
        np.testing.assert_allclose(b.R, a.R, atol=1e-12)
        X = _points(a, 20)
        np.testing.assert_allclose(b.project(X), a.project(X), atol=1e-9)
