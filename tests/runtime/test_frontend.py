"""Frontend: triangulation known answers, bucketed detection, KLT tracking, keyframe selection."""

import cv2
import numpy as np
import pytest

from runtime.frontend.features import FeatureConfig, FeatureDetector
from runtime.frontend.keyframes import KeyframeConfig, KeyframeSelector, rotation_compensated_parallax
from runtime.frontend.tracking import FeatureTracker, TrackerConfig
from runtime.frontend.triangulation import TriangulationConfig, stack_views, triangulate
from runtime.geometry import Camera, inv_T, make_T, so3_exp
from tests.runtime.synth import EUROC_CAM, EUROC_T_BS


def _views(X, centres, seed=0):
    """Cameras at ``centres`` looking at the mean of X (small random roll): T_w_c (V,4,4), xn (M,V,2)."""
    rng = np.random.default_rng(seed)
    target = X.mean(0)
    Ts = []
    for c in centres:
        z = target - c
        z /= np.linalg.norm(z)
        x = np.cross([0, 0, 1.0], z)
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        R = np.stack([x, y, z], 1) @ so3_exp(np.array([0, 0, rng.normal(0, 0.05)]))
        Ts.append(make_T(R, c))
    Ts = np.array(Ts)
    p_c = (
        np.einsum("vij,mj->mvi", np.array([inv_T(T)[:3, :3] for T in Ts]), X)
        + np.array([inv_T(T)[:3, 3] for T in Ts])[None]
    )
    return Ts, p_c[..., :2] / p_c[..., 2:3], p_c[..., 2]


def test_triangulation_known_answer_multiview():
    rng = np.random.default_rng(0)
    X = rng.uniform([-1, -1, 4], [1, 1, 6], (50, 3))
    centres = np.array([[0, 0, 0], [0.3, 0, 0], [0.6, 0.1, 0], [0.9, 0.0, 0.1]], float)
    Ts, xn, _ = _views(X, centres)
    M, V = 50, 4
    mask = np.ones((M, V), bool)
    mask[::3, 1] = False  # some points miss a view
    P, ok, diag = triangulate(np.broadcast_to(Ts, (M, V, 4, 4)), xn, mask, focal=458.0)
    assert ok.all()
    assert np.abs(P - X).max() < 1e-8
    assert np.all(diag["max_err_px"] < 1e-6)
    # with 0.5 px noise the error stays a few millimetres per metre of depth
    xn_noisy = xn + rng.normal(0, 0.5 / 458.0, xn.shape)
    P, ok, _ = triangulate(np.broadcast_to(Ts, (M, V, 4, 4)), xn_noisy, mask, focal=458.0)
    assert ok.mean() > 0.9
    assert np.median(np.linalg.norm(P - X, axis=1)) < 0.03


def test_tracks_of_different_lengths_stack_into_the_triangulation_arrays():
    rng = np.random.default_rng(1)
    X = rng.uniform([-1, -1, 4], [1, 1, 6], (6, 3))
    centres = np.array([[0, 0, 0], [0.3, 0, 0], [0.6, 0.1, 0], [0.9, 0.0, 0.1]], float)
    Ts, xn, _ = _views(X, centres)
    frames = [np.array([0, 1, 2, 3]), np.array([1, 3]), np.array([0, 2, 3]), np.array([3, 0]), [1, 2], [0, 1]]
    T, x, mask = stack_views(Ts, [(np.asarray(f), xn[m, f]) for m, f in enumerate(frames)])
    assert T.shape == (6, 4, 4, 4) and mask.sum(1).tolist() == [4, 2, 3, 2, 2, 2]
    assert np.array_equal(T[3, 0], Ts[3]) and np.array_equal(x[3, 1], xn[3, 0]) and not mask[1, 2:].any()
    P, ok, _ = triangulate(T, x, mask, focal=458.0)
    assert ok.all() and np.abs(P - X).max() < 1e-8


def test_triangulation_rejects_low_parallax_and_points_behind():
    X = np.array([[0.0, 0.0, 5.0], [0.2, 0.1, 5.0]])
    Ts, xn, _ = _views(X, np.array([[0, 0, 0], [0.05, 0, 0]], float))  # 0.6 deg of parallax
    P, ok, diag = triangulate(np.broadcast_to(Ts, (2, 2, 4, 4)), xn, np.ones((2, 2), bool), focal=458.0)
    assert not ok.any() and np.all(diag["parallax_deg"] < 1.0)
    # mirrored observation: the ray geometry puts the point behind the cameras
    Ts, xn, _ = _views(X, np.array([[0, 0, 0], [1.0, 0, 0]], float))
    P, ok, _ = triangulate(np.broadcast_to(Ts, (2, 2, 4, 4)), xn, np.ones((2, 2), bool), focal=458.0)
    assert ok.all()
    T_flip = Ts.copy()
    T_flip[:, :3, :3] = T_flip[:, :3, :3] @ np.diag([-1.0, -1.0, 1.0]) @ np.diag([1.0, 1.0, 1.0])
    T_back = Ts.copy()
    T_back[:, :3, :3] = Ts[:, :3, :3] @ np.diag([1.0, -1.0, -1.0])  # cameras turned around
    P, ok, diag = triangulate(np.broadcast_to(T_back, (2, 2, 4, 4)), xn, np.ones((2, 2), bool), focal=458.0)
    assert not ok.any()
    cfg = TriangulationConfig(min_views=3)
    P, ok, _ = triangulate(np.broadcast_to(Ts, (2, 2, 4, 4)), xn, np.ones((2, 2), bool), focal=458.0, cfg=cfg)
    assert not ok.any()


def _texture(h=480, w=752, seed=0):
    rng = np.random.default_rng(seed)
    img = np.full((h, w), 128, np.uint8)
    for _ in range(900):
        x, y = int(rng.integers(0, w - 20)), int(rng.integers(0, h - 20))
        s = int(rng.integers(6, 20))
        cv2.rectangle(img, (x, y), (x + s, y + s), int(rng.integers(0, 255)), -1)
    return cv2.GaussianBlur(img, (3, 3), 0.8)


@pytest.mark.parametrize("detector", ["gftt", "fast", "orb"])
def test_detection_is_bucketed_and_avoids_tracked_points(detector):
    img = _texture()
    cfg = FeatureConfig(detector=detector, max_features=120, grid_cols=6, grid_rows=4, min_distance=20)
    det = FeatureDetector(752, 480, cfg)
    pts = det.detect(img)
    assert 100 <= len(pts) <= 120
    cells = (pts[:, 1] * 4 // 480).astype(int) * 6 + (pts[:, 0] * 6 // 752).astype(int)
    counts = np.bincount(cells, minlength=24)
    assert counts.max() <= det.per_cell and (counts > 0).sum() >= 20  # spread over the grid
    existing = pts[:60]
    new = det.detect(img, existing)
    assert len(new) <= 60
    d = np.linalg.norm(new[:, None] - existing[None], axis=-1)
    assert d.min() >= cfg.min_distance - 1
    with pytest.raises(ValueError, match="expects 752x480"):
        det.detect(img[:100])


def test_klt_recovers_known_shift_and_rejects_unrelated_image():
    cam = EUROC_CAM.pinhole()  # no distortion: a pixel shift stays a shift
    trk = FeatureTracker(cam, EUROC_T_BS, FeatureConfig(max_features=150), TrackerConfig())
    img = _texture()
    trk.track(0, img)
    f0 = trk.replenish(0, img)
    shift = np.array([3.4, -2.2])
    img2 = cv2.warpAffine(img, np.array([[1, 0, shift[0]], [0, 1, shift[1]]]), (752, 480), flags=cv2.INTER_LINEAR)
    f1 = trk.track(1, img2)
    common, i0, i1 = np.intersect1d(f0.ids, f1.ids, return_indices=True)
    assert len(common) > 0.8 * len(f0.ids)
    err = np.abs(f1.uv[i1] - f0.uv[i0] - shift)
    assert np.median(err) < 0.05
    assert f1.flow_px == pytest.approx(np.linalg.norm(shift), abs=0.1)
    f2 = trk.track(2, _texture(seed=5))  # nothing corresponds: forward-backward and RANSAC reject most
    assert len(f2.ids) < 0.2 * len(f1.ids)


def test_imu_rotation_prediction_is_the_infinite_homography():
    trk = FeatureTracker(EUROC_CAM, EUROC_T_BS)
    R_b0_b1 = so3_exp(np.array([0.01, -0.03, 0.02]))
    rng = np.random.default_rng(1)
    dirs_c0 = np.concatenate([rng.uniform(-0.4, 0.4, (20, 2)), np.ones((20, 1))], 1)
    uv0, _ = EUROC_CAM.project(dirs_c0)
    R_b_c = EUROC_T_BS[:3, :3]
    dirs_c1 = dirs_c0 @ (R_b_c.T @ R_b0_b1.T @ R_b_c).T  # far points: only the rotation moves them
    uv1, _ = EUROC_CAM.project(dirs_c1)
    pred = trk.predict(uv0.astype(np.float32), R_b0_b1)
    assert np.abs(pred - uv1).max() < 1e-3


def test_parallax_is_zero_for_pure_rotation_and_selector_triggers():
    rng = np.random.default_rng(2)
    xn0 = rng.uniform(-0.5, 0.5, (30, 2))
    R = so3_exp(np.array([0.0, 0.1, 0.02]))
    f = np.concatenate([xn0, np.ones((30, 1))], 1) @ R.T
    xn1 = f[:, :2] / f[:, 2:]
    assert np.abs(rotation_compensated_parallax(xn0, xn1, R, 458.0)).max() < 1e-9
    assert rotation_compensated_parallax(xn0, xn1, np.eye(3), 458.0).mean() > 10
    sel = KeyframeSelector(KeyframeConfig(min_parallax_px=10, min_tracked_ratio=0.6, max_interval_s=0.5))
    assert sel.decide(0.05, 100, 100, 50.0, 100) == (False, "")  # too soon
    assert sel.decide(0.2, 100, 100, 12.0, 100) == (True, "parallax")
    assert sel.decide(0.2, 100, 50, 1.0, 100) == (True, "tracked_ratio")
    assert sel.decide(0.2, 100, 90, 1.0, 10) == (True, "few_landmarks")
    assert sel.decide(0.6, 100, 100, 0.0, 100) == (True, "time")
    assert sel.decide(0.2, 100, 100, 30.0, 100, still=True) == (False, "")


def test_dense_and_sparse_systems_have_their_own_parallax_trigger():
    c = KeyframeConfig(min_parallax_px=35.0, dense_min_parallax_px=18.0, max_interval_s=0.5)
    sparse, dense = KeyframeSelector(c.for_system(dense=False)), KeyframeSelector(c.for_system(dense=True))
    # 25 px since the last keyframe: a keyframe for the dense system only
    assert sparse.decide(0.2, 100, 100, 25.0, 100) == (False, "")
    assert dense.decide(0.2, 100, 100, 25.0, 100) == (True, "parallax")
    assert c.for_system(dense=True).max_interval_s == 0.5 and c.min_parallax_px == 35.0  # the rest kept, c unchanged


def test_chi_square_bounds_scale_with_the_stated_pixel_sigma():
    # quantiles: chi2_2(0.99) = 9.2103, chi2_1(0.99) = 6.6349
    t = TrackerConfig(pixel_sigma=1.0, chi2_prob=0.99)
    assert t.fb_threshold_px == pytest.approx(np.sqrt(2 * 9.2103), abs=1e-3)  # two KLT solves, 2 dof
    assert t.ransac_threshold_px == pytest.approx(np.sqrt(2 * 6.6349), abs=1e-3)  # two observations, 1 dof
    t2 = TrackerConfig(pixel_sigma=0.5, chi2_prob=0.99)
    assert t2.fb_threshold_px == pytest.approx(0.5 * t.fb_threshold_px)
    c = TriangulationConfig(pixel_sigma=0.8, chi2_prob=0.95)
    assert c.reproj_bound_px == pytest.approx(0.8 * np.sqrt(-2 * np.log(0.05)))
    assert TriangulationConfig(max_reproj_px=1.5).reproj_bound_px == 1.5  # an explicit bound wins


def test_triangulation_accepts_views_at_the_stated_noise_and_rejects_beyond():
    rng = np.random.default_rng(3)
    X = rng.uniform([-1, -1, 4], [1, 1, 6], (400, 3))
    Ts, xn, _ = _views(X, np.array([[0, 0, 0], [0.5, 0, 0], [1.0, 0.1, 0]], float))
    M, V = X.shape[0], 3
    T = np.broadcast_to(Ts, (M, V, 4, 4))
    noisy = xn + rng.normal(0, 1.0 / 458.0, xn.shape)  # 1 px per axis
    _, ok, _ = triangulate(T, noisy, np.ones((M, V), bool), 458.0, TriangulationConfig(pixel_sigma=1.0))
    assert ok.mean() > 0.97  # 3 views at 99 % each, less the fitted point's absorption
    _, ok, _ = triangulate(T, noisy, np.ones((M, V), bool), 458.0, TriangulationConfig(pixel_sigma=0.3))
    assert ok.mean() < 0.6  # sub-pixel bounds tuned to ideal images reject real noise


def _exposure_texture(h=480, w=752, seed=0):
    """Texture in grey levels 30-150, so that 1.5 x + 20 does not saturate."""
    return (30 + _texture(h, w, seed).astype(np.float32) * (120 / 255)).astype(np.uint8)


def test_klt_holds_tracks_through_an_exposure_change():
    cam = EUROC_CAM.pinhole()
    img = _exposure_texture()
    shift = np.array([2.6, 1.3])
    moved = cv2.warpAffine(img, np.array([[1, 0, shift[0]], [0, 1, shift[1]]]), (752, 480), flags=cv2.INTER_LINEAR)
    bright = np.clip(1.5 * moved.astype(np.float32) + 20, 0, 255).astype(np.uint8)
    kept = {}
    for normalize in (True, False):
        trk = FeatureTracker(cam, EUROC_T_BS, FeatureConfig(max_features=200), TrackerConfig(normalize=normalize))
        trk.track(0, img)
        f0 = trk.replenish(0, img)
        f1 = trk.track(1, bright)
        common, i0, i1 = np.intersect1d(f0.ids, f1.ids, return_indices=True)
        kept[normalize] = len(common) / len(f0.ids)
        if normalize:
            assert np.median(np.abs(f1.uv[i1] - f0.uv[i0] - shift)) < 0.1
    assert kept[True] >= 0.9
    assert kept[False] < kept[True]  # the raw KLT's brightness constancy does not hold


def test_weak_cells_get_their_minimum_from_the_low_threshold():
    strong = _texture(seed=1)
    faint = (120 + (_texture(seed=2).astype(np.float32) - 128) * 0.07).astype(np.uint8)  # +-9 grey levels
    img = faint.copy()
    img[:, :376] = strong[:, :376]  # left half high contrast, right half faint
    base = dict(max_features=240, grid_cols=6, grid_rows=4, fast_threshold=15, fast_threshold_low=5)
    cells = lambda p: (p[:, 1] * 4 // 480).astype(int) * 6 + (p[:, 0] * 6 // 752).astype(int)  # noqa: E731
    right = np.array([r * 6 + q for r in range(4) for q in (3, 4, 5)])
    p0 = FeatureDetector(752, 480, FeatureConfig(**base, min_per_cell=0)).detect(img)
    p2 = FeatureDetector(752, 480, FeatureConfig(**base, min_per_cell=3)).detect(img)
    n0, n2 = np.bincount(cells(p0), minlength=24), np.bincount(cells(p2), minlength=24)
    assert n0[right].max() == 0  # the faint half holds no corner at the normal threshold
    assert n2[right].min() >= 3  # every faint cell gets its minimum
    assert len(p2) <= 240


def _rolling_shutter_frame(base: np.ndarray, x_at_stamp: float, speed: float, line_delay: float) -> np.ndarray:
    """``base`` moving right at ``speed`` px/s, seen by a rolling shutter: row ``v`` is read ``(v - (H-1)/2) *
    line_delay`` after the stamp, when the content has moved ``x_at_stamp + speed * that`` px."""
    h, w = base.shape
    rows = np.arange(h, dtype=np.float32)[:, None]
    shift = x_at_stamp + speed * (rows - 0.5 * (h - 1)) * line_delay
    map_x = (np.arange(w, dtype=np.float32)[None] - shift).astype(np.float32)
    map_y = np.repeat(rows, w, 1).astype(np.float32)
    return cv2.remap(base, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


def test_rolling_shutter_correction_puts_tracks_at_the_stamp():
    """A texture moving at 400 px/s under a rolling shutter (1e-4 s a row: up to 9.6 px of skew at the top and
    bottom of a 480-row image): corrected, every track sits where the content was at the stamp (known answer);
    uncorrected, it is off by the row's delay times the speed."""
    speed, line_delay, dt = 400.0, 1e-4, 0.05
    cam = EUROC_CAM.pinhole()
    base = _texture()
    frames = [_rolling_shutter_frame(base, speed * k * dt, speed, line_delay) for k in range(4)]
    errors = {}
    for delay in (0.0, line_delay):
        trk = FeatureTracker(cam, EUROC_T_BS, FeatureConfig(max_features=150), TrackerConfig(line_delay_s=delay))
        assert trk.line_delay_s == delay
        trk.track(0, frames[0])
        f0 = trk.replenish(0, frames[0])
        for k in range(1, 4):
            f = trk.track(int(k * dt * 1e9), frames[k])
        common, i0, i1 = np.intersect1d(f0.ids, f.ids, return_indices=True)
        assert len(common) > 0.5 * len(f0.ids)
        # the stamp positions: where the content of the first frame's stamp position went after 3 frames ...
        skew0 = speed * (f0.uv[i0, 1] - 0.5 * (cam.height - 1)) * line_delay
        expected = f0.uv[i0, 0] - skew0 + speed * 3 * dt
        got = f.uv_u[i1, 0]  # ... and where the estimator is told the track is (pinhole: uv_u = corrected pixels)
        errors[delay] = np.abs(got - expected)
    skew = speed * (f.uv[i1, 1] - 0.5 * (cam.height - 1)) * line_delay
    assert np.median(np.abs(f.uv[i1, 0] - f.uv_u[i1, 0] - skew)) < 0.1  # the KLT keeps the image's pixels
    assert np.median(errors[line_delay]) < 0.1
    assert np.median(np.abs(errors[0.0] - np.abs(skew))) < 0.1  # uncorrected: off by the skew
    with pytest.raises(ValueError, match="line_delay_s"):
        TrackerConfig(line_delay_s=-1e-5)


def test_a_camera_reads_its_line_delay_from_sensor_yaml(tmp_path):
    from runtime.io.asl_format import EurocFormatError
    from runtime.io.sensor_yaml import read_camera_yaml
    from sim.euroc import _cam_yaml

    cam = EUROC_CAM.pinhole()
    (tmp_path / "gs.yaml").write_text(_cam_yaml(cam, EUROC_T_BS, 20))
    assert "line_delay_s" not in (tmp_path / "gs.yaml").read_text()
    assert read_camera_yaml(tmp_path / "gs.yaml")[0].line_delay_s == 0.0
    rs = Camera(*cam.intrinsics, cam.width, cam.height, line_delay_s=3.125e-5)
    (tmp_path / "rs.yaml").write_text(_cam_yaml(rs, EUROC_T_BS, 20))
    read = read_camera_yaml(tmp_path / "rs.yaml")[0]
    assert read == rs and FeatureTracker(read, EUROC_T_BS).line_delay_s == 3.125e-5
    assert FeatureTracker(read, EUROC_T_BS, cfg=TrackerConfig(line_delay_s=0.0)).line_delay_s == 0.0  # override
    (tmp_path / "bad.yaml").write_text((tmp_path / "rs.yaml").read_text().replace("3.125e-05", "-1e-5"))
    with pytest.raises(EurocFormatError, match="line_delay_s"):
        read_camera_yaml(tmp_path / "bad.yaml")
