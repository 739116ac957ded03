"""The equidistant (Kannala-Brandt) camera model against OpenCV's ``cv2.fisheye`` and its own inverse."""

import cv2
import numpy as np
import pytest

from runtime.geometry import Camera, NetworkMapping

# TUM-VI cam0 (512x512, equidistant), as its camchain.yaml ships it
TUMVI = Camera(
    190.97847715128717,
    190.9733070521226,
    254.93170605935475,
    256.8974428996504,
    512,
    512,
    (0.0034823894022493434, 0.0007150348452162257, -0.0020532361418706202, 0.00020293673591811182),
    "equidistant",
)


def _points(n=500, max_deg=85.0, seed=0):
    rng = np.random.default_rng(seed)
    theta = np.deg2rad(rng.uniform(0.0, max_deg, n))
    phi = rng.uniform(-np.pi, np.pi, n)
    d = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1)
    return d * rng.uniform(0.5, 10.0, n)[:, None]


def test_known_answer_zero_coefficients():
    cam = Camera(100, 100, 50, 40, 100, 80, (0.0, 0.0, 0.0, 0.0), "equidistant")
    uv, ok = cam.project(np.array([[0.0, 1.0, 1.0], [0.0, 0.0, 3.0]]))
    assert ok.all()
    np.testing.assert_allclose(uv, [[50.0, 40.0 + 100 * np.pi / 4], [50.0, 40.0]], atol=1e-12)
    assert cam.has_distortion and cam.is_fisheye and not cam.pinhole().has_distortion


def test_project_matches_cv2_fisheye():
    p = _points()
    uv, ok = TUMVI.project(p)
    ref, _ = cv2.fisheye.projectPoints(
        p.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), TUMVI.K, np.asarray(TUMVI.dist, dtype=np.float64)
    )
    assert ok.all()
    assert np.abs(uv - ref.reshape(-1, 2)).max() < 1e-6


def test_undistort_points_matches_cv2_fisheye():
    uv, _ = TUMVI.project(_points(max_deg=80.0, seed=1))
    ours = TUMVI.undistort_points(uv)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-14)
    ref = cv2.fisheye.undistortPoints(
        uv.reshape(-1, 1, 2), TUMVI.K, np.asarray(TUMVI.dist), R=np.eye(3), P=TUMVI.K, criteria=crit
    ).reshape(-1, 2)
    # compare where the pinhole pixel is moderate (tan grows without bound towards 90 deg)
    near = np.linalg.norm(ours - [TUMVI.cx, TUMVI.cy], axis=1) < 5000
    assert near.sum() > 400
    assert np.abs(ours[near] - ref[near]).max() < 1e-6


def test_round_trip_below_1e6_px():
    u, v = np.meshgrid(np.arange(0, 512, 7.3), np.arange(0, 512, 6.1))
    uv = np.stack([u.ravel(), v.ravel()], -1)
    p = TUMVI.unproject(uv, np.full(len(uv), 2.0))
    ok = np.isfinite(p).all(1)  # pixels beyond 90 deg have no point in front of the camera
    assert ok.mean() > 0.9
    back, valid = TUMVI.project(p[ok])
    assert valid.all()
    assert np.abs(back - uv[ok]).max() < 1e-6
    p3 = _points(seed=2)
    np.testing.assert_allclose(TUMVI.unproject(TUMVI.project(p3)[0], p3[:, 2]), p3, atol=1e-9)


def test_beyond_90_degrees_is_nan():
    cam = Camera(100, 100, 50, 40, 100, 80, (0.0, 0.0, 0.0, 0.0), "equidistant")
    xn = cam.pixel_to_normalized(np.array([[50.0 + 100 * 1.7, 40.0]]))  # theta = 1.7 rad > pi/2
    assert np.isnan(xn).all()


def test_undistort_image_matches_cv2_fisheye():
    rng = np.random.default_rng(3)
    img = cv2.GaussianBlur(rng.integers(0, 256, (512, 512), dtype=np.uint8), (0, 0), 3)
    mx, my = TUMVI.undistort_maps()
    rx, ry = cv2.fisheye.initUndistortRectifyMap(
        TUMVI.K, np.asarray(TUMVI.dist), np.eye(3), TUMVI.K, (512, 512), cv2.CV_32FC1
    )
    assert max(np.abs(mx - rx).max(), np.abs(my - ry).max()) < 1e-3  # float32 maps
    ours = TUMVI.undistort_image(img).astype(int)
    ref = cv2.remap(img, rx, ry, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT).astype(int)
    assert np.abs(ours - ref).max() <= 1


def test_network_mapping_of_a_fisheye_camera():
    """A point reaches the same network pixel through fisheye pixels + undistortion or the network camera."""
    m = NetworkMapping.fit(512, 512, 224, 224)
    net_cam = m.camera(TUMVI.pinhole())
    p = _points(max_deg=40.0, seed=4)
    direct, _ = net_cam.project(p)
    via = m.points_to_network(TUMVI.undistort_points(TUMVI.project(p)[0]))
    assert np.abs(direct - via).max() < 1e-6


def test_unknown_model_raises():
    with pytest.raises(ValueError, match="camera model 'fov'"):
        Camera(1, 1, 0, 0, 2, 2, (0.0,) * 4, "fov")
