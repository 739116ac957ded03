"""Known answers and round trips for the project's conventions (runtime/geometry.py)."""

import cv2
import gtsam
import numpy as np
import pytest

from runtime import geometry as g
from runtime.io.euroc import EUROC_CAM0 as EUROC_CAM
from runtime.io.euroc import EUROC_T_B_C0 as EUROC_T_BS


def random_rotations(n, seed=0):
    rng = np.random.default_rng(seed)
    return g.so3_exp(rng.normal(size=(n, 3)))


def test_so3_exp_known_answer_and_log_round_trip():
    R = g.so3_exp(np.array([0.0, 0.0, np.pi / 2]))
    np.testing.assert_allclose(R, [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    rng = np.random.default_rng(1)
    for w in list(rng.normal(size=(20, 3))) + [np.array([1e-10, 0, 0]), np.array([0, np.pi - 1e-7, 0])]:
        if np.linalg.norm(w) > np.pi:
            w = w / np.linalg.norm(w) * (np.linalg.norm(w) % np.pi)
        np.testing.assert_allclose(g.so3_log(g.so3_exp(w)), w, atol=1e-6)
    # skew is the cross product
    a, b = rng.normal(size=3), rng.normal(size=3)
    np.testing.assert_allclose(g.skew(a) @ b, np.cross(a, b), atol=1e-12)


def test_so3_exp_matches_gtsam():
    w = np.array([0.3, -0.2, 0.9])
    np.testing.assert_allclose(g.so3_exp(w), gtsam.Rot3.Expmap(w).matrix(), atol=1e-12)


def test_transform_inverse_and_composition():
    R = random_rotations(2, seed=3)
    T_a_b = g.make_T(R[0], [1.0, 2.0, 3.0])
    T_b_c = g.make_T(R[1], [-0.5, 0.1, 0.2])
    p_c = np.array([[0.3, -0.4, 2.0], [1.0, 1.0, 1.0]])
    # inner frames cancel: T_a_c = T_a_b @ T_b_c
    np.testing.assert_allclose(g.transform(T_a_b @ T_b_c, p_c), g.transform(T_a_b, g.transform(T_b_c, p_c)))
    np.testing.assert_allclose(g.inv_T(T_a_b) @ T_a_b, np.eye(4), atol=1e-12)
    np.testing.assert_allclose(g.inv_T(T_a_b), np.linalg.inv(T_a_b), atol=1e-12)
    assert g.pose_error(T_a_b, T_a_b) == pytest.approx((0.0, 0.0), abs=1e-9)


def test_quaternion_orders_known_answer():
    # 90 degrees about z: w = cos(45 deg), z = sin(45 deg)
    c = np.sqrt(0.5)
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(g.quat_wxyz_to_R([c, 0, 0, c]), R, atol=1e-12)
    np.testing.assert_allclose(g.quat_xyzw_to_R([0, 0, c, c]), R, atol=1e-12)
    np.testing.assert_allclose(g.R_to_quat_wxyz(R), [c, 0, 0, c], atol=1e-12)
    np.testing.assert_allclose(g.R_to_quat_xyzw(R), [0, 0, c, c], atol=1e-12)
    # agrees with gtsam's quaternion (w, x, y, z)
    q = gtsam.Rot3(EUROC_T_BS[:3, :3]).toQuaternion()
    np.testing.assert_allclose(
        np.abs(g.R_to_quat_wxyz(EUROC_T_BS[:3, :3])), np.abs([q.w(), q.x(), q.y(), q.z()]), atol=1e-6
    )


def test_quaternion_round_trip_batch_and_sign():
    R = random_rotations(50, seed=4)
    q = g.R_to_quat_wxyz(R)
    assert q.shape == (50, 4) and np.all(q[:, 0] >= 0)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(g.quat_wxyz_to_R(q), R, atol=1e-12)
    np.testing.assert_allclose(g.quat_wxyz_to_R(-q), R, atol=1e-12)  # q and -q: the same rotation
    np.testing.assert_allclose(g.quat_xyzw_to_R(g.R_to_quat_xyzw(R)), R, atol=1e-12)


def test_gtsam_pose3_round_trip_and_retract_convention():
    T = g.make_T(random_rotations(1, seed=5)[0], [0.4, -1.0, 2.5])
    P = g.to_pose3(T)
    np.testing.assert_allclose(g.from_pose3(P), T, atol=1e-12)
    np.testing.assert_allclose(P.transformFrom(np.array([1.0, 2.0, 3.0])), g.transform(T, [1.0, 2.0, 3.0]))
    # retract is a right perturbation, rotation first: translation moves along the body axes
    xi = np.array([0, 0, 0, 0.1, 0, 0])
    np.testing.assert_allclose(g.from_pose3(P.retract(xi))[:3, 3], T[:3, 3] + 0.1 * T[:3, 0], atol=1e-12)
    np.testing.assert_allclose(g.pose_sigmas(rot_rad=0.1, trans_m=2.0), [0.1] * 3 + [2.0] * 3)


def test_camera_projection_known_answer_and_round_trip():
    cam = g.Camera(100.0, 120.0, 50.0, 40.0, 100, 80)
    uv, valid = cam.project(np.array([[1.0, -0.5, 2.0], [0.0, 0.0, -1.0]]))
    np.testing.assert_allclose(uv[0], [100.0, 10.0])
    assert valid.tolist() == [True, False]
    # distorted camera: unproject(project(p)) == p
    rng = np.random.default_rng(6)
    p = np.column_stack(
        [rng.uniform(-1.0, 1.0, 200), rng.uniform(-0.6, 0.6, 200), rng.uniform(1.0, 5.0, 200)]
    )
    uv, _ = EUROC_CAM.project(p)
    assert EUROC_CAM.in_image(uv).all()
    np.testing.assert_allclose(EUROC_CAM.unproject(uv, p[:, 2]), p, atol=1e-8)


def test_distortion_matches_opencv():
    rng = np.random.default_rng(7)
    p = np.column_stack([rng.uniform(-1.0, 1.0, 50), rng.uniform(-0.6, 0.6, 50), rng.uniform(1.0, 5.0, 50)])
    uv, _ = EUROC_CAM.project(p)
    dist = np.array([*EUROC_CAM.dist, 0.0])
    uv_cv, _ = cv2.projectPoints(p, np.zeros(3), np.zeros(3), EUROC_CAM.K, dist)
    np.testing.assert_allclose(uv, uv_cv[:, 0], atol=1e-6)
    # OpenCV's default 5 iterations stop short near the corners; ask it to converge
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    und = cv2.undistortPoints(uv.reshape(-1, 1, 2), EUROC_CAM.K, dist, R=None, P=EUROC_CAM.K, criteria=crit)[
        :, 0
    ]
    np.testing.assert_allclose(EUROC_CAM.undistort_points(uv), und, atol=1e-4)


def test_undistort_image_moves_pixels_to_pinhole_positions():
    cam = EUROC_CAM
    p = np.array([0.8, 0.5, 2.0])  # lands near a corner where distortion is strong
    uv_d, _ = cam.project(p)
    uv_p, _ = cam.pinhole().project(p)
    assert np.linalg.norm(uv_d - uv_p) > 5.0
    img = np.zeros((cam.height, cam.width), np.uint8)
    r, c = np.round(uv_d[1]).astype(int), np.round(uv_d[0]).astype(int)
    img[r - 2 : r + 3, c - 2 : c + 3] = 255
    und = cam.undistort_image(img)
    vv, uu = np.nonzero(und > 128)
    assert np.hypot(uu.mean() - uv_p[0], vv.mean() - uv_p[1]) < 1.0


def test_network_mapping_points_intrinsics_and_image_agree():
    cam = g.Camera(518.86, 519.47, 325.58, 253.74, 640, 480)
    m = g.NetworkMapping.fit(640, 480, 224, 224)
    assert m.scale == pytest.approx(224 / 480)
    net_cam = m.camera(cam)
    rng = np.random.default_rng(8)
    p = np.column_stack([rng.uniform(-0.5, 0.5, 30), rng.uniform(-0.4, 0.4, 30), rng.uniform(1.0, 4.0, 30)])
    uv_cam, _ = cam.project(p)
    uv_net, _ = net_cam.project(p)
    np.testing.assert_allclose(m.points_to_network(uv_cam), uv_net, atol=1e-9)
    np.testing.assert_allclose(m.points_from_network(uv_net), uv_cam, atol=1e-9)
    # the image follows the same mapping (nearest for depth, area/linear for images)
    for nearest in (True, False):
        img = np.zeros((480, 640), np.float32)
        img[200:220, 400:420] = 1.0  # a 20x20 block centred at (409.5, 209.5)
        out = m.image_to_network(img, nearest=nearest)
        assert out.shape == (224, 224)
        vv, uu = np.nonzero(out > 0.5)
        centre = m.points_to_network(np.array([409.5, 209.5]))
        assert np.hypot(uu.mean() - centre[0], vv.mean() - centre[1]) < 0.6
    with pytest.raises(ValueError, match="640x480"):
        m.image_to_network(np.zeros((100, 100), np.uint8))
