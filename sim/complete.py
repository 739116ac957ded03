"""``dit-sim imu``: complete an EuRoC-layout sequence that has images and ground truth but no IMU.

The ground truth (``state_groundtruth_estimate0/data.csv``, e.g. 200 Hz from a laser tracker or motion capture)
is fitted by smoothing splines: quintic splines on the position, quintic splines on the four quaternion
components (sign-continuous, normalised after evaluation). Their derivatives give the velocity, the
acceleration and the body rate ``w_b = 2 Im(q* dq/dt)``; the IMU samples are instantaneous:

    gyro  = w_b(t_k) + b_g(t_k) + vibration + white noise
    accel = R_w_b(t_k)^T (a_w(t_k) - g_w) + b_a(t_k) + vibration + white noise

with the ground truth's own biases (interpolated) plus a random walk from the ``sensor.yaml`` densities. The
written ground truth is the fit itself at the IMU timestamps (the IMU and the ground truth agree exactly up to
the noise); the images are symbolic links to the source's files, never copies.

Ground-truth steps: a recorded ground truth can jump by millimetres to centimetres in one sample (EuRoC MH_05
jumps 1.8 cm at 40.2 s and 1.7 cm at 46.6 s: 3.7 and 3.3 m/s of extra speed for 5 ms, which the MAV never
flew). A fit that follows such a step turns it into a 10-20 g accelerometer impulse that no camera motion
explains. :func:`remove_steps` finds them (the finite-difference velocity off its running median by more than
``step_mps``) and spreads each over ``step_blend_s`` seconds with a smooth step before the fit, so the written
ground truth equals the source's outside those windows and the IMU sees a gentle bend instead.

``still > 0`` prepends a still period: the first image repeated at the camera rate while the platform rests,
then a smooth speed ramp into the recorded motion (the recorded trajectory is time-warped by ``s(tau)`` with
``s' = smooth_step`` over ``ramp`` seconds, so images and poses stay consistent; the frames of the ramp get the
warped timestamps).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.interpolate import UnivariateSpline

from runtime.geometry import GRAVITY_W, R_to_quat_wxyz, quat_wxyz_to_R
from runtime.io.euroc import GT_HEADER, IMU_HEADER, read_groundtruth, read_imu_yaml
from sim.euroc import _imu_yaml, _write_csv
from sim.imu import EUROC_ADIS16448, FLIGHT_IMU, ImuErrors, ImuNoise, add_imu_errors
from sim.output import GENERATOR, sim_output, write_info
from sim.trajectory import smooth_step

__all__ = ["SplineFit", "fit_ground_truth", "fit_source", "remove_steps", "steps_line", "complete_imu"]


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        -1,
    )


@dataclass
class SplineFit:
    """Smooth fit of a body trajectory; time ``t`` in seconds from ``t0_ns``.

    Attributes:
        t0_ns: time origin [ns].
        pos: three position splines [m].
        quat: four quaternion-component splines (w, x, y, z).
        t_range: (first, last) fitted time [s].
    """

    t0_ns: int
    pos: list
    quat: list
    t_range: tuple[float, float]

    def position(self, t: np.ndarray, nu: int = 0) -> np.ndarray:
        """Position (nu = 0), velocity (1) or acceleration (2) in the world: (N, 3)."""
        return np.stack([s(t, nu) for s in self.pos], -1)

    def rotation(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(R_w_b (N, 3, 3), w_b (N, 3))``: orientation and body-frame angular rate [rad/s]."""
        q = np.stack([s(t) for s in self.quat], -1)
        dq = np.stack([s(t, 1) for s in self.quat], -1)
        n = np.linalg.norm(q, axis=-1, keepdims=True)
        qn = q / n
        dqn = (dq - qn * np.sum(qn * dq, -1, keepdims=True)) / n
        conj = qn * np.array([1.0, -1.0, -1.0, -1.0])
        w = 2.0 * _quat_mul(conj, dqn)[:, 1:]
        return quat_wxyz_to_R(qn), w


def remove_steps(
    ts_ns: np.ndarray, p: np.ndarray, step_mps: float = 0.5, blend_s: float = 2.0, median_n: int = 21
) -> tuple[np.ndarray, list[dict]]:
    """Spread the ground truth's single-sample position steps over ``blend_s`` seconds.

    A step is a sample whose finite-difference velocity departs from its running median (``median_n`` samples)
    by more than ``step_mps``; consecutive such samples form one step (their summed excess displacement). Each
    step ``d`` at ``t_k`` is replaced by ``d * smooth_step((t - t_k) / blend_s + 1/2)``: the positions are
    unchanged before ``t_k - blend_s/2`` and after ``t_k + blend_s/2``.

    Args:
        ts_ns: (N,) int64 timestamps [ns], increasing.
        p: (N, 3) positions [m].
        step_mps: speed excess that marks a step [m/s] (0.5 m/s at 200 Hz: 2.5 mm in one sample).
        blend_s: width of the smooth replacement [s].
        median_n: running-median length [samples].

    Returns:
        ``(p_fixed, steps)``: the positions without the steps, and one ``{"t_ns", "step_m"}`` per step.
    """
    from scipy.ndimage import median_filter

    p = np.asarray(p, dtype=np.float64)
    t = (np.asarray(ts_ns, np.int64) - int(ts_ns[0])) * 1e-9
    if len(t) < median_n + 2:
        return p.copy(), []
    dt = np.diff(t)
    v = np.diff(p, axis=0) / dt[:, None]
    excess = (v - median_filter(v, size=(median_n, 1), mode="nearest")) * dt[:, None]  # displacement [m]
    flagged = np.linalg.norm(excess, axis=1) > step_mps * dt
    # the jumps themselves out (sample k carries every flagged displacement before it), then each step back in, smooth
    out = p - np.concatenate([np.zeros((1, 3)), np.cumsum(excess * flagged[:, None], axis=0)])
    bounds = np.flatnonzero(np.diff(np.concatenate([[0], flagged.astype(np.int8), [0]])))
    steps = []
    for i, j1 in zip(bounds[::2], bounds[1::2], strict=True):  # flagged[i:j1] is one step
        d = excess[i:j1].sum(0)
        tk = 0.5 * (t[i] + t[j1])  # the jump happens between samples i and j1
        out += d * smooth_step((t - tk) / blend_s + 0.5)[:, None]
        steps.append({"t_ns": int(ts_ns[0]) + int(round(tk * 1e9)), "step_m": [float(x) for x in d]})
    return out, steps


def steps_line(info: dict) -> str:
    """One line on the ground-truth steps of a :func:`complete_imu` summary: how many, their size and time."""
    steps = info["ground_truth_steps"]
    line = f"ground-truth steps spread over {info['ground_truth_step_blend_s']:g} s before the fit: {len(steps)}"
    sizes = ", ".join(f"{1e3 * float(np.linalg.norm(st['step_m'])):.1f} mm at {st['t_ns']} ns" for st in steps)
    return line + (f" ({sizes})" if steps else "")


def fit_ground_truth(
    ts_ns: np.ndarray, p: np.ndarray, q_wxyz: np.ndarray, sigma_p: float = 3e-4, sigma_q: float = 1.5e-4
) -> SplineFit:
    """Quintic smoothing splines through a ground truth (``s = N sigma^2`` per component).

    Args:
        ts_ns: (N,) int64 timestamps [ns].
        p: (N, 3) positions [m].
        q_wxyz: (N, 4) unit quaternions (signs made continuous here).
        sigma_p: expected position noise of the ground truth [m] (sets the smoothing).
        sigma_q: expected quaternion-component noise (1e-4 ~ 0.01 deg).

    Returns:
        The :class:`SplineFit`.
    """
    t0 = int(ts_ns[0])
    t = (np.asarray(ts_ns, np.int64) - t0) * 1e-9
    q = np.array(q_wxyz, dtype=np.float64)
    flip = np.cumprod(np.where(np.sum(q[1:] * q[:-1], -1) < 0, -1.0, 1.0))
    q[1:] *= flip[:, None]
    n = len(t)
    pos = [UnivariateSpline(t, p[:, i], k=5, s=n * sigma_p**2) for i in range(3)]
    quat = [UnivariateSpline(t, q[:, i], k=5, s=n * sigma_q**2) for i in range(4)]
    return SplineFit(t0, pos, quat, (float(t[0]), float(t[-1])))


def _read_frames(cam_dir: Path) -> tuple[np.ndarray, list[str]]:
    ts, names = [], []
    for line in (cam_dir / "data.csv").read_text().splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        a, b = (x.strip() for x in line.split(","))
        if (cam_dir / "data" / b).is_file():
            ts.append(int(a))
            names.append(b)
    if not ts:
        raise ValueError(f"{cam_dir / 'data.csv'}: no frame with an existing image")
    return np.asarray(ts, np.int64), names


class _Warp:
    """Time warp ``s(tau)`` [s]: constant ``s0`` until ``tau0``, ``s' = smooth_step`` over ``ramp``, then 1."""

    def __init__(self, s0: float, tau0: float, ramp: float):
        self.s0, self.tau0, self.ramp = s0, tau0, ramp
        g = np.linspace(0.0, ramp, 20001)
        self._g = g
        self._cum = np.concatenate(
            [[0.0], np.cumsum(0.5 * (smooth_step(g[1:] / ramp) + smooth_step(g[:-1] / ramp)) * np.diff(g))]
        )
        self.lag = ramp - self._cum[-1]  # s(tau) = tau - tau0 + s0 - lag after the ramp

    def __call__(self, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(s, s', s'')`` at ``tau`` (N,)."""
        x = np.asarray(tau, np.float64) - self.tau0
        xc = np.clip(x, 0.0, self.ramp)
        s = self.s0 + np.interp(xc, self._g, self._cum) + np.maximum(x - self.ramp, 0.0)
        d1 = smooth_step(x / self.ramp)
        h = 1e-5
        d2 = (smooth_step((x + h) / self.ramp) - smooth_step((x - h) / self.ramp)) / (2 * h)
        return s, d1, d2

    def inverse(self, s: np.ndarray) -> np.ndarray:
        """``tau`` of original times ``s >= s0`` (on the ramp by interpolation)."""
        s = np.asarray(s, np.float64) - self.s0
        on = s <= self._cum[-1]
        tau = self.tau0 + np.where(on, np.interp(s, self._cum, self._g), s + self.lag)
        return np.where(s <= 0.0, self.tau0, tau)


def fit_source(
    gt,
    cam_dir: Path,
    sigma_p: float = 3e-4,
    sigma_q: float = 1.5e-4,
    step_mps: float | None = 0.5,
    step_blend_s: float = 2.0,
) -> tuple[np.ndarray, list[str], np.ndarray, SplineFit, list]:
    """The frames of ``cam_dir`` inside the ground truth ``gt`` (0.2 s margins) and the fit of ``gt`` around them
    (1 s margins; steps spread first unless ``step_mps`` is None), as :func:`complete_imu` makes it.

    Returns:
        ``(frame_ts, names, sel, fit, steps)``: ``sel`` the ground-truth samples fitted.
    """
    frame_ts, names = _read_frames(cam_dir)
    keep = (frame_ts >= gt.ts[0] + 200_000_000) & (frame_ts <= gt.ts[-1] - 200_000_000)
    if keep.sum() < 2:
        raise ValueError(f"{cam_dir}: fewer than 2 frames lie inside the ground truth (with 0.2 s margins)")
    frame_ts, names = frame_ts[keep], [n for n, k in zip(names, keep, strict=True) if k]
    sel = (gt.ts >= frame_ts[0] - 1_000_000_000) & (gt.ts <= frame_ts[-1] + 1_000_000_000)
    p_src, steps = gt.p_w_b[sel], []
    if step_mps is not None:
        p_src, steps = remove_steps(gt.ts[sel], p_src, step_mps, step_blend_s)
    return frame_ts, names, sel, fit_ground_truth(gt.ts[sel], p_src, gt.q_wxyz[sel], sigma_p, sigma_q), steps


def complete_imu(
    source: str | Path,
    out: str | Path,
    *,
    seed: int = 0,
    noise: ImuNoise | None = None,
    errors: ImuErrors | None = FLIGHT_IMU,
    use_gt_bias: bool = True,
    still: float = 0.0,
    ramp: float = 2.0,
    rate_hz: int = 200,
    sigma_p: float = 3e-4,
    sigma_q: float = 1.5e-4,
    step_mps: float | None = 0.5,
    step_blend_s: float = 2.0,
    ideal: bool = False,
) -> dict:
    """Write ``out/mav0`` with ``imu0/``, a consistent ground truth and links to ``source``'s images.

    Args:
        source: EuRoC-layout root (``mav0/cam0`` with images, ``mav0/state_groundtruth_estimate0``).
        out: output root (created; an earlier ``dit-sim imu`` output there is replaced, a partial one too,
            anything else refused). An interrupted or failed run removes its partial output
            (:func:`sim.output.sim_output`).
        seed: noise seed.
        noise: white noise and random-walk densities (default: the source's ``imu0/sensor.yaml`` if it has one,
            else EuRoC's ADIS16448).
        errors: turn-on biases, vibration, scale (None: white noise and random walk only). With
            ``use_gt_bias`` the ground truth's biases replace the random turn-on biases.
        use_gt_bias: start the biases from the ground truth's own ``b_w``, ``b_a`` columns.
        still: seconds of rest prepended (first image repeated); 0: none.
        ramp: seconds of the speed ramp after the still period.
        rate_hz: IMU rate.
        sigma_p, sigma_q: smoothing of the fit (expected ground-truth noise).
        step_mps, step_blend_s: ground-truth steps above this speed excess are spread over this many seconds
            before the fit (:func:`remove_steps`); None keeps them.
        ideal: write the exact samples of the fitted motion (no noise, biases or vibration; ``errors`` and
            ``use_gt_bias`` ignored) with ``noise``'s densities in ``imu0/sensor.yaml``, so that an estimator
            weighs them as a real IMU's: what the images alone limit, with a perfect IMU.

    Returns:
        A summary (also written to ``out/sim_info.json``): fit errors, counts, the options.
    """
    source, out = Path(source).resolve(), Path(out)
    mav_src = source / "mav0" if (source / "mav0").is_dir() else source
    cam_src = mav_src / "cam0"
    gt_path = mav_src / "state_groundtruth_estimate0" / "data.csv"
    for p in (cam_src / "data.csv", cam_src / "sensor.yaml", gt_path):
        if not p.is_file():
            raise ValueError(f"{p}: missing (dit-sim imu needs cam0 images and a ground truth)")
    if noise is None:
        yml = mav_src / "imu0" / "sensor.yaml"
        if yml.is_file():
            ip = read_imu_yaml(yml)
            noise = ImuNoise(ip.gyro_noise_density, ip.gyro_random_walk, ip.accel_noise_density, ip.accel_random_walk)
        else:
            noise = EUROC_ADIS16448
    if still < 0 or ramp <= 0:
        raise ValueError(f"still must be >= 0 and ramp > 0, got still={still}, ramp={ramp}")
    if ideal:
        errors, use_gt_bias = None, False
    gt = read_groundtruth(gt_path)
    frame_ts, names, sel, fit, steps = fit_source(gt, cam_src, sigma_p, sigma_q, step_mps, step_blend_s)
    tg = (gt.ts[sel] - fit.t0_ns) * 1e-9
    inner = (gt.ts[sel] >= frame_ts[0]) & (gt.ts[sel] <= frame_ts[-1])
    e_p = np.linalg.norm(fit.position(tg[inner]) - gt.p_w_b[sel][inner], axis=1)
    R_fit, _ = fit.rotation(tg[inner])
    rel = np.swapaxes(R_fit, -1, -2) @ gt.T_w_b[sel][inner][:, :3, :3]
    e_r = np.degrees(np.arccos(np.clip((np.trace(rel, axis1=-2, axis2=-1) - 1) / 2, -1, 1)))
    e_v = np.linalg.norm(fit.position(tg[inner], 1) - gt.v_w[sel][inner], axis=1)

    # the output clock: tau [s] from the original first frame; the IMU every 1/rate from the first output frame
    dt_ns = int(round(1e9 / rate_hz))
    t_first = (frame_ts[0] - fit.t0_ns) * 1e-9
    orig = (frame_ts - frame_ts[0]) * 1e-9  # original frame times [s] from the first frame
    if still > 0:
        cam_dt_ns = max(dt_ns, int(round(float(np.median(np.diff(frame_ts))) / dt_ns)) * dt_ns)
        n_rep = max(1, int(round(still * 1e9 / cam_dt_ns)))
        pre_ns = n_rep * cam_dt_ns + int(round(ramp * 1e9 / dt_ns)) * dt_ns
        ramp = (pre_ns - n_rep * cam_dt_ns) * 1e-9  # on the IMU grid
        warp = _Warp(0.0, -ramp, ramp)  # s = 0 (the first frame's pose) until -ramp, then the ramp
        rep_ns = frame_ts[0] - pre_ns + cam_dt_ns * np.arange(n_rep, dtype=np.int64)
        new_ns = frame_ts[0] + np.round(warp.inverse(orig) * 1e9).astype(np.int64)
        out_frame_ts = np.concatenate([rep_ns, new_ns])
        out_names = [names[0]] * n_rep + names
        lag_ns = int(round((ramp - warp.lag) * 1e9))  # after the ramp, tau = original time - lag_ns
    else:
        pre_ns, n_rep, lag_ns = 0, 0, 0
        out_frame_ts, out_names = frame_ts, names
    t_out0_ns = int(frame_ts[0]) - pre_ns
    n_imu = int((out_frame_ts[-1] - t_out0_ns) // dt_ns) + 1
    imu_ts = t_out0_ns + dt_ns * np.arange(n_imu, dtype=np.int64)
    tau = (imu_ts - frame_ts[0]) * 1e-9
    if still > 0:
        s, s1, s2 = warp(tau)
    else:
        s, s1, s2 = tau, np.ones_like(tau), np.zeros_like(tau)
    t_fit = t_first + s
    if t_fit.max() > fit.t_range[1] or t_fit.min() < fit.t_range[0]:
        raise ValueError("the IMU span leaves the fitted ground truth (internal error)")
    p = fit.position(t_fit)
    v = fit.position(t_fit, 1) * s1[:, None]
    a = fit.position(t_fit, 2) * (s1 * s1)[:, None] + fit.position(t_fit, 1) * s2[:, None]
    R, w = fit.rotation(t_fit)
    w = w * s1[:, None]
    gyro = w
    accel = np.einsum("nji,nj->ni", R, a - GRAVITY_W)

    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x1A2]))
    err = errors if errors is not None else ImuErrors(gyro_bias_max=0.0, accel_bias_max=0.0, vibration=None)
    if use_gt_bias:
        from dataclasses import replace

        err = replace(err, gyro_bias_max=0.0, accel_bias_max=0.0)
    dt = dt_ns * 1e-9
    if ideal:
        g_meas, a_meas, bg, ba = gyro, accel, np.zeros_like(gyro), np.zeros_like(accel)
    else:
        g_meas, a_meas, bg, ba = add_imu_errors(gyro, accel, dt, rng, noise, err)
    if use_gt_bias:
        gt_t = (gt.ts - fit.t0_ns) * 1e-9
        bg0 = np.stack([np.interp(t_fit, gt_t, gt.bg[:, i]) for i in range(3)], -1)
        ba0 = np.stack([np.interp(t_fit, gt_t, gt.ba[:, i]) for i in range(3)], -1)
        g_meas, a_meas = g_meas + bg0, a_meas + ba0
        bg, ba = bg + bg0, ba + ba0

    info = {
        "generator": GENERATOR,
        "job": "imu",
        "source": str(source),
        "seed": int(seed),
        "frames": int(len(out_frame_ts)),
        "repeated_first_frames": int(n_rep),
        "imu_samples": int(n_imu),
        "imu_rate_hz": int(rate_hz),
        "still_s": float(still),
        "ramp_s": float(ramp if still > 0 else 0.0),
        "time_shift_after_ramp_ns": lag_ns,
        "vibration": errors is not None and errors.vibration is not None,
        "use_gt_bias": bool(use_gt_bias),
        "ideal": bool(ideal),
        "noise": {
            k: getattr(noise, k)
            for k in ("gyro_noise_density", "gyro_random_walk", "accel_noise_density", "accel_random_walk")
        },
        "fit": {
            "samples": int(inner.sum()),
            "pos_err_median_mm": float(np.median(e_p) * 1e3),
            "pos_err_p95_mm": float(np.percentile(e_p, 95) * 1e3),
            "pos_err_max_mm": float(e_p.max() * 1e3),
            "rot_err_median_deg": float(np.median(e_r)),
            "rot_err_p95_deg": float(np.percentile(e_r, 95)),
            "rot_err_max_deg": float(e_r.max()),
            "vel_err_median_mm_s": float(np.median(e_v) * 1e3),
        },
        "ground_truth_steps": steps,
        "ground_truth_step_blend_s": float(step_blend_s),
        "max_accel_mps2": float(np.linalg.norm(a_meas, axis=1).max()),
    }
    with sim_output(out, ("mav0",), "imu", source=str(source), seed=int(seed)):
        _write_completed(out, cam_src, out_frame_ts, out_names, noise, imu_ts, g_meas, a_meas, p, R, v, bg, ba)
        write_info(out, info)
    return info


def _write_completed(out, cam_src, out_frame_ts, out_names, noise, imu_ts, g_meas, a_meas, p, R, v, bg, ba) -> None:
    """The files of :func:`complete_imu` below ``out/mav0``: image links, IMU, ground truth, sensor files."""
    mav0 = out / "mav0"
    (mav0 / "cam0" / "data").mkdir(parents=True)
    lines = ["#timestamp [ns],filename"]
    for t, name in zip(out_frame_ts, out_names, strict=True):
        link = mav0 / "cam0" / "data" / f"{int(t)}.png"
        os.symlink(cam_src / "data" / name, link)
        lines.append(f"{int(t)},{int(t)}.png")
    (mav0 / "cam0" / "data.csv").write_text("\n".join(lines) + "\n")
    (mav0 / "cam0" / "sensor.yaml").write_text((cam_src / "sensor.yaml").read_text())
    (mav0 / "imu0").mkdir(parents=True)
    (mav0 / "imu0" / "sensor.yaml").write_text(
        _imu_yaml(noise).replace("simulated by dit-sim", "synthesised by dit-sim imu")
    )
    _write_csv(mav0 / "imu0" / "data.csv", IMU_HEADER, imu_ts, np.concatenate([g_meas, a_meas], 1))
    gt_rows = np.concatenate([p, R_to_quat_wxyz(R), v, bg, ba], 1)
    _write_csv(mav0 / "state_groundtruth_estimate0" / "data.csv", GT_HEADER, imu_ts, gt_rows)
