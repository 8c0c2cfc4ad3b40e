"""Skeleton specs, forward kinematics against hand-computed points, and its Jacobian."""

import numpy as np
import pytest

from graph.errors import InputError
from graph.skeleton import available_skeletons, load_skeleton


@pytest.fixture(scope="module")
def cheetah():
    return load_skeleton("cheetah")


def rot_x(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, s], [0, -s, c]])


def rot_y(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, -s], [0, 1, 0], [s, 0, c]])


def rot_z(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]])


def test_cheetah_has_the_papers_dimensions(cheetah):
    assert cheetah.n_params == 25
    assert len(cheetah.markers) == 20
    assert "head" not in cheetah.markers  # virtual root
    assert cheetah.param_names[:6] == ["x_0", "y_0", "z_0", "phi_0", "theta_0", "psi_0"]
    i = cheetah.param_names.index
    assert cheetah.upper[i("phi_0")] == pytest.approx(np.pi / 6)
    assert cheetah.lower[i("theta_4")] == pytest.approx(-np.pi / 1.5)
    assert (cheetah.lower[i("theta_7")], cheetah.upper[i("theta_7")]) == pytest.approx((-np.pi, 0))
    assert (cheetah.lower[i("theta_11")], cheetah.upper[i("theta_11")]) == pytest.approx((0, np.pi))
    assert cheetah.process_noise[i("theta_12")] == 334
    assert "cheetah" in available_skeletons() and "points" in available_skeletons()


def test_forward_kinematics_matches_hand_computation(cheetah):
    rng = np.random.default_rng(3)
    q = rng.uniform(-0.4, 0.4, 25)
    q[:3] = [1.0, 2.0, 0.5]
    q[18], q[20] = -0.7, -0.9  # front knees
    q[22], q[24] = 0.6, 0.8  # back knees
    names = cheetah.param_names
    v = dict(zip(names, q))
    head = q[:3]
    R0 = rot_z(v["psi_0"]) @ rot_x(v["phi_0"]) @ rot_y(v["theta_0"])
    R1 = rot_z(v["psi_1"]) @ rot_x(v["phi_1"]) @ rot_y(v["theta_1"]) @ R0
    R2 = rot_y(v["theta_2"]) @ R1
    R3 = rot_z(v["psi_3"]) @ rot_x(v["phi_3"]) @ rot_y(v["theta_3"]) @ R2
    R4 = rot_z(v["psi_4"]) @ rot_y(v["theta_4"]) @ R3
    R5 = rot_z(v["psi_5"]) @ rot_y(v["theta_5"]) @ R4
    R10 = rot_y(v["theta_10"]) @ R3
    R11 = rot_y(v["theta_11"]) @ R10
    nose = head + R0.T @ [0.055, 0, -0.055]
    neck = head + R1.T @ [-0.28, 0, 0]
    spine = neck + R2.T @ [-0.37, 0, 0]
    tail_base = spine + R3.T @ [-0.37, 0, 0]
    tail1 = tail_base + R4.T @ [-0.28, 0, 0]
    tail2 = tail1 + R5.T @ [-0.36, 0, 0]
    l_hip = tail_base + R3.T @ [0.12, 0.08, -0.06]
    l_back_knee = l_hip + R10.T @ [0, 0, -0.32]
    l_back_ankle = l_back_knee + R11.T @ [0, 0, -0.25]
    pos = dict(zip(cheetah.markers, cheetah.positions(q)))
    for name, expected in [("nose", nose), ("neck_base", neck), ("spine", spine), ("tail_base", tail_base),
                           ("tail1", tail1), ("tail2", tail2), ("l_hip", l_hip), ("l_back_knee", l_back_knee),
                           ("l_back_ankle", l_back_ankle)]:
        assert np.allclose(pos[name], expected, atol=1e-12), name


def test_forward_kinematics_jacobian_matches_finite_differences(cheetah):
    q = np.random.default_rng(4).uniform(-0.5, 0.5, 25)
    _, J = cheetah.positions_and_jacobian(q)
    eps = 1e-6
    num = np.stack([(cheetah.positions(q + eps * e) - cheetah.positions(q - eps * e)) / (2 * eps)
                    for e in np.eye(25)], -1)
    assert np.abs(J - num).max() < 1e-8


def test_points_skeleton_and_custom_spec(tmp_path):
    sk = load_skeleton("points", bodyparts=["snout", "tailbase"], bone_pairs=[("snout", "tailbase")])
    assert sk.n_params == 6 and sk.markers == ["snout", "tailbase"]
    q = np.arange(6.0)
    assert np.allclose(sk.positions(q), [[0, 1, 2], [3, 4, 5]])
    spec = tmp_path / "pendulum.toml"
    spec.write_text(
        'name = "pendulum"\n'
        'params = [{ name = "x", noise = 1 }, { name = "y", noise = 1 }, { name = "z", noise = 1 },\n'
        '          { name = "swing", noise = 5, bounds = ["-pi/2", "pi/2"] }]\n'
        'segments = [{ name = "arm", parent = "world", rotation = [["y", "swing"]] }]\n'
        'points = [{ name = "pivot", root = ["x", "y", "z"] },\n'
        '          { name = "bob", base = "pivot", segment = "arm", offset = [0.0, 0.0, -1.0] }]\n'
        'bones = [["pivot", "bob"]]\n')
    pend = load_skeleton(spec)
    assert pend.markers == ["pivot", "bob"]
    p = pend.positions(np.array([0, 0, 0, np.pi / 2]))
    assert np.allclose(p[1], rot_y(np.pi / 2).T @ [0, 0, -1])
    assert pend.upper[3] == pytest.approx(np.pi / 2)


def test_bad_specs_are_one_line_errors(tmp_path):
    with pytest.raises(InputError, match="unknown skeleton"):
        load_skeleton("dragon")
    bad = tmp_path / "bad.toml"
    bad.write_text("params = [ { name = 'x' }\n")
    with pytest.raises(InputError, match="bad.toml") as e:
        load_skeleton(bad)
    assert "\n" not in str(e.value)
    bad.write_text('params = [{ name = "x" }]\nsegments = []\n'
                   'points = [{ name = "a", base = "b", segment = "s", offset = [0,0,0] }]\n')
    with pytest.raises(InputError, match="before its base"):
        load_skeleton(bad)
