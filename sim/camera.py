"""Camera physics: exposure and motion blur, auto-exposure, shot and read noise, gamma, vignetting, 8 bits.

A frame starts as linear scene radiance (:meth:`sim.render.Renderer.radiance`, 1 = a white surface fully lit)
at the middle of its exposure. Then, per pixel:

1. illumination (a global level with sudden changes: a lamp switched on or off) and vignetting
   (``1 - v r^2``, ``r`` = distance from the centre over the half-diagonal);
2. motion blur and rolling shutter by per-pixel flow: the pixel velocity (px/s) follows from the depth and the
   camera's motion at mid-exposure; the image is the mean of ``K`` resampled copies at times spread over the
   exposure (plus the row's read-out delay with a rolling shutter), ``K`` about one per pixel of blur;
3. photo-electrons ``e = radiance * electrons_per_s * exposure``, shot noise ``sqrt(e)`` and read noise (Gaussian
   approximations), clipped at the full well;
4. analogue gain, the transfer curve ``x^(1 / gamma)``, 8-bit quantisation.

Auto-exposure runs frame by frame on what the previous frame measured (a one-frame lag, as real controllers
have): exposure time first, up to ``exposure_max_s``, then gain. A sudden change of light therefore gives a few
badly exposed frames, as in real recordings.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from runtime.geometry import Camera

__all__ = [
    "CameraPhysics",
    "illumination",
    "auto_exposure",
    "vignetting",
    "pixel_velocity",
    "expose",
    "perturbed_calibration",
]


@dataclass(frozen=True)
class CameraPhysics:
    """Sensor, optics and controller parameters (defaults: a global-shutter MT9M034-like camera, as EuRoC's).

    Attributes:
        electrons_per_s: photo-electrons per second at radiance 1 and illumination 1.
        full_well_e: saturation [e-].
        read_noise_e: read noise [e-] (before gain).
        gain_max: largest analogue gain.
        exposure_min_s, exposure_max_s: exposure time range [s].
        ae_target: auto-exposure target of the mean linear signal (fraction of full scale).
        ae_rate: fraction of the log-brightness error corrected per frame.
        gamma: transfer curve exponent (8-bit value = 255 x^(1/gamma)).
        vignetting: relative brightness loss at the image corners.
        readout_s: rolling-shutter read-out time of the whole image [s] (0: global shutter).
        time_offset_s: the frame stamped t shows the scene at t + time_offset_s (camera-IMU offset).
        illum_range: (lo, hi) of the scene's initial illumination level (log-uniform).
        lamp_events_per_min: rate of sudden illumination changes.
        lamp_factor: (lo, hi) factor of a change (log-uniform, up or down).
        calib_focal_rel: standard deviation of the written focal lengths' relative error.
        calib_pp_px: standard deviation of the written principal point's error [px at full resolution].
        calib_dist_rel: standard deviation of the written distortion coefficients' relative error.
        max_blur_samples: cap on the resampled copies per frame.
    """

    electrons_per_s: float = 1.5e6
    full_well_e: float = 10000.0
    read_noise_e: float = 12.0
    gain_max: float = 8.0
    exposure_min_s: float = 5e-5
    exposure_max_s: float = 0.01
    ae_target: float = 0.22
    ae_rate: float = 0.5
    gamma: float = 1.6
    vignetting: float = 0.3
    readout_s: float = 0.0
    time_offset_s: float = 0.0
    illum_range: tuple[float, float] = (0.4, 1.5)
    lamp_events_per_min: float = 1.5
    lamp_factor: tuple[float, float] = (0.35, 0.7)
    calib_focal_rel: float = 0.005
    calib_pp_px: float = 1.0
    calib_dist_rel: float = 0.02
    max_blur_samples: int = 12


def illumination(t: np.ndarray, duration: float, physics: CameraPhysics, rng: np.random.Generator) -> np.ndarray:
    """Global illumination level at times ``t`` (F,) [s]: a base level with sudden (step) changes."""
    lo, hi = physics.illum_range
    level = float(np.exp(rng.uniform(np.log(lo), np.log(hi))))
    n = int(rng.poisson(physics.lamp_events_per_min * duration / 60.0))
    times = np.sort(rng.uniform(0.0, duration, n))
    fl, fh = physics.lamp_factor
    factors = np.exp(rng.uniform(np.log(fl), np.log(fh), n)) ** rng.choice([-1.0, 1.0], n)
    out = np.full(np.shape(t), level)
    for tc, f in zip(times, factors, strict=True):
        out = np.where(np.asarray(t) >= tc, out * f, out)
    return out


def auto_exposure(previews: np.ndarray, illum: np.ndarray, physics: CameraPhysics) -> tuple[np.ndarray, np.ndarray]:
    """Exposure time and gain of every frame from low-resolution radiance previews.

    Args:
        previews: (F, h, w) float32 linear radiance of each frame (vignetting applied or not).
        illum: (F,) illumination level of each frame.
        physics: the controller's parameters.

    Returns:
        ``(exposure_s, gain)``: (F,) each. Frame k uses the settings computed from frame k - 1's measurement.
    """
    F = previews.shape[0]
    exp_s, gain = np.empty(F), np.empty(F)
    e_max = physics.exposure_max_s * physics.gain_max
    # start settled on the first frame
    m0 = float(np.mean(np.minimum(previews[0] * illum[0], 1e3))) * physics.electrons_per_s / physics.full_well_e
    E = float(np.clip(physics.ae_target / max(m0, 1e-9), physics.exposure_min_s, e_max))
    for k in range(F):
        t = min(max(E, physics.exposure_min_s), physics.exposure_max_s)
        g = min(max(E / t, 1.0), physics.gain_max)
        exp_s[k], gain[k] = t, g
        s = physics.electrons_per_s * t * g / physics.full_well_e
        m = float(np.mean(np.minimum(previews[k] * illum[k] * s, 1.0)))  # what the camera measured (clipped)
        E = float(np.clip(t * g * (physics.ae_target / max(m, 1e-6)) ** physics.ae_rate, physics.exposure_min_s, e_max))
    return exp_s, gain


def vignetting(shape: tuple[int, int], amount: float) -> np.ndarray:
    """(H, W) float32 factor ``1 - amount r^2``, r = distance from the centre over the half-diagonal."""
    H, W = shape
    v, u = np.mgrid[0:H, 0:W].astype(np.float32)
    r2 = ((u - (W - 1) / 2) ** 2 + (v - (H - 1) / 2) ** 2) / (((W - 1) / 2) ** 2 + ((H - 1) / 2) ** 2)
    return (1.0 - np.float32(amount) * r2).astype(np.float32)


def pixel_velocity(
    depth: np.ndarray,
    camera: Camera,
    rays: tuple[np.ndarray, np.ndarray],
    T_c1_c0: np.ndarray,
    dt: float,
    step: int = 4,
) -> np.ndarray:
    """Image velocity (H, W, 2) [px/s] of every pixel for the relative motion ``T_c1_c0`` over ``dt`` seconds.

    Computed on every ``step``-th pixel (the flow is smooth but at depth edges) and upsampled bilinearly.
    """
    H, W = depth.shape
    d = depth[::step, ::step].astype(np.float64)
    x, y = rays[0][::step, ::step], rays[1][::step, ::step]
    p = np.stack([x * d, y * d, d], -1).reshape(-1, 3)
    p1 = p @ T_c1_c0[:3, :3].T + T_c1_c0[:3, 3]
    uv1, _ = camera.project(p1)
    uv0, _ = camera.project(p)
    vel = ((uv1 - uv0) / dt).reshape(d.shape + (2,)).astype(np.float32)
    return cv2.resize(vel, (W, H), interpolation=cv2.INTER_LINEAR)


def expose(
    radiance: np.ndarray,
    vel: np.ndarray | None,
    exposure_s: float,
    gain: float,
    illum: float,
    physics: CameraPhysics,
    vig: np.ndarray,
    rng: np.random.Generator,
    row_time_s: float = 0.0,
) -> np.ndarray:
    """The 8-bit image a sensor records from linear ``radiance`` (H, W) or (H, W, 3).

    Args:
        radiance: scene radiance at mid-exposure.
        vel: (H, W, 2) pixel velocity [px/s] or None (no motion).
        exposure_s, gain, illum: this frame's exposure time, analogue gain and illumination level.
        physics: sensor parameters.
        vig: (H, W) vignetting factor.
        rng: noise generator.
        row_time_s: rolling-shutter delay per row [s] (rows read from the top; the middle row is on time).

    Returns:
        (H, W) or (H, W, 3) uint8.
    """
    f32 = np.float32
    H, W = radiance.shape[:2]
    lin = radiance * (f32(illum) * (vig if radiance.ndim == 2 else vig[..., None]))
    if vel is not None:
        speed = np.linalg.norm(vel, axis=-1)
        blur_px = float(np.percentile(speed, 99)) * exposure_s
        rs_px = float(np.percentile(speed, 99)) * abs(row_time_s) * H
        K = int(np.clip(np.ceil(blur_px), 1, physics.max_blur_samples)) if blur_px > 0.3 else 1
        if K > 1 or rs_px > 0.1:
            u, v = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
            row_dt = (v - f32((H - 1) / 2)) * f32(row_time_s)
            acc = np.zeros_like(lin)
            for j in range(K):
                dtj = row_dt + f32(exposure_s * ((j + 0.5) / K - 0.5)) if K > 1 else row_dt
                mx = u - vel[..., 0] * dtj
                my = v - vel[..., 1] * dtj
                acc += cv2.remap(lin, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            lin = acc / f32(K)
    e = lin * f32(physics.electrons_per_s * exposure_s)
    sigma = np.sqrt(np.maximum(e, 0) + f32(physics.read_noise_e**2))
    e = e + sigma * rng.standard_normal(e.shape, dtype=np.float32)
    x = np.clip(e * f32(gain / physics.full_well_e), 0.0, 1.0)
    x = np.power(x, f32(1.0 / physics.gamma))
    return np.clip(x * f32(255.0) + f32(0.5), 0, 255).astype(np.uint8)


def perturbed_calibration(
    camera: Camera, physics: CameraPhysics, rng: np.random.Generator, scale: float = 1.0
) -> Camera:
    """The calibration a user would have: ``camera`` with realistic errors (focal, principal point, distortion)."""
    ef = rng.normal(0.0, physics.calib_focal_rel, 2)
    ep = rng.normal(0.0, physics.calib_pp_px * scale, 2)
    ed = rng.normal(0.0, physics.calib_dist_rel, len(camera.dist))
    return Camera(
        camera.fx * (1.0 + float(ef[0])),
        camera.fy * (1.0 + float(ef[1])),
        camera.cx + float(ep[0]),
        camera.cy + float(ep[1]),
        camera.width,
        camera.height,
        tuple(float(d * (1.0 + e)) for d, e in zip(camera.dist, ed, strict=True)),
        camera.model,
    )
