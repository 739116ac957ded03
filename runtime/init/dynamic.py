"""Dynamic (in-motion) visual-inertial initialisation: VINS-Mono's visual-inertial alignment.

For a sequence with no period at rest (a MAV already flying, a hand-held camera picked up while moving):

1. **Visual structure from motion** over the frames of the last ``window_s`` (subsampled to ``n_frames``; when
   this or the alignment below fails, :class:`runtime.init.runner.InitRunner` tries the longest window up to
   ``max_window_s`` once more): the essential matrix between the first and the last frame (RANSAC), their
   common tracks triangulated, every other frame's pose by PnP on those points, then all tracks triangulated and
   refined by a small bundle adjustment (GTSAM, Huber). Poses ``T_c0_ck`` are known up to one scale.
2. **Gyroscope bias**: the visual relative rotations against the gyro's (Gauss-Newton on ``b_g``). The bias is
   constant over seconds: when earlier attempts agreed on one (``earlier_bias``, kept by the runner), an attempt
   whose bias lies more than ``bias_agree`` from it has a wrong structure from motion and is refused
   (:class:`BiasDisagrees`; on ``handheld`` seed 42 a two-view solution 11.7 deg off in rotation, reports/). Wrong
   structures from motion of one scene can agree with each other, though: a bias larger than ``max_gyro_bias``,
   which no MEMS gyroscope has, is refused and not remembered (on ``handheld`` seed 108 four of them, at 0.31-0.34
   rad/s against the true 0.09, had refused the right attempt).
3. **Linear alignment** (Qin et al., VINS-Mono, IEEE T-RO 2018, Sec. V-B): with the IMU preintegrated between
   the frames (``alpha``, ``beta`` in the earlier body frame), the body positions ``P_k = s pc_k - R_c0_bk t_bc``
   and velocities ``V_k`` in the frame ``c0`` obey

       s (pc_{k+1} - pc_k) - V_k dt - g dt^2 / 2 = R_c0_bk (alpha_k + J_alpha b_a) + (R_c0_bk+1 - R_c0_bk) t_bc
       V_{k+1} - V_k - g dt = R_c0_bk (beta_k + J_beta b_a)

   linear in ``(V_0..V_n, g, b_a, s)``. Then gravity is refined on the sphere ``|g| = 9.81`` (two tangent
   parameters, four iterations). VINS-Mono takes the accelerometer bias ``b_a`` as 0. Here it is solved with a
   zero prior of weight ``accel_bias_weight``, and the window starts from it: a real IMU's bias of 0.1-0.2 m/s^2
   is larger than a slow camera's accelerations. On the realistic ``tabletop`` preset (5 cm/s), with a 0 bias the
   scale came out negative for seconds, or several times too large (reports/ablations.md).
4. **Checks**: positive scale, a plausible median depth of the scaled structure (``min_depth_m``),
   ``| |g| - 9.81 |`` of the unconstrained solve below ``gravity_tol``, the
   alignment's position residual below ``max_residual_m``, the SfM's reprojection RMS below ``max_reproj_px``.

When the camera only turns (a hovering MAV: the rotation-only fit to the oldest frame leaves less than
``hover_max_px``), structure from motion has no baseline; :func:`initialize_hovering` then takes the rotations
from the images, the gyro bias from them, gravity from the mean specific force and the velocity as 0 (with a
looser prior).

The world frame is gravity-aligned with zero yaw at ``c0`` (:func:`runtime.init.static.gravity_aligned_rotation`).
The result gives every frame of the window its state; the system hands them to the sliding window, which
refines them with the IMU factors (accelerometer bias included).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from runtime.backend.imu import propagate
from runtime.frontend.triangulation import TriangulationConfig, triangulate
from runtime.geometry import GRAVITY, inv_T, ns_to_s, so3_log
from runtime.init.static import gravity_aligned_rotation

log = logging.getLogger(__name__)


@dataclass
class DynamicInitConfig:
    """Settings of the in-motion initialisation (see the module doc)."""

    enabled: bool = True  # initialise in motion when the sequence is not at rest
    window_s: float = 1.0  # s of frames used (the window grows from the first frame up to this)
    max_window_s: float = 3.0  # s, longest window tried when ``window_s`` fails
    min_window_s: float = 0.5  # s, shortest window tried
    n_frames: int = 10  # frames of the window used (evenly spaced in time), at most backend.window_size
    min_tracks: int = 30  # tracks common to the first and last frame
    # the triangulation angle decides whether the pair translated; a gate on the parallax left after a rotation-only
    # image fit was dropped: in front of a wall that fit absorbs a translation (handheld s289, reports/ablations.md)
    min_parallax_deg: float = 1.5  # median triangulation angle of the pair
    ransac_px: float = 1.5  # essential-matrix and PnP inlier threshold
    max_reproj_px: float = 2.0  # bundle-adjusted reprojection RMS bound
    gravity_tol: float = 1.0  # m/s^2, | |g| - 9.81 | of the unconstrained solve
    max_residual_m: float = 0.05  # RMS position residual of the alignment
    accel_bias_weight: float = 0.05  # zero prior on the alignment's accelerometer bias, in velocity-row units
    # (a bias b costs as much as a velocity residual of weight * b [m/s]); 0: the bias is taken as 0 (VINS-Mono)
    min_depth_m: float = 0.2  # median depth of the scaled structure (closer: corrupt tracks or a wrong scale)
    ba_iterations: int = 15
    # (3.0 px refused MH_05 IMU seed 2 at 3.03 px during the take-off, and structure from motion then waited until
    # 2.9 s; reports/ablations.md)
    hover_max_px: float = 4.0  # rotation-only fit residual below this over the window: turning in place
    try_every_s: float = 0.1  # s between attempts
    backfill_s: float = 10.0  # frames before the start window get IMU poses this far back (every kept frame)
    refine_within_s: float = 10.0  # after a start turning in place, re-initialise in motion within this time
    restart_recent_after_s: float = 3.0  # s after that start: the restart may also take a recent window (1e9: never)
    # priors on the first state (looser than at rest: estimated in motion)
    prior_vel_sigma: float = 0.1  # m/s
    prior_hover_vel_sigma: float = 0.2  # m/s, velocity taken as 0 while hovering
    prior_roll_pitch_sigma: float = 0.03  # rad
    prior_gyro_bias_sigma: float = 0.01  # rad/s
    # a start whose gyroscope bias is farther than this from the earlier attempts' (when at least two of them agree
    # to within it) is refused: its structure from motion is wrong (reports/ablations.md, handheld seed 42)
    bias_agree: float = 0.03  # rad/s; 0: off
    # a start whose gyroscope bias is larger than this is refused and not remembered: no MEMS gyroscope's bias is
    # that large, its structure from motion is wrong (reports/ablations.md, handheld seed 108); raise it for an
    # uncalibrated gyroscope with a larger zero-rate offset
    max_gyro_bias: float = 0.25  # rad/s (14 deg/s)


@dataclass
class DynamicResult:
    """States of the window's frames in the gravity-aligned world frame."""

    ts: np.ndarray  # (F,) ns
    T_w_b: np.ndarray  # (F, 4, 4)
    v_w: np.ndarray  # (F, 3)
    bg: np.ndarray  # (3,) gyroscope bias
    scale: float
    info: dict  # figures of the solve (for the log and metrics.json)
    ba: np.ndarray = field(default_factory=lambda: np.zeros(3))  # (3,) accelerometer bias (body frame)


class InitFailed(Exception):
    """The window does not allow an initialisation; the message says why. ``gyro_bias``: the gyroscope bias (3,)
    that the window's structure from motion gave before the start failed on a later step (None when it did not
    get that far, or when the start was refused for that bias)."""

    gyro_bias: np.ndarray | None = None


class BiasDisagrees(InitFailed):
    """The window's structure from motion gives a gyroscope bias unlike the one earlier attempts agreed on, or
    larger than ``max_gyro_bias``: a wrong structure from motion, whose bias is not one to remember."""


# ---------------------------------------------------------------------------------------------- SfM
def _common(a, b) -> tuple[np.ndarray, np.ndarray]:
    _, i, j = np.intersect1d(a.ids, b.ids, assume_unique=True, return_indices=True)
    return i, j


def _pnp(X: np.ndarray, xn: np.ndarray, thr: float) -> np.ndarray:
    """``T_c_w`` from 3-D points and normalised coordinates (RANSAC EPnP, then iterative refinement)."""
    import cv2

    if X.shape[0] < 6:
        raise InitFailed(f"PnP with {X.shape[0]} points")
    ok, rvec, tvec, inl = cv2.solvePnPRansac(
        X, xn, np.eye(3), None, reprojectionError=thr, iterationsCount=100, flags=cv2.SOLVEPNP_EPNP
    )
    if not ok or inl is None or inl.shape[0] < 6:
        raise InitFailed("PnP failed")
    idx = inl[:, 0]
    ok, rvec, tvec = cv2.solvePnP(X[idx], xn[idx], np.eye(3), None, rvec, tvec, True, cv2.SOLVEPNP_ITERATIVE)
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec[:, 0]
    return T


def _triangulate_all(frames, T_w_c: np.ndarray, focal: float, max_err_px: float):
    """All tracks seen in >= 2 frames: ``(ids, X_w, obs)`` with ``obs[i] = [(frame, xn)]``."""
    obs: dict[int, list] = {}
    for f, fr in enumerate(frames):
        for j, x in zip(fr.ids, fr.xn, strict=True):
            obs.setdefault(int(j), []).append((f, x))
    ids = [j for j, o in obs.items() if len(o) >= 2]
    M, V = len(ids), len(frames)
    T = np.tile(np.eye(4), (M, V, 1, 1))
    xn = np.zeros((M, V, 2))
    mask = np.zeros((M, V), bool)
    for m, j in enumerate(ids):
        for f, x in obs[j]:
            T[m, f], xn[m, f], mask[m, f] = T_w_c[f], x, True
    cfg = TriangulationConfig(min_parallax_deg=0.5, min_depth=1e-3, max_depth=1e3, max_reproj_px=max_err_px)
    X, ok, _ = triangulate(T, xn, mask, focal=focal, cfg=cfg)
    keep = np.nonzero(ok)[0]
    return np.array(ids, np.int64)[keep], X[keep], [obs[ids[m]] for m in keep]


def _bundle_adjust(T_w_c: np.ndarray, X: np.ndarray, obs: list, focal: float, cfg: DynamicInitConfig, hold=(0, -1)):
    """Refine camera poses (frame ``hold[0]`` held, ``hold[1]`` loosely: the scale gauge) and points on
    normalised coordinates; returns the poses, the points and the reprojection RMS [px]."""
    import gtsam

    Xk, Lk = gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.L
    cal = gtsam.Cal3_S2(1.0, 1.0, 0.0, 0.0, 0.0)
    sigma = 1.0 / focal
    noise = gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Huber.Create(1.5), gtsam.noiseModel.Isotropic.Sigma(2, sigma)
    )
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    F = T_w_c.shape[0]
    for f in range(F):
        values.insert(Xk(f), gtsam.Pose3(T_w_c[f]))
    h0, h1 = hold[0] % F, hold[1] % F
    graph.add(gtsam.PriorFactorPose3(Xk(h0), gtsam.Pose3(T_w_c[h0]), gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
    loose = gtsam.noiseModel.Diagonal.Sigmas(np.array([1e2] * 3 + [1e-1] * 3))
    graph.add(gtsam.PriorFactorPose3(Xk(h1), gtsam.Pose3(T_w_c[h1]), loose))
    for m, o in enumerate(obs):
        values.insert(Lk(m), X[m])
        for f, x in o:
            graph.add(gtsam.GenericProjectionFactorCal3_S2(np.asarray(x, float), noise, Xk(f), Lk(m), cal))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(cfg.ba_iterations)
    res = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    T = np.array([res.atPose3(Xk(f)).matrix() for f in range(F)])
    P = np.array([res.atPoint3(Lk(m)) for m in range(len(obs))]).reshape(-1, 3)
    err = [np.linalg.norm(_project(T[f], P[m]) - x) * focal for m, o in enumerate(obs) for f, x in o]
    return T, P, float(np.sqrt(np.mean(np.square(err)))) if err else np.inf


def _project(T_w_c: np.ndarray, X: np.ndarray) -> np.ndarray:
    p = T_w_c[:3, :3].T @ (X - T_w_c[:3, 3])
    return p[:2] / p[2]


def _two_view(a, b, focal: float, cfg: DynamicInitConfig):
    """Relative pose of ``b`` to ``a`` (unit baseline) and their triangulated inliers: ``(T_a_b, ids, X_a, par)``."""
    import cv2

    i0, i1 = _common(a, b)
    if i0.size < cfg.min_tracks:
        raise InitFailed(f"{i0.size} tracks common to the pair (< {cfg.min_tracks})")
    x0, x1 = a.xn[i0], b.xn[i1]
    try:  # a pure rotation seen exactly makes the five-point solver's polynomial degenerate (OpenCV raises)
        E, inl = cv2.findEssentialMat(x0, x1, np.eye(3), method=cv2.RANSAC, prob=0.999, threshold=cfg.ransac_px / focal)
        if E is None or E.shape != (3, 3):
            raise InitFailed("no essential matrix")
        n_in, R, t, inl = cv2.recoverPose(E, x0, x1, np.eye(3), mask=inl)
    except cv2.error as e:
        raise InitFailed("no essential matrix (degenerate: no translation?)") from e
    if n_in < cfg.min_tracks:
        raise InitFailed(f"{n_in} essential-matrix inliers (< {cfg.min_tracks})")
    T_b_a = np.eye(4)
    T_b_a[:3, :3], T_b_a[:3, 3] = R, t[:, 0] / np.linalg.norm(t)
    pair = np.stack([np.eye(4), inv_T(T_b_a)])
    sel = inl[:, 0] > 0
    M = int(sel.sum())
    X, ok, diag = triangulate(
        np.broadcast_to(pair, (M, 2, 4, 4)),
        np.stack([x0[sel], x1[sel]], 1),
        np.ones((M, 2), bool),
        focal=focal,
        cfg=TriangulationConfig(min_parallax_deg=0.0, min_depth=1e-3, max_depth=1e3, max_reproj_px=2 * cfg.ransac_px),
    )
    par = float(np.median(diag["parallax_deg"][ok])) if ok.any() else 0.0
    if par < cfg.min_parallax_deg:
        raise InitFailed(f"median parallax {par:.2f} deg (< {cfg.min_parallax_deg}): not enough translation")
    return pair[1], a.ids[i0][sel][ok], X[ok], par


def structure_from_motion(frames: list, focal: float, cfg: DynamicInitConfig) -> tuple[np.ndarray, float, dict]:
    """Camera poses ``T_c0_ck`` (F, 4, 4), up to scale, and the median depth of the points in the newest frame
    (same scale) of the tracked ``frames``
    (:class:`runtime.frontend.tracking.FrameFeatures`, oldest first). Raises :class:`InitFailed`.

    The pair is the newest frame and the oldest frame ``l`` that shares ``min_tracks`` tracks with it (as
    VINS-Mono picks it); the frames after ``l`` are placed by PnP on the pair's points, the frames before it one by
    one on the points triangulated so far; then all tracks are triangulated and bundle adjusted.
    """
    F = len(frames)
    n_common = [_common(f, frames[-1])[0].size for f in frames[:-1]]
    cand = [k for k, n in enumerate(n_common) if n >= cfg.min_tracks]
    if not cand:
        raise InitFailed(f"at most {max(n_common, default=0)} tracks common with the newest frame (< {cfg.min_tracks})")
    l = cand[0]
    T_l_n, ids, X, par = _two_view(frames[l], frames[-1], focal, cfg)
    thr = cfg.ransac_px / focal
    T_w_c = np.zeros((F, 4, 4))
    T_w_c[l], T_w_c[-1] = np.eye(4), T_l_n
    for f in list(range(l + 1, F - 1)) + list(range(l - 1, -1, -1)):
        _, a, b = np.intersect1d(ids, frames[f].ids, assume_unique=True, return_indices=True)
        T_w_c[f] = inv_T(_pnp(X[a], frames[f].xn[b], thr))
        if f < l:  # extend the points to the frames before the pair
            done = [k for k in range(F) if k >= f]
            sub_ids, X_sub, _ = _triangulate_all([frames[k] for k in done], T_w_c[done], focal, 3 * cfg.ransac_px)
            ids, X = sub_ids, X_sub
    lm_ids, P, obs = _triangulate_all(frames, T_w_c, focal, 3 * cfg.ransac_px)
    if lm_ids.size < cfg.min_tracks:
        raise InitFailed(f"{lm_ids.size} points triangulated (< {cfg.min_tracks})")
    T_w_c, P, rms = _bundle_adjust(T_w_c, P, obs, focal, cfg, hold=(l, -1))
    if rms > cfg.max_reproj_px:
        raise InitFailed(f"structure-from-motion reprojection RMS {rms:.2f} px (> {cfg.max_reproj_px})")
    T_n = T_w_c[-1]
    depth = float(np.median((P - T_n[:3, 3]) @ T_n[:3, :3][:, 2]))  # along the newest camera's axis
    T_w_c = np.einsum("ij,fjk->fik", inv_T(T_w_c[0]), T_w_c)  # c0 = the oldest frame
    return (
        T_w_c,
        depth,
        {
            "sfm_points": int(lm_ids.size),
            "sfm_reproj_px": round(rms, 3),
            "parallax_deg": round(par, 2),
            "pair": [l, F - 1],
        },
    )


# ---------------------------------------------------------------------------------------------- alignment
def _preintegrate(seg, bg: np.ndarray, ba: np.ndarray | None = None):
    """``(dR, alpha, beta, dt)`` of one ZOH segment ``(gyro, accel, dt)`` with gyro bias ``bg`` (accel bias ``ba``,
    default 0)."""
    gyro, acc, dt = seg
    R, a, b = propagate(np.eye(3), np.zeros(3), np.zeros(3), gyro, acc, dt, bg=bg, ba=ba, g_w=np.zeros(3))
    return R, a, b, float(dt.sum())


def estimate_gyro_bias(R_w_b: np.ndarray, segs: list, iterations: int = 3) -> np.ndarray:
    """Gyroscope bias (3,) that best maps the gyro's relative rotations onto the visual ones ``R_w_b`` (F, 3, 3);
    ``segs[k]``: the IMU segment between frames k and k+1 (Gauss-Newton, numerical Jacobian)."""
    bg = np.zeros(3)
    rel = [R_w_b[k].T @ R_w_b[k + 1] for k in range(len(segs))]

    def residual(b):
        return np.concatenate([so3_log(_preintegrate(s, b)[0].T @ r) for s, r in zip(segs, rel, strict=True)])

    for _ in range(iterations):
        r0 = residual(bg)
        eps = 1e-5
        J = np.stack([(residual(bg + eps * e) - r0) / eps for e in np.eye(3)], 1)
        bg = bg - np.linalg.lstsq(J, r0, rcond=None)[0]
    return bg


def _tangent_basis(g: np.ndarray) -> np.ndarray:
    a = g / np.linalg.norm(g)
    tmp = np.array([0.0, 0.0, 1.0]) if abs(a[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    b1 = np.cross(a, tmp)
    b1 /= np.linalg.norm(b1)
    return np.stack([b1, np.cross(a, b1)], 1)  # (3, 2)


def linear_alignment(
    pc: np.ndarray,
    R_c0_b: np.ndarray,
    t_bc: np.ndarray,
    pre: list,
    gravity: float = GRAVITY,
    jac: list | None = None,
    ba_weight: float = 0.0,
):
    """Scale, gravity ``g_c0`` (3,) and velocities ``V`` (F, 3) in the frame ``c0`` (see the module doc).

    Args:
        pc: (F, 3) camera centres in ``c0``, up to scale.
        R_c0_b: (F, 3, 3) body orientations in ``c0``.
        t_bc: (3,) camera position in the body frame.
        pre: per interval ``(dR, alpha, beta, dt)``.
        jac: per interval ``(J_alpha, J_beta)`` (3, 3): the derivatives of ``alpha`` and ``beta`` by the
            accelerometer bias; None: the bias is taken as 0.
        ba_weight: weight of the bias's zero prior row (with ``jac``).

    Returns:
        ``(s, g, V, g_norm_free, residual_rms_m, b_a)``: ``g`` has norm ``gravity``; ``g_norm_free`` is the norm of
        the unconstrained solution, ``residual_rms_m`` the RMS of the position rows after refinement, ``b_a`` (3,)
        the accelerometer bias (zeros without ``jac``).
    """
    F = pc.shape[0]

    def rows(g_fixed: np.ndarray | None, B: np.ndarray | None):
        n_g = 3 if B is None else 2
        n_b = 3 if jac is not None else 0
        n = 3 * F + n_g + n_b + 1
        A, y = [], []
        for k, (_, al, be, dt) in enumerate(pre):
            Ap = np.zeros((3, n))
            Av = np.zeros((3, n))
            Ap[:, 3 * k : 3 * k + 3] = -dt * np.eye(3)
            Av[:, 3 * k : 3 * k + 3] = -np.eye(3)
            Av[:, 3 * k + 3 : 3 * k + 6] = np.eye(3)
            yp = R_c0_b[k] @ al + (R_c0_b[k + 1] - R_c0_b[k]) @ t_bc
            yv = R_c0_b[k] @ be
            G = np.eye(3) if B is None else B
            Ap[:, 3 * F : 3 * F + n_g] = -0.5 * dt * dt * G
            Av[:, 3 * F : 3 * F + n_g] = -dt * G
            if g_fixed is not None:
                yp = yp + 0.5 * dt * dt * g_fixed
                yv = yv + dt * g_fixed
            Ap[:, -1] = pc[k + 1] - pc[k]
            if n_b:
                Ap[:, -4:-1] = -R_c0_b[k] @ jac[k][0]
                Av[:, -4:-1] = -R_c0_b[k] @ jac[k][1]
            A += [Ap, Av]
            y += [yp, yv]
        if n_b:
            Ab = np.zeros((3, n))
            Ab[:, -4:-1] = ba_weight * np.eye(3)
            A.append(Ab)
            y.append(np.zeros(3))
        return np.concatenate(A), np.concatenate(y)

    A, y = rows(None, None)
    x = np.linalg.lstsq(A, y, rcond=None)[0]
    g = x[3 * F : 3 * F + 3]
    g_free = float(np.linalg.norm(g))
    for _ in range(4):
        g0 = gravity * g / np.linalg.norm(g)
        B = _tangent_basis(g0)
        A, y = rows(g0, B)
        x = np.linalg.lstsq(A, y, rcond=None)[0]
        g = g0 + B @ x[3 * F : 3 * F + 2]
    g = gravity * g / np.linalg.norm(g)
    A, y = rows(g, _tangent_basis(g))
    x = np.linalg.lstsq(A, y, rcond=None)[0]
    r = (A @ x - y)[: 6 * (F - 1)].reshape(-1, 2, 3)[:, 0]
    ba = x[-4:-1] if jac is not None else np.zeros(3)
    return float(x[-1]), g, x[: 3 * F].reshape(F, 3), g_free, float(np.sqrt(np.mean(r**2))), ba


def initialize_in_motion(
    frames: list,
    imu,
    T_b_c: np.ndarray,
    focal: float,
    cfg: DynamicInitConfig,
    gravity=GRAVITY,
    earlier_bias: np.ndarray | None = None,
):
    """States of ``frames`` (tracked :class:`FrameFeatures`, oldest first) from SfM and the IMU stream ``imu``
    (:class:`runtime.backend.imu.ImuStream`). Raises :class:`InitFailed` with the reason (and, once structure from
    motion has given it, the gyroscope bias). ``earlier_bias``: the gyroscope bias (3,) that earlier attempts
    agreed on; a bias larger than ``cfg.max_gyro_bias``, or farther than ``cfg.bias_agree`` from it, refuses the
    start (the gyroscope bias is constant over seconds, so a different one means a wrong structure from motion)."""
    T_c0_c, depth, info = structure_from_motion(frames, focal, cfg)
    R_c_b = T_b_c[:3, :3].T
    R_c0_b = T_c0_c[:, :3, :3] @ R_c_b
    ts = np.array([f.ts for f in frames], np.int64)
    segs = [imu.segment(int(a), int(b)) for a, b in zip(ts[:-1], ts[1:], strict=True)]
    bg = estimate_gyro_bias(R_c0_b, segs)
    if float(np.linalg.norm(bg)) > cfg.max_gyro_bias:
        raise BiasDisagrees(
            f"structure from motion implausible: gyroscope bias {np.round(bg, 3).tolist()} rad/s, larger than "
            f"max_gyro_bias {cfg.max_gyro_bias}"
        )
    if earlier_bias is not None and cfg.bias_agree > 0:
        off = float(np.linalg.norm(bg - earlier_bias))
        if off > cfg.bias_agree:
            raise BiasDisagrees(
                f"structure from motion disagrees with the earlier attempts: gyroscope bias {np.round(bg, 3).tolist()} "
                f"rad/s, {off:.3f} from their {np.round(earlier_bias, 3).tolist()} (> {cfg.bias_agree})"
            )
    try:
        return _align(T_c0_c, depth, info, R_c0_b, ts, segs, bg, T_b_c, cfg, gravity)
    except InitFailed as e:
        e.gyro_bias = bg
        raise


def _align(T_c0_c, depth, info, R_c0_b, ts, segs, bg, T_b_c, cfg, gravity) -> DynamicResult:
    """The visual-inertial alignment of :func:`initialize_in_motion` from its structure from motion and gyro bias."""
    pre = [_preintegrate(s, bg) for s in segs]
    rot_err = np.degrees(
        [np.linalg.norm(so3_log(p[0].T @ R_c0_b[k].T @ R_c0_b[k + 1])) for k, p in enumerate(pre)]
    ).max()
    t_bc = T_b_c[:3, 3]
    jac = None
    if cfg.accel_bias_weight > 0:  # alpha and beta are linear in the accelerometer bias
        jac = []
        for sg, p0 in zip(segs, pre, strict=True):
            cols = [_preintegrate(sg, bg, e) for e in np.eye(3)]
            jac.append((np.stack([c[1] - p0[1] for c in cols], 1), np.stack([c[2] - p0[2] for c in cols], 1)))
    s, g, V, g_free, res, ba = linear_alignment(
        T_c0_c[:, :3, 3], R_c0_b, t_bc, pre, gravity, jac, cfg.accel_bias_weight
    )
    info.update(
        scale=round(s, 4),
        gravity_free=round(g_free, 3),
        residual_m=round(res, 4),
        rot_err_deg=round(float(rot_err), 3),
        gyro_bias=np.round(bg, 5).tolist(),
        accel_bias=np.round(ba, 4).tolist(),
    )
    if not s > 0:
        raise InitFailed(f"alignment scale {s:.3g} is not positive")
    if abs(g_free - gravity) > cfg.gravity_tol:
        raise InitFailed(f"unconstrained gravity {g_free:.2f} m/s^2 is not ~{gravity} (scale {s:.3g})")
    if res > cfg.max_residual_m:
        raise InitFailed(f"alignment position residual {res:.3f} m (> {cfg.max_residual_m})")
    info["median_depth_m"] = round(s * depth, 3)
    if s * depth < cfg.min_depth_m:
        raise InitFailed(f"median scene depth {s * depth:.3f} m (< {cfg.min_depth_m}): tracks or scale implausible")
    R_w_c0 = gravity_aligned_rotation(-g)
    T = np.zeros((len(ts), 4, 4))
    T[:, 3, 3] = 1.0
    T[:, :3, :3] = R_w_c0 @ R_c0_b
    P = s * T_c0_c[:, :3, 3] - np.einsum("fij,j->fi", R_c0_b, t_bc)
    T[:, :3, 3] = (P - P[-1]) @ R_w_c0.T  # the newest frame at the origin
    info["span_s"] = round(ns_to_s(int(ts[-1] - ts[0])), 3)
    return DynamicResult(ts, T, V @ R_w_c0.T, bg, s, info, ba)


# ---------------------------------------------------------------------------------------------- hovering
def _bearings(xn: np.ndarray) -> np.ndarray:
    b = np.concatenate([xn, np.ones((xn.shape[0], 1))], 1)
    return b / np.linalg.norm(b, axis=1, keepdims=True)


def rotation_only(a, b, focal: float) -> tuple[np.ndarray, float, int]:
    """Rotation ``R_a_b`` (3, 3) that best maps the bearings of ``b``'s tracks onto ``a``'s (Kabsch, one
    re-fit without the worst quarter), the median residual [px] and the number of common tracks."""
    i, j = _common(a, b)
    if i.size < 3:
        return np.eye(3), np.inf, int(i.size)
    ba, bb = _bearings(a.xn[i]), _bearings(b.xn[j])
    keep = np.ones(i.size, bool)
    for _ in range(2):
        U, _, Vt = np.linalg.svd(ba[keep].T @ bb[keep])
        D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
        R = U @ D @ Vt
        res = np.linalg.norm(ba - bb @ R.T, axis=1) * focal
        keep = res <= np.quantile(res, 0.75)
    return R, float(np.median(res)), int(i.size)


def initialize_hovering(frames: list, imu, T_b_c: np.ndarray, focal: float, cfg: DynamicInitConfig):
    """States of ``frames`` while the camera turns without translating enough for structure from motion (a
    hovering MAV): rotations from the images (rotation-only fits to the oldest frame), the gyro bias from them,
    gravity from the mean specific force rotated into the oldest body frame (the velocity change over the window
    is taken as 0), zero velocity. Raises :class:`InitFailed` when the images show translation."""
    F = len(frames)
    R_c0_c = np.zeros((F, 3, 3))
    worst = 0.0
    for f in range(F):
        R, res, n = rotation_only(frames[0], frames[f], focal)
        if n < cfg.min_tracks:
            raise InitFailed(f"{n} tracks common with the oldest frame (< {cfg.min_tracks})")
        R_c0_c[f], worst = R, max(worst, res)
    if worst > cfg.hover_max_px:
        raise InitFailed(f"rotation-only residual {worst:.2f} px (> {cfg.hover_max_px}): the camera translates")
    R_c0_b = R_c0_c @ T_b_c[:3, :3].T
    ts = np.array([f.ts for f in frames], np.int64)
    segs = [imu.segment(int(a), int(b)) for a, b in zip(ts[:-1], ts[1:], strict=True)]
    bg = estimate_gyro_bias(R_c0_b, segs)
    g, a, dt = imu.segment(int(ts[0]), int(ts[-1]))
    R_b0_bn, _, dv = propagate(np.eye(3), np.zeros(3), np.zeros(3), g, a, dt, bg=bg, g_w=np.zeros(3))
    f_mean = dv / dt.sum()  # mean specific force in the oldest body frame: -g when the velocity did not change
    R_w_b0 = gravity_aligned_rotation(f_mean)
    T = np.tile(np.eye(4), (F, 1, 1))
    T[:, :3, :3] = R_w_b0 @ R_c0_b[0].T @ R_c0_b
    info = {
        "rotation_only_px": round(worst, 3),
        "gravity_free": round(float(np.linalg.norm(f_mean)), 3),
        "gyro_bias": np.round(bg, 5).tolist(),
        "span_s": round(ns_to_s(int(ts[-1] - ts[0])), 3),
    }
    return DynamicResult(ts, T, np.zeros((F, 3)), bg, float("nan"), info)
