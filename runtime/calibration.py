"""The camera's intrinsics refined from the sequence itself: a visual-inertial bundle adjustment with the calibration
as a variable.

A written calibration is never exact. On the realistic presets of ``dit-sim euroc`` (focal lengths 0.5 % off, the
principal point 1 px, the distortion 2 %, as a user's own calibration would be) the error of the written intrinsics
alone cost flight seed 0 about 20 mm of its 23 mm Sim(3) ATE and handheld seed 2 about 22 of its 31 mm (2026-11-28,
``reports/ablations.md``). Monocular vision cannot see a focal error by itself, but the gyroscope can: a rotation of
angle ``a`` moves the image by ``f a`` pixels, so a wrong ``f`` makes the images disagree with the IMU. OpenVINS
estimates the intrinsics online for this reason; here they are estimated once, from the first seconds of the run,
for the sparse and the dense system alike (dense since 2026-12-02: SE(3) -17.0 +- 6.1 mm over 20 fresh runs against
the dense system on the written calibration, ``reports/ablations.md``).

:func:`refine_intrinsics` takes what a first sparse pass over those seconds gives (its per-frame poses and the
front end's tracks) and solves one Levenberg-Marquardt problem with GTSAM, all factors built in:

* every ``frame_step``-th posed frame gets a body state ``X, V, B`` and a camera pose ``C`` tied to it by the
  fixed ``T_b_c`` (``BetweenFactorPose3``, 1e-6 sigma);
* consecutive frames are linked by ``CombinedImuFactor`` with the first pass's IMU noise (its raise included);
* each track seen in at least ``min_views`` of these frames is a landmark, observed through
  ``GeneralSFMFactor2Cal3DS2`` on the raw (distorted, rolling-shutter corrected) pixels, with a Huber kernel;
* the calibration ``K`` (``Cal3DS2``: fx, fy, skew, cx, cy, k1, k2, p1, p2) starts at the written one, with a
  prior at about twice a careful calibration's error (skew held at 0);
* the first pose is held and the first bias weakly tied to 0 (the gauge).

With ``time_offset`` the same solve also estimates the camera-IMU time offset ``d`` (the image stamped ``t`` was
taken at ``t + d`` on the IMU's clock), as VINS-Mono and OpenVINS estimate it online: each camera pose is tied to
its body state through the body's twist, ``C = X Exp(d [omega, R^T v]) T_b_c`` (:func:`timed_camera_tie`), and the
run then moves the camera's stamps by ``d``. The estimate holds whatever delays the camera and the IMU integration
have against each other: the IMU factors hold each sample over the next sample period, half a period (2.5 ms at
200 Hz) behind samples that are instantaneous values.

The result is accepted when the solve used enough landmarks and the change stays within physical bounds; otherwise
the written calibration is kept and the reason reported. Radial-tangential cameras only (and the distortion-free
pinhole camera of an undistorted view); an equidistant (fisheye) model, or a distortion with more than four
coefficients, keeps its calibration, and the first pass is then not run (:func:`not_refined`).
"""

from __future__ import annotations

import logging
import os
import sys
import time
from contextlib import contextmanager
from dataclasses import dataclass, replace

import numpy as np

log = logging.getLogger(__name__)

__all__ = ["IntrinsicsConfig", "IntrinsicsResult", "not_refined", "refine_intrinsics", "tracks_from_features"]


@dataclass
class IntrinsicsConfig:
    """Settings of the intrinsics refinement (``runtime.intrinsics``)."""

    refine: bool = True  # refine the written intrinsics over a first sparse pass before the run (sparse and dense)
    seconds: float = 15.0  # seconds of data of the first (sparse) pass from the first frame
    frame_step: int = 3  # every n-th posed frame of the first pass is a frame of the adjustment
    min_views: int = 3  # a track needs this many frames of the adjustment
    pixel_sigma: float = 1.0  # [px] reprojection sigma
    huber_k: float = 1.345  # Huber threshold in sigmas
    focal_prior_rel: float = 0.01  # prior sigma of fx, fy relative to the written ones
    principal_prior_px: float = 2.0  # [px] prior sigma of cx, cy
    radial_prior_rel: float = 0.04  # prior sigma of k1, k2 relative to the written ones (at least radial_prior_min)
    radial_prior_min: float = 1e-3
    tangential_prior: float = 1e-5  # prior sigma of p1, p2
    min_landmarks: int = 150  # fewer: keep the written calibration
    min_frames: int = 15  # fewer frames of the adjustment: keep the written calibration
    max_focal_change_rel: float = 0.05  # a larger change is taken for a failure: keep the written calibration
    max_principal_change_px: float = 30.0
    iterations: int = 50  # LM iterations
    time_offset: bool = False  # also estimate the camera-IMU time offset in the same solve, and apply it
    time_offset_prior_s: float = 0.02  # [s] prior sigma of the offset (around 0)
    max_time_offset_s: float = 0.05  # a larger estimate is taken for a failure: keep the written calibration and stamps

    def __post_init__(self) -> None:
        if not self.seconds > 0:
            raise ValueError(f"intrinsics.seconds={self.seconds}: must be > 0")
        if self.frame_step < 1 or self.min_views < 2:
            raise ValueError("intrinsics.frame_step must be >= 1 and intrinsics.min_views >= 2")
        for name in (
            "pixel_sigma",
            "focal_prior_rel",
            "principal_prior_px",
            "radial_prior_rel",
            "radial_prior_min",
            "tangential_prior",
            "time_offset_prior_s",
            "max_time_offset_s",
        ):
            if not getattr(self, name) > 0:
                raise ValueError(f"intrinsics.{name}={getattr(self, name)}: must be > 0")


@dataclass
class IntrinsicsResult:
    """``camera``: the refined camera when ``accepted``, else the written one; ``report``: figures for
    ``metrics.json`` (written and refined intrinsics, counts, the reason when not accepted); ``time_offset_ns``:
    the camera-IMU time offset to add to the camera's stamps (0 unless estimated and accepted)."""

    camera: object
    accepted: bool
    report: dict
    time_offset_ns: int = 0


def tracks_from_features(camera, features: list, frame_ts: np.ndarray, min_views: int) -> tuple[list, np.ndarray]:
    """Tracks over selected frames from the front end's per-frame features.

    Args:
        camera: the written camera (maps the features' normalised coordinates back to raw pixels).
        features: :class:`runtime.frontend.tracking.FrameFeatures` of the first pass, in order.
        frame_ts: (F,) stamps [ns] of the frames of the adjustment.
        min_views: shortest track kept.

    Returns:
        ``(tracks, xn)``: each track a list of ``(frame index into frame_ts, raw pixel (2,))``; ``xn`` the same
        views' normalised coordinates as a list of (V, 2) arrays (for triangulation).
    """
    where = {int(t): n for n, t in enumerate(np.asarray(frame_ts, dtype=np.int64))}
    views: dict[int, list] = {}
    for f in features:
        n = where.get(int(f.ts))
        if n is None or f.ids.size == 0:
            continue
        uv, ok = camera.project(np.concatenate([f.xn, np.ones((f.xn.shape[0], 1))], 1))
        for i, x, q, good in zip(f.ids, f.xn, uv, ok, strict=True):
            if good:
                views.setdefault(int(i), []).append((n, q.astype(np.float64), x.astype(np.float64)))
    tracks = [v for v in views.values() if len(v) >= min_views]
    return [[(n, q) for n, q, _ in v] for v in tracks], [np.array([x for _, _, x in v]) for v in tracks]


@contextmanager
def _cpp_stdout():
    """Hold back what GTSAM's C++ prints on the process's stdout (file descriptor 1) while the block runs, and count
    its lines. ``GeneralSFMFactor2`` prints "CheiralityException: Landmark lN behind Camera cM" for every
    observation of a landmark that an LM step put behind a camera (and gives that observation zero error and
    Jacobians), thousands of lines in a poor step. Yields a one-element list holding the count afterwards."""
    import ctypes
    import tempfile

    count = [0]
    sys.stdout.flush()
    libc = ctypes.CDLL(None)
    saved = os.dup(1)
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 1)
        try:
            yield count
        finally:
            libc.fflush(None)
            os.dup2(saved, 1)
            os.close(saved)
            tmp.seek(0)
            text = tmp.read().decode(errors="replace")
            count[0] = text.count("behind Camera")
            other = [ln for ln in text.splitlines() if ln.strip() and "behind Camera" not in ln]
            if other:
                log.info("intrinsics: GTSAM printed: %s", " | ".join(other[:5]))


def _whitened(cond) -> tuple[np.ndarray, np.ndarray]:
    """A Gaussian conditional's ``R`` (frontal) and ``S`` (parents) with their rows divided by the noise model's
    sigmas (GTSAM keeps R's diagonal at 1 and the scale in the model)."""
    model = cond.get_model()
    sig = model.sigmas()[:, None] if model is not None else 1.0
    return np.asarray(cond.R(), np.float64) / sig, np.asarray(cond.S(), np.float64) / sig


def _initial_landmarks(tracks_xn: list, frames: list, T_w_c: np.ndarray, focal: float):
    """Linear triangulation (the runtime's) of each track from the first pass's camera poses."""
    from runtime.frontend.triangulation import stack_views, triangulate

    X, _, diag = triangulate(*stack_views(T_w_c, list(zip(frames, tracks_xn, strict=True))), focal=focal)
    good = (diag["min_depth"] >= 0.2) & np.isfinite(X).all(1) & (diag["max_err_px"] < 5.0)
    return X, good


def body_rates(traj_ts: np.ndarray, traj_T: np.ndarray, sel: np.ndarray, imu=None) -> np.ndarray:
    """The body's angular rate at the posed frames ``sel`` of a trajectory.

    The rate over the interval between a frame's neighbours is the trajectory's rotation over it; with ``imu`` it
    is the gyroscope's mean over the same interval less the gyroscope's bias, taken as the median over the frames
    of that mean less the trajectory's rate. A rate differenced from estimated poses carries their noise, and a
    time offset fitted against a noisy rate comes out too small (errors in the regressor); the gyroscope's is far
    less noisy.

    Args:
        traj_ts: (N,) stamps [ns]; traj_T: (N, 4, 4) body poses ``T_w_b``; sel: (F,) indices into them.
        imu: an :class:`runtime.backend.imu.ImuStream`, or None.

    Returns:
        (F, 3) angular rate [rad/s] in the body frame (central differences, one-sided at the ends).

    >>> from runtime.geometry import so3_exp
    >>> ts = np.arange(3) * 50_000_000
    >>> T = np.repeat(np.eye(4)[None], 3, 0); T[:, :3, :3] = [so3_exp(np.array([0, 0, 0.05 * k])) for k in range(3)]
    >>> body_rates(ts, T, np.array([1])).round(6).tolist()
    [[0.0, 0.0, 1.0]]
    """
    from runtime.geometry import so3_log

    traj_ts = np.asarray(traj_ts, dtype=np.int64)
    traj_T = np.asarray(traj_T, dtype=np.float64)
    n = traj_ts.size
    out = np.zeros((len(sel), 3))
    gyro = np.full((len(sel), 3), np.nan)
    for k, i in enumerate(np.asarray(sel, dtype=np.int64)):
        a, b = max(int(i) - 1, 0), min(int(i) + 1, n - 1)
        dt = (traj_ts[b] - traj_ts[a]) * 1e-9
        if b == a or not dt > 0:
            continue
        out[k] = so3_log(traj_T[a, :3, :3].T @ traj_T[b, :3, :3]) / dt
        if imu is not None:
            g, _, h = imu.segment(int(traj_ts[a]), int(traj_ts[b]))
            if h.sum() > 0:
                gyro[k] = (g * h[:, None]).sum(0) / h.sum()
    have = np.isfinite(gyro).all(1)
    if have.any():
        out[have] = gyro[have] - np.median(gyro[have] - out[have], axis=0)
    return out


def timed_camera_tie(noise, key_X: int, key_V: int, key_C: int, key_d: int, omega: np.ndarray, T_b_c):
    """A factor tying camera pose ``C`` to body state ``X, V`` through the camera-IMU time offset ``d``.

    The image stamped ``t`` was taken at ``t + d`` on the IMU's clock, where the body pose is, to first order in
    ``d``, ``X Exp(d xi)`` with the body's twist ``xi = [omega, R_X^T V]`` (``omega`` the body's angular rate at
    ``t``, :func:`body_rates`; the velocity is the state's own). The factor's error is
    ``Log((Exp(d xi) T_b_c)^-1 X^-1 C)`` (6,), with exact Jacobians with respect to ``X``, ``V``, ``C`` (GTSAM's
    retractions) and ``d`` (a ``Vector`` of size 1, seconds).

    Args:
        noise: 6-D noise model; key_X, key_V, key_C, key_d: GTSAM keys; omega: (3,) [rad/s];
        T_b_c: ``gtsam.Pose3`` of the camera in the body frame.
    """
    import gtsam

    from runtime.backend.factors import custom_factor
    from runtime.geometry import skew

    omega = np.asarray(omega, dtype=np.float64).reshape(3)
    Ad_cb = T_b_c.inverse().AdjointMap()

    def error_fn(values, jac: bool):
        Xp, Cp = values.atPose3(key_X), values.atPose3(key_C)
        v_w, d = np.asarray(values.atVector(key_V), np.float64), float(values.atVector(key_d)[0])
        R = Xp.rotation().matrix()
        xi = np.concatenate([omega, R.T @ v_w])
        M = gtsam.Pose3.Expmap(d * xi).compose(T_b_c)
        E = M.inverse().compose(Xp.inverse()).compose(Cp)
        e = gtsam.Pose3.Logmap(E)
        if not jac:
            return e, None
        J = np.linalg.inv(gtsam.Pose3.ExpmapDerivative(e))  # Log(E Exp(s)) ~ e + J s
        G = -J @ E.inverse().AdjointMap() @ Ad_cb  # a change s of M's twist in the body, M Exp(Ad_cb s)
        dxi = np.zeros((6, 9))  # d(d xi) / d[X (6), V (3)] through the velocity R^T v
        dxi[3:, :3] = d * skew(xi[3:])
        dxi[3:, 6:] = d * R.T
        D = G @ gtsam.Pose3.ExpmapDerivative(d * xi) @ dxi
        H_X = -J @ Cp.inverse().compose(Xp).AdjointMap() + D[:, :6]
        return e, [H_X, D[:, 6:], J, (G @ xi).reshape(6, 1)]

    return custom_factor(noise, [key_X, key_V, key_C, key_d], error_fn, [6, 3, 6, 1])


def not_refined(camera) -> str | None:
    """Why ``camera``'s model is outside the adjustment (None: it is refined). Checked before the first pass,
    which would otherwise be run for nothing."""
    if camera.model != "radtan":
        return f"camera model {camera.model!r} is not refined (radial-tangential only)"
    if len(camera.dist) > 4 and any(float(v) != 0.0 for v in camera.dist[4:]):
        return "a distortion with more than four coefficients is not refined"
    return None


def refine_intrinsics(
    camera,
    T_b_c: np.ndarray,
    imu_params,
    imu,
    features: list,
    traj_ts: np.ndarray,
    traj_T: np.ndarray,
    noise_scales: tuple[float, float] | None,
    cfg: IntrinsicsConfig | None = None,
) -> IntrinsicsResult:
    """Refine ``camera``'s intrinsics by a visual-inertial bundle adjustment over a first pass (module docstring).

    Args:
        camera: the written :class:`runtime.geometry.Camera`.
        T_b_c: (4, 4) cam0 pose in the body frame.
        imu_params: the IMU's noise densities (io ``ImuParams``).
        imu: the :class:`runtime.backend.imu.ImuStream` of the sequence.
        features: the first pass's per-frame :class:`~runtime.frontend.tracking.FrameFeatures`.
        traj_ts, traj_T: (N,) stamps [ns] and (N, 4, 4) body poses of the first pass's posed frames.
        noise_scales: (gyro, accel) white-noise multipliers the first pass used (None: the densities as stated).
        cfg: settings.

    Returns:
        The refined camera (or the written one, with the reason in ``report["reason"]``).
    """
    import gtsam
    from gtsam.symbol_shorthand import B, C, D, K, L, V, X
    from scipy.linalg import solve_triangular

    from runtime.backend.imu import integrate, preintegration_params

    cfg = cfg or IntrinsicsConfig()
    t0 = time.perf_counter()
    dist = [*map(float, camera.dist), 0.0, 0.0, 0.0, 0.0][:4]  # radial-tangential: k1, k2, p1, p2
    written = [*map(float, camera.intrinsics), *dist]
    report: dict = {"written": [round(v, 6) for v in written]}

    def keep(reason: str) -> IntrinsicsResult:
        report.update(reason=reason, seconds=round(time.perf_counter() - t0, 3))
        log.info("intrinsics: kept the written calibration (%s)", reason)
        return IntrinsicsResult(camera, False, report)

    if (why := not_refined(camera)) is not None:
        return keep(why)
    traj_ts = np.asarray(traj_ts, dtype=np.int64)
    sel = np.arange(0, traj_ts.size, cfg.frame_step)
    if sel.size < cfg.min_frames:
        return keep(f"{sel.size} posed frames in the first pass, fewer than {cfg.min_frames}")
    fts, T_w_b = traj_ts[sel], np.asarray(traj_T, dtype=np.float64)[sel]
    T_w_c = T_w_b @ T_b_c
    tracks, tracks_xn = tracks_from_features(camera, features, fts, cfg.min_views)
    frames = [np.array([n for n, _ in t]) for t in tracks]
    if not tracks:
        return keep("no track reaches min_views frames")
    X_l, good = _initial_landmarks(tracks_xn, frames, T_w_c, camera.fx)
    report.update(frames=int(sel.size), tracks=len(tracks), landmarks=int(good.sum()))
    if good.sum() < cfg.min_landmarks:
        return keep(f"{int(good.sum())} landmarks, fewer than {cfg.min_landmarks}")

    graph, vals = gtsam.NonlinearFactorGraph(), gtsam.Values()
    K0 = gtsam.Cal3DS2(written[0], written[1], 0.0, written[2], written[3], *written[4:])
    vals.insert(K(0), K0)
    fp, pp, tp = cfg.focal_prior_rel, cfg.principal_prior_px, cfg.tangential_prior
    rp = [max(cfg.radial_prior_rel * abs(k), cfg.radial_prior_min) for k in written[4:6]]
    k_sig = [fp * written[0], fp * written[1], 1e-9, pp, pp, *rp, tp, tp]
    graph.add(gtsam.PriorFactorCal3DS2(K(0), K0, gtsam.noiseModel.Diagonal.Sigmas(np.array(k_sig))))
    params = preintegration_params(imu_params, scales=noise_scales)
    dt_s = np.maximum(np.diff(fts) * 1e-9, 1e-6)
    vel = np.gradient(T_w_b[:, :3, 3], np.concatenate([[0.0], np.cumsum(dt_s)]), axis=0)
    tie = gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)
    T_bc = gtsam.Pose3(np.asarray(T_b_c, dtype=np.float64))
    zero = gtsam.imuBias.ConstantBias()
    if cfg.time_offset:  # the camera poses at the images' true times: C = X Exp(d xi) T_b_c, d a variable
        omega = body_rates(traj_ts, traj_T, sel, imu)
        # looser than the fixed tie: with the offset and the velocity in it, an LM step leaves second-order
        # misfits (offset x velocity change) that 1e-6 turned into errors no step could lower
        timed_tie = gtsam.noiseModel.Isotropic.Sigma(6, 1e-4)
        vals.insert(D(0), np.zeros(1))
        graph.add(
            gtsam.PriorFactorVector(D(0), np.zeros(1), gtsam.noiseModel.Isotropic.Sigma(1, cfg.time_offset_prior_s))
        )
    for n in range(fts.size):
        vals.insert(X(n), gtsam.Pose3(T_w_b[n]))
        vals.insert(V(n), vel[n])
        vals.insert(B(n), zero)
        vals.insert(C(n), gtsam.Pose3(T_w_c[n]))
        if cfg.time_offset:
            graph.add(timed_camera_tie(timed_tie, X(n), V(n), C(n), D(0), omega[n], T_bc))
        else:
            graph.add(gtsam.BetweenFactorPose3(X(n), C(n), T_bc, tie))
        if n:
            pim = gtsam.PreintegratedCombinedMeasurements(params, zero)
            integrate(pim, *imu.segment(int(fts[n - 1]), int(fts[n])))
            graph.add(gtsam.CombinedImuFactor(X(n - 1), V(n - 1), X(n), V(n), B(n - 1), B(n), pim))
    graph.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(T_w_b[0]), gtsam.noiseModel.Isotropic.Sigma(6, 1e-4)))
    graph.add(
        gtsam.PriorFactorConstantBias(B(0), zero, gtsam.noiseModel.Diagonal.Sigmas(np.array([0.5] * 3 + [0.2] * 3)))
    )
    M = gtsam.noiseModel.mEstimator
    pix = gtsam.noiseModel.Robust.Create(
        M.Huber.Create(cfg.huber_k), gtsam.noiseModel.Isotropic.Sigma(2, cfg.pixel_sigma)
    )
    n_obs = 0
    for m in np.flatnonzero(good):
        vals.insert(L(int(m)), X_l[m])
        for n, q in tracks[m]:
            graph.add(gtsam.GeneralSFMFactor2Cal3DS2(q, pix, C(int(n)), L(int(m)), K(0)))
            n_obs += 1
    lp = gtsam.LevenbergMarquardtParams()
    lp.setMaxIterations(int(cfg.iterations))
    # the elimination order: landmarks, then each frame's C, X, V, B in time, the time offset, the calibration last.
    # GTSAM's COLAMD order took 24 s for 4 LM steps on textured s0 (long tracks), this one 0.6 s, same optimum
    order = gtsam.Ordering()
    for m in np.flatnonzero(good):
        order.push_back(L(int(m)))
    for n in range(fts.size):
        for key in (C(n), X(n), V(n), B(n)):
            order.push_back(key)
    if cfg.time_offset:
        order.push_back(D(0))
    order.push_back(K(0))
    lp.setOrdering(order)
    with _cpp_stdout() as behind:
        e0 = graph.error(vals)
        try:
            opt = gtsam.LevenbergMarquardtOptimizer(graph, vals, lp)
            res = opt.optimize()
            e1 = graph.error(res)
        except RuntimeError as e:  # an indeterminant system: too little of the data constrains some variable
            res = e
    report["behind_camera_evaluations"] = behind[0]
    if isinstance(res, RuntimeError):
        return keep(f"the adjustment failed ({res})")
    k = res.atCal3DS2(K(0))
    refined = [k.fx(), k.fy(), k.px(), k.py(), k.k1(), k.k2(), k.p1(), k.p2()]
    t_m = time.perf_counter()
    # the estimate's standard deviations: the Gaussian approximation at the optimum, eliminated in the solve's order,
    # whose last conditional is the calibration's marginal (gtsam.Marginals, with its own order, found the system
    # indeterminant near a camera pose). A landmark whose every view LM put behind its camera has zero Jacobians
    # (_cpp_stdout): a weak prior (1 km) on each keeps the linear system determinate without moving that marginal
    try:
        held = gtsam.NonlinearFactorGraph(graph)
        far = gtsam.noiseModel.Isotropic.Sigma(3, 1e3)
        for m in np.flatnonzero(good):
            held.add(gtsam.PriorFactorPoint3(L(int(m)), res.atPoint3(L(int(m))), far))
        with _cpp_stdout():
            lin = held.linearize(res)
            try:
                bn = lin.eliminateSequential(order)
            except RuntimeError:  # a landmark too poorly conditioned for Cholesky: QR, 6x slower, same figures
                bn = lin.eliminateSequential(order, gtsam.EliminateQR)
        last = bn.at(bn.size() - 1)  # p(K): R K = d with the model's sigmas (GTSAM keeps R's diagonal at 1)
        R_K = _whitened(last)[0]
        R_inv = solve_triangular(R_K, np.eye(9))  # covariance R^-1 R^-T, by rows: the held
        sd = np.sqrt(np.sum(R_inv**2, axis=1))  # skew makes R^T R too ill-conditioned to invert as a whole
        report["std"] = {
            "focal_rel": [round(float(sd[0] / refined[0]), 6), round(float(sd[1] / refined[1]), 6)],
            "principal_px": [round(float(sd[3]), 4), round(float(sd[4]), 4)],
        }
        if cfg.time_offset:  # p(d | K) p(K): the joint's upper-triangular factor, d's row first
            R_d, S_d = _whitened(bn.at(bn.size() - 2))
            A = np.zeros((10, 10))
            A[0, 0], A[0, 1:], A[1:, 1:] = R_d[0, 0], S_d[0], R_K
            row = solve_triangular(A, np.eye(10))[0]
            report["std"]["time_offset_s"] = round(float(np.sqrt(np.sum(row**2))), 6)
    except (RuntimeError, np.linalg.LinAlgError) as e:
        report["std"] = None
        log.warning("intrinsics: no standard deviations (%s)", e)
    report["marginals_s"] = round(time.perf_counter() - t_m, 3)
    report.update(
        estimated=[round(float(v), 6) for v in refined],
        iterations=opt.iterations(),
        observations=n_obs,
        error_before=round(float(e0), 1),
        error_after=round(float(e1), 1),
        focal_change_rel=[round(refined[i] / written[i] - 1.0, 6) for i in (0, 1)],
        principal_change_px=[round(refined[i] - written[i], 4) for i in (2, 3)],
    )
    if not np.isfinite(refined).all():
        return keep("the adjustment returned a non-finite calibration")
    if max(abs(v) for v in report["focal_change_rel"]) > cfg.max_focal_change_rel:
        return keep(f"focal lengths changed by more than {cfg.max_focal_change_rel:.0%}")
    if max(abs(v) for v in report["principal_change_px"]) > cfg.max_principal_change_px:
        return keep(f"principal point moved by more than {cfg.max_principal_change_px:g} px")
    d = 0.0
    if cfg.time_offset:
        d = float(res.atVector(D(0))[0])
        report["time_offset_s"] = round(d, 6)
        if not (np.isfinite(d) and abs(d) <= cfg.max_time_offset_s):
            return keep(f"time offset {d * 1e3:.1f} ms, beyond {cfg.max_time_offset_s * 1e3:g} ms")
    out = replace(
        camera,
        fx=float(refined[0]),
        fy=float(refined[1]),
        cx=float(refined[2]),
        cy=float(refined[3]),
        dist=tuple(float(v) for v in refined[4:]),
    )
    report["seconds"] = round(time.perf_counter() - t0, 3)
    log.info(
        "intrinsics: refined over %d frames, %d landmarks: fx %+.2f %%, fy %+.2f %%, cx %+.2f px, cy %+.2f px",
        sel.size,
        int(good.sum()),
        100 * report["focal_change_rel"][0],
        100 * report["focal_change_rel"][1],
        *report["principal_change_px"],
    )
    if cfg.time_offset:
        log.info("intrinsics: camera-IMU time offset %+.2f ms (the camera's stamps move by it)", 1e3 * d)
    return IntrinsicsResult(out, True, report, time_offset_ns=int(round(d * 1e9)))
