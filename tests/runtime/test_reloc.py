"""Map re-use: descriptor and guided matching, PnP, the backend's drift correction and re-activation."""

import cv2
import numpy as np

from runtime.backend.state import Keyframe
from runtime.backend.window import BackendConfig, SlidingWindowBackend
from runtime.geometry import inv_T, make_T, pose_error, so3_exp
from runtime.reloc.descriptors import MapDescriptors, candidates_in_view, guided_match, hamming, match, pnp
from tests.runtime.synth import EUROC_CAM, EUROC_T_BS, ImuNoise


def test_hamming_known_answer_and_ratio_matching():
    a = np.zeros((2, 32), np.uint8)
    b = np.zeros((3, 32), np.uint8)
    b[1, 0] = 0b1011  # 3 bits from a[*]
    b[2, :] = 255  # 256 bits
    a[1, 5] = 1
    D = hamming(a, b)
    assert D.tolist() == [[0, 3, 256], [1, 4, 255]]
    rng = np.random.default_rng(0)
    t = rng.integers(0, 256, (50, 32), dtype=np.uint8)
    q = t[[3, 7, 11]].copy()
    q[:, 0] ^= 1  # one bit flipped
    qi, ti = match(q, t, max_dist=40, ratio=0.8)
    assert qi.tolist() == [0, 1, 2] and ti.tolist() == [3, 7, 11]
    qi, _ = match(rng.integers(0, 256, (5, 32), dtype=np.uint8), t, max_dist=40, ratio=0.8)
    assert qi.size == 0  # random descriptors (~128 bits apart) do not match


def test_guided_match_respects_radius_and_uniqueness():
    rng = np.random.default_rng(1)
    d = rng.integers(0, 256, (4, 32), dtype=np.uint8)
    uv_map = np.array([[100.0, 100], [200, 200], [300, 300], [102, 101]])
    uv_f = np.array([[101.0, 99], [205, 203], [500, 500]])
    d_f = np.stack([d[0], d[1], d[2]])
    d_map = np.stack([d[0], d[1], d[2], d[0]])  # map point 3 duplicates point 0 near the same feature
    mi, fi = guided_match(uv_map, d_map, uv_f, d_f, radius=10, max_dist=40, ratio=0.9)
    pairs = sorted(zip(mi.tolist(), fi.tolist(), strict=False))
    assert (1, 1) in pairs and all(f != 2 for _, f in pairs)  # feature 2 is 200 px from map point 2
    assert sum(f == 0 for _, f in pairs) == 1  # feature 0 is given to one map point only


def test_describe_marks_border_points_and_is_repeatable():
    rng = np.random.default_rng(2)
    img = cv2.GaussianBlur(rng.integers(0, 255, (120, 160), dtype=np.uint8), (3, 3), 1.0)
    db = MapDescriptors()
    uv = np.array([[80.0, 60.0], [2.0, 2.0], [100.0, 40.0]])
    d, ok = db.describe(img, uv)
    assert ok.tolist() == [True, False, True]
    d2, _ = db.describe(img, uv)
    assert np.array_equal(d[ok], d2[ok])
    db.add(np.array([10, 11, 12]), d, ok)
    got, has = db.get(np.array([12, 11, 99]))
    assert has.tolist() == [True, False, False] and np.array_equal(got[0], d[2])


def test_pnp_recovers_a_known_pose_with_outliers():
    rng = np.random.default_rng(3)
    T_w_c = make_T(so3_exp(np.array([0.1, -0.4, 0.2])), [0.5, -1.0, 0.3])
    Xc = np.concatenate([rng.uniform(-2, 2, (80, 2)), rng.uniform(2, 6, (80, 1))], 1)
    Xw = Xc @ T_w_c[:3, :3].T + T_w_c[:3, 3]
    xn = Xc[:, :2] / Xc[:, 2:] + rng.normal(0, 0.5 / 458, (80, 2))
    xn[:15] += rng.uniform(-0.2, 0.2, (15, 2))  # outliers
    T, inl = pnp(Xw, xn, 2.5 / 458)
    dp, dr = pose_error(T, T_w_c)
    assert dp < 0.01 and np.degrees(dr) < 0.2
    assert inl[15:].mean() > 0.95 and inl[:15].mean() < 0.2
    assert candidates_in_view(T_w_c, Xw, EUROC_CAM.K, 752, 480, 0.5, 12.0).all()
    assert not candidates_in_view(T_w_c, Xw[:3] - 10 * T_w_c[:3, 2], EUROC_CAM.K, 752, 480, 0.5, 12.0).any()


def test_correction_and_reactivated_map_points_pull_the_window_onto_the_map():
    import gtsam

    from runtime.backend.imu import preintegration_params

    params = preintegration_params(ImuNoise())
    be = SlidingWindowBackend(EUROC_CAM.intrinsics, EUROC_T_BS, params, BackendConfig(lm_max_iterations=20))
    T0 = make_T(so3_exp(np.array([0.0, 0.0, 0.3])), [1.0, 2.0, 0.5])
    be.initialize(Keyframe(0, 0, 0, T0, np.zeros(3), np.zeros(6)))
    pim = gtsam.PreintegratedCombinedMeasurements(params, gtsam.imuBias.ConstantBias())
    for _ in range(20):  # 0.1 s at rest
        pim.integrateMeasurement(T0[:3, :3].T @ np.array([0, 0, 9.81]), np.zeros(3), 0.005)
    drift = make_T(so3_exp(np.array([0.0, 0.0, 0.02])), [0.3, -0.2, 0.0])  # the estimate is off the map
    be.add_keyframe(Keyframe(1, int(0.1e9), 1, drift @ T0, np.zeros(3), np.zeros(6)), pim)
    # map points seen by keyframe 1 at its true pose T0
    rng = np.random.default_rng(4)
    T_c_w = inv_T(T0 @ EUROC_T_BS)
    Xc = np.concatenate([rng.uniform(-1.5, 1.5, (40, 2)), rng.uniform(2, 5, (40, 1))], 1)
    Xw = (Xc - T_c_w[:3, 3]) @ T_c_w[:3, :3]
    K = EUROC_CAM.pinhole().K
    uv = Xc[:, :2] / Xc[:, 2:] * [K[0, 0], K[1, 1]] + K[:2, 2]
    C = inv_T(drift)
    be.apply_correction(lambda ts: C, t_from=int(0.05e9))  # keyframe 1 only
    assert pose_error(be.map.keyframes[1].T_w_b, T0)[0] < 1e-9
    assert pose_error(be.map.keyframes[0].T_w_b, T0)[0] < 1e-9  # before t_from: untouched
    be.reactivate_landmarks(np.arange(100, 140), Xw, 1, uv, sigma=0.01)
    assert all(be.map.landmarks[j].map_prior is not None for j in range(100, 140))
    # perturb keyframe 1 again: the map points (one view each, held by their priors) bring it back
    be.map.keyframes[1].T_w_b = make_T(so3_exp(np.array([0.0, 0.01, 0.0])), [0.05, 0.0, 0.02]) @ T0
    stats = be.optimize()
    assert stats["ok"] and pose_error(be.map.keyframes[1].T_w_b, T0)[0] < 0.005


def test_rename_keeps_track_ids_unique():
    from runtime.frontend.tracking import FeatureTracker

    tr = FeatureTracker(EUROC_CAM, EUROC_T_BS)
    tr.ids, tr.uv = np.array([1, 2, 3], np.int64), np.zeros((3, 2), np.float32)
    ok = tr.rename(np.array([1, 2]), np.array([3, 9]))  # 3 is another track's id: that pair is skipped
    assert ok.tolist() == [False, True] and tr.ids.tolist() == [1, 9, 3]
    ok = tr.rename(np.array([1, 9]), np.array([5, 5]))  # one id for two tracks: only the first
    assert ok.tolist() == [True, False] and tr.ids.tolist() == [5, 9, 3]
    ok = tr.rename(np.array([3, 5]), np.array([10, 3]))  # an id freed by the same call can be taken
    assert ok.all() and tr.ids.tolist() == [3, 9, 10]


def test_guided_match_leaves_a_map_point_that_is_still_tracked_to_its_own_track():
    """A map point whose own track is still alive (its landmark left the window while the track went on) must not
    be handed to a second track: two tracks with one id broke the keyframe decision (an IndexError)."""
    from types import SimpleNamespace

    from runtime.frontend.tracking import FeatureTracker
    from runtime.reloc.relocalizer import Relocalizer, RelocConfig

    rng = np.random.default_rng(0)
    image = cv2.GaussianBlur(rng.integers(0, 256, (EUROC_CAM.height, EUROC_CAM.width)).astype(np.uint8), (5, 5), 1.0)
    tr = FeatureTracker(EUROC_CAM, EUROC_T_BS)
    tr.ids = np.array([3, 7, 4], np.int64)  # track 7 is map point 7, still tracked
    tr.uv = np.array([[200.0, 150.0], [500.0, 300.0], [350.0, 260.0]], np.float32)
    feats = tr.current(0)
    K = EUROC_CAM.pinhole().K
    depth = np.array([[3.0], [4.0]])
    # map point 7 projects onto track 3, map point 8 onto track 4 (the undistorted pixels the match uses)
    xn = (feats.uv_u[[0, 2]] - K[:2, 2]) / [K[0, 0], K[1, 1]]
    Xm = np.concatenate([xn, np.ones((2, 1))], 1) * depth  # camera frame = world frame below
    reactivated = []
    backend = SimpleNamespace(
        map=SimpleNamespace(
            map_point_arrays=lambda: (np.array([7, 8]), Xm),
            landmark_arrays=lambda: (np.zeros(0, np.int64), np.zeros((0, 3))),  # no window landmark to re-find
            landmarks={},
            is_landmark=lambda j: False,
        ),
        reactivate_landmarks=lambda ids, X, k, uv, s: reactivated.append(np.asarray(ids).tolist()),
        add_observations=lambda k, ids, uv: None,
    )
    reloc = Relocalizer(RelocConfig(), EUROC_CAM, EUROC_T_BS, backend, tr)
    desc, ok = reloc.descriptors.describe(image, feats.uv[[0, 2]])
    assert ok.all()
    reloc.descriptors.add(np.array([7, 8]), desc, ok)
    kf = SimpleNamespace(kf_id=5, ts=0, T_w_b=inv_T(np.asarray(EUROC_T_BS, np.float64)))
    renamed = reloc.guided_match(kf, image)
    assert renamed.tolist() == [4] and reactivated == [[8]]  # map point 8 is re-found on track 4
    assert tr.ids.tolist() == [3, 7, 8]  # track 3 keeps its id: 7 stays with its own track


def test_guided_window_re_finds_a_lost_window_landmark_within_its_radius():
    """With ``guided_window_radius_px`` the guided search also looks for the window's own landmarks that no track
    follows: a free track within that radius of such a landmark's projection, with its descriptor, takes its id and
    the keyframe observes it (no map prior: it is the window's own point). A landmark that a track still follows, a
    re-activated map point (held by its prior), and one projecting farther than the radius are not re-found; with
    the radius 0 nothing is."""
    from types import SimpleNamespace

    from runtime.frontend.tracking import FeatureTracker
    from runtime.reloc.relocalizer import Relocalizer, RelocConfig

    rng = np.random.default_rng(1)
    image = cv2.GaussianBlur(rng.integers(0, 256, (EUROC_CAM.height, EUROC_CAM.width)).astype(np.uint8), (5, 5), 1.0)
    K = EUROC_CAM.pinhole().K
    for radius in (4.0, 0.0):
        tr = FeatureTracker(EUROC_CAM, EUROC_T_BS)
        tr.ids = np.array([3, 4, 5, 6, 21], np.int64)  # 3-6 free tracks; 21 follows landmark 21
        tr.uv = np.array([[200.0, 150.0], [500.0, 300.0], [350.0, 260.0], [600.0, 120.0], [100.0, 400.0]], np.float32)
        feats = tr.current(0)
        xn = (feats.uv_u - K[:2, 2]) / [K[0, 0], K[1, 1]]
        X = np.concatenate([xn, np.ones((5, 1))], 1) * np.array([[3.0], [4.0], [5.0], [6.0], [2.0]])  # camera = world
        X[3] += [6.0 * 6.0 / K[0, 0], 0.0, 0.0]  # landmark 23 projects 6 px from track 6: outside a 4 px radius
        # window landmarks: 20 (lost, on track 4), 21 (tracked, on its own track), 22 (re-activated, on track 5),
        # 23 (lost, 6 px off track 6), 24 (lost, on track 3, projecting onto it)
        lm_ids = np.array([20, 21, 22, 23, 24])
        lm_X = X[[1, 4, 2, 3, 0]]
        lms = {int(j): SimpleNamespace(map_prior=object() if j == 22 else None) for j in lm_ids}
        observed = []
        backend = SimpleNamespace(
            map=SimpleNamespace(
                map_point_arrays=lambda: (np.zeros(0, np.int64), np.zeros((0, 3))),
                landmark_arrays=lambda lm_ids=lm_ids, lm_X=lm_X: (lm_ids, lm_X),
                landmarks=lms,
                is_landmark=lambda j: int(j) == 21,
            ),
            add_observations=lambda k, ids, uv, out=observed: out.append((k, np.asarray(ids).tolist(), np.asarray(uv))),
        )
        reloc = Relocalizer(RelocConfig(guided_window_radius_px=radius), EUROC_CAM, EUROC_T_BS, backend, tr)
        desc, ok = reloc.descriptors.describe(image, feats.uv[[1, 4, 2, 3, 0]])
        assert ok.all()
        reloc.descriptors.add(lm_ids, desc, ok)
        kf = SimpleNamespace(kf_id=5, ts=0, T_w_b=inv_T(np.asarray(EUROC_T_BS, np.float64)))
        renamed = reloc.guided_match(kf, image)
        if radius == 0.0:
            assert renamed.size == 0 and observed == [] and tr.ids.tolist() == [3, 4, 5, 6, 21]
            continue
        assert sorted(renamed.tolist()) == [3, 4] and tr.ids.tolist() == [24, 20, 5, 6, 21]
        ((k, ids, uv),) = observed
        assert k == 5 and sorted(ids) == [20, 24]
        assert np.allclose(uv[np.argsort(ids)], feats.uv_u[[1, 0]])
