"""Synthetic sequences in the EuRoC ASL layout (cam0, imu0, ground truth, plus depth0).

Layout written under ``out``::

    out/sim_info.json                              what was rendered (seed, preset, white-wall window, ...)
    out/mav0/cam0/{data.csv, data/<ts>.png, sensor.yaml}    752x480 grey, 20 Hz, EuRoC cam0 intrinsics, radtan
    out/mav0/imu0/{data.csv, sensor.yaml}                   200 Hz gyro (w_RS_S), accel (a_RS_S), ADIS16448
    out/mav0/state_groundtruth_estimate0/data.csv           200 Hz p, q (w,x,y,z), v, b_w, b_a of the body
    out/mav0/depth0/{data.csv, data/<ts>.png, sensor.yaml}  uint16 PNG, cam0 z-depth [m] * 5000, 0 = invalid

IMU, ground truth and camera share one clock: ``t_k = T0_NS + k * 5 ms``, a camera frame every 10th sample.
IMU sample k holds over ``[t_k, t_k+1)``; with ``imu_noise=False`` GTSAM's preintegration of samples
``i..j-1`` reproduces the ground-truth state j from state i (see :mod:`sim.imu`). Images are rendered at the
ground-truth body poses through cam0's ``T_BS``: ``T_w_c = T_w_b @ T_b_c``.
"""

from __future__ import annotations

import multiprocessing
import os
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from runtime.geometry import Camera, R_to_quat_wxyz
from runtime.io.euroc import EUROC_CAM0, EUROC_T_B_C0, GT_HEADER, IMU_HEADER
from runtime.outputs import atomic_write
from sim.camera import (
    CameraPhysics,
    auto_exposure,
    expose,
    illumination,
    perturbed_calibration,
    pixel_velocity,
    vignetting,
)
from sim.imu import (
    EUROC_ADIS16448,
    FLIGHT_IMU,
    HANDHELD_IMU,
    ImuErrors,
    ImuNoise,
    add_imu_errors,
    add_imu_noise,
    instantaneous_imu,
    synthesize_imu,
)
from sim.output import GENERATOR, sim_output, write_info
from sim.render import Renderer
from sim.scenes import PRESETS, ROOM_PRESETS, Scene, make_scene
from sim.trajectory import Trajectory, make_trajectory

__all__ = [
    "EUROC_CAM0",
    "FISHEYE_CAM0",
    "EUROC_T_B_C0",
    "IMU_RATE_HZ",
    "CAM_EVERY",
    "T0_NS",
    "DEPTH_SCALE",
    "scaled_camera",
    "SequenceData",
    "simulate_sequence",
    "write_euroc_sequence",
]

IMU_RATE_HZ = 200
CAM_EVERY = 10  # one camera frame per 10 IMU samples: 20 Hz
DT_NS = 1_000_000_000 // IMU_RATE_HZ
T0_NS = 1_700_000_000_000_000_000  # first timestamp [ns]
DEPTH_SCALE = 5000.0  # depth0 PNG value per metre
PNG_PARAMS = [cv2.IMWRITE_PNG_COMPRESSION, 1]
MAX_SCALE = 4.0  # image resolution factor: 3008x1920 at most
RENDER_BYTES_PER_PIXEL = 100  # peak memory of one frame's rendering (measured 84 B/px at scales 0.5-2)
PHYSICS_DT = 1e-3  # [s] step of the camera motion that gives the pixel velocities (motion blur, rolling shutter)


#: The fisheye of ``dit-sim euroc camera=fisheye``: EuRoC's 752x480 sensor behind an equidistant lens with TUM-VI's
#: cam0 coefficients, 143 deg across the width and 85 deg from the axis at the corners.
FISHEYE_CAM0 = Camera(
    300.0,
    300.0,
    375.5,
    239.5,
    752,
    480,
    (0.0034823894022493434, 0.0007150348452162257, -0.0020532361418706202, 0.00020293673591811182),
    "equidistant",
)
CAMERAS = {"pinhole": EUROC_CAM0, "fisheye": FISHEYE_CAM0}


def scaled_camera(scale: float = 1.0, base: Camera = EUROC_CAM0) -> Camera:
    """``base`` resampled by ``scale`` (pixel centres: ``u' = scale (u + 0.5) - 0.5``); 1.0 gives ``base``.

    >>> cam = scaled_camera(0.5)
    >>> (cam.width, cam.height, cam.fx == EUROC_CAM0.fx / 2)
    (376, 240, True)
    """
    if scale <= 0:
        raise ValueError(f"scale must be positive, got {scale}")
    if scale == 1.0:
        return base
    return Camera(
        base.fx * scale,
        base.fy * scale,
        (base.cx + 0.5) * scale - 0.5,
        (base.cy + 0.5) * scale - 0.5,
        int(round(base.width * scale)),
        int(round(base.height * scale)),
        base.dist,
        base.model,
    )


@dataclass
class SequenceData:
    """Everything of a sequence except the images.

    Attributes:
        ts: (N,) int64 IMU / ground-truth timestamps [ns].
        gyro, accel: (N, 3) IMU samples (rad/s, m/s^2), noisy when requested.
        R_w_b: (N, 3, 3), p_w_b: (N, 3), v_w: (N, 3): discrete ground-truth body states.
        bg, ba: (N, 3) true biases (zero without IMU noise).
        frame_idx: (F,) indices into ``ts`` of the camera frames.
        window: whitewall hold (t0, t1) [s] after the first sample, or None.
        scene: the grey scene the frames are rendered from.
        trajectory: the smooth camera trajectory the states were sampled from.
    """

    ts: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    R_w_b: np.ndarray
    p_w_b: np.ndarray
    v_w: np.ndarray
    bg: np.ndarray
    ba: np.ndarray
    frame_idx: np.ndarray
    window: tuple[float, float] | None
    scene: Scene | None = None
    trajectory: Trajectory | None = None

    def T_w_b(self, k: int | np.ndarray) -> np.ndarray:
        """Ground-truth body pose(s) at sample index(es) ``k``: (4, 4) or (K, 4, 4)."""
        k = np.asarray(k)
        T = np.zeros(k.shape + (4, 4))
        T[..., :3, :3] = self.R_w_b[k]
        T[..., :3, 3] = self.p_w_b[k]
        T[..., 3, 3] = 1.0
        return T


def imu_errors_for(preset: str) -> ImuErrors:
    """The real-IMU errors of a preset: rotor vibration for MAV-like ones, none for hand-held ones."""
    return HANDHELD_IMU if preset in ("handheld", "tabletop") else FLIGHT_IMU


def make_any_trajectory(scene: Scene, duration: float, seed: int, preset: str):
    """``make_trajectory`` or, for the realistic presets, :func:`sim.motion.make_motion_trajectory`."""
    if preset in ROOM_PRESETS:
        from sim.motion import make_motion_trajectory

        return make_motion_trajectory(scene, duration, seed, preset)
    return make_trajectory(scene, duration, seed, preset)


def camera_physics_for(preset: str) -> CameraPhysics:
    """Camera physics of a preset: EuRoC-like global shutter for MAV ones, a rolling shutter for hand-held ones."""
    if preset in ("handheld", "tabletop"):
        return CameraPhysics(readout_s=0.015, time_offset_s=-0.006, exposure_max_s=0.015)
    return CameraPhysics(time_offset_s=0.003, illum_range=(0.2, 0.7))  # a dim hall: long exposures, as EuRoC MH


def physics_jobs(
    data: SequenceData, physics: CameraPhysics, duration: float, scale: float, rng: np.random.Generator
) -> tuple[list, np.ndarray, np.ndarray, np.ndarray]:
    """Frame jobs with camera physics: poses at mid-exposure (+ time offset), motion, auto-exposure settings.

    Returns:
        ``(jobs, exposure_s, gain, illumination)``: a job per frame ``(k, ts, T_w_c, T_c1_c0, exposure, gain,
        illumination)`` for :func:`render_job`, and the per-frame settings (F,).
    """
    t_f = data.frame_idx * (DT_NS * 1e-9) + physics.time_offset_s
    T_w_c = data.trajectory.camera_T(t_f)
    T_c1_c0 = np.linalg.inv(data.trajectory.camera_T(t_f + PHYSICS_DT)) @ T_w_c
    illum = illumination(t_f, duration, physics, rng)
    preview = Renderer(data.scene, scaled_camera(scale * 0.125))
    previews = np.stack([preview.radiance(T)[0] for T in T_w_c])
    exposure_s, gain = auto_exposure(previews, illum, physics)
    frame_ts = data.ts[data.frame_idx]
    jobs = [
        (int(k), int(ts), T, Tr, float(e), float(g), float(li))
        for k, ts, T, Tr, e, g, li in zip(
            data.frame_idx, frame_ts, T_w_c, T_c1_c0, exposure_s, gain, illum, strict=True
        )
    ]
    return jobs, exposure_s, gain, illum


def check_scale(scale: float, workers: int = 1) -> None:
    """Refuse an image scale whose rendering cannot fit, before any work, with the memory it would need.

    Raises:
        ValueError: ``scale`` is not in (0, MAX_SCALE] or the rendering processes would need more memory than
            the machine has.
    """
    if not np.isfinite(scale) or scale <= 0:
        raise ValueError(f"scale must be a positive number, got {scale}")
    cam = scaled_camera(min(float(scale), 1e3))
    need = cam.width * cam.height * RENDER_BYTES_PER_PIXEL * max(1, int(workers))
    msg = (
        f"scale={scale:g} renders {cam.width}x{cam.height} frames: about {need / 1e9:.1f} GB for "
        f"{max(1, workers)} rendering process(es)"
    )
    if scale > MAX_SCALE:
        raise ValueError(f"{msg}; scale must be <= {MAX_SCALE:g}")
    try:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):  # not available on this platform
        return
    if need > 0.8 * total:
        raise ValueError(f"{msg}, more than this machine's {total / 1e9:.1f} GB; use a smaller scale or fewer workers")


def write_png(path: Path, img: np.ndarray) -> None:
    """Encode ``img`` as PNG and write it atomically (temporary name, then rename): never a half-written PNG."""
    ok, buf = cv2.imencode(".png", img, PNG_PARAMS)
    if not ok:
        raise OSError(f"could not encode {path}")
    atomic_write(path, lambda tmp: tmp.write_bytes(buf.tobytes()))


def _check_args(preset: str, duration: float, seed: int) -> None:
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; expected one of {PRESETS}")
    if not np.isfinite(duration) or duration <= 0:
        raise ValueError(f"duration must be a positive number of seconds, got {duration}")
    if int(seed) != seed or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed}")


def simulate_sequence(
    preset: str = "textured",
    duration: float = 10.0,
    seed: int = 0,
    imu_noise: bool = True,
    noise: ImuNoise = EUROC_ADIS16448,
    T_b_c: np.ndarray = EUROC_T_B_C0,
    realism: bool = False,
) -> SequenceData:
    """Scene, trajectory, IMU and ground truth of a sequence (no rendering, no files).

    Args:
        preset: ``textured`` or ``whitewall``.
        duration: length [s]; ``round(duration * 200)`` IMU samples.
        seed: scene, trajectory and noise seed.
        imu_noise: add white noise and random-walk biases.
        noise: the IMU noise model.
        T_b_c: cam0 pose in the body frame.
        realism: a real IMU (:func:`imu_errors_for`): instantaneous samples of the continuous trajectory,
            turn-on biases, rotor vibration (``flight``, ``textured``, ``whitewall``); with ``imu_noise`` only.
            The ground truth is then the continuous trajectory at the sample times.

    Returns:
        The :class:`SequenceData` (``scene`` is the grey scene, ``trajectory`` the smooth camera path).
    """
    _check_args(preset, duration, seed)
    scene = make_scene(seed, preset, rgb=False)
    traj = make_any_trajectory(scene, duration, seed, preset)
    n = int(round(duration * IMU_RATE_HZ))
    if n < 2:
        raise ValueError(f"duration {duration} s gives fewer than 2 IMU samples")
    dt = DT_NS * 1e-9
    t = np.arange(n + 1) * dt
    R_w_b, p_w_b = traj.body_pose(t, T_b_c)
    v_w = traj.body_velocity(t, T_b_c)
    if realism and imu_noise:
        gyro, accel = instantaneous_imu(lambda tt: traj.body_pose(tt, T_b_c), t[:n])
        p = p_w_b
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x1A1]))
        gyro, accel, bg, ba = add_imu_errors(gyro, accel, dt, rng, noise, imu_errors_for(preset))
    else:
        gyro, accel, p = synthesize_imu(R_w_b, v_w, p_w_b[0], dt)
        if imu_noise:
            rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x1A0]))
            gyro, accel, bg, ba = add_imu_noise(gyro, accel, dt, rng, noise)
        else:
            bg = ba = np.zeros((n, 3))
    return SequenceData(
        ts=T0_NS + DT_NS * np.arange(n, dtype=np.int64),
        gyro=gyro,
        accel=accel,
        R_w_b=R_w_b[:n],
        p_w_b=p[:n],
        v_w=v_w[:n],
        bg=bg,
        ba=ba,
        frame_idx=np.arange(0, n, CAM_EVERY),
        window=traj.window,
        scene=scene,
        trajectory=traj,
    )


# --------------------------------------------------------------------------- files
def _yaml_matrix(T: np.ndarray, indent: str = "         ") -> str:
    rows = [", ".join(repr(float(x)) for x in r) for r in T]
    return "[" + (",\n" + indent).join(rows) + "]"


def _cam_yaml(cam: Camera, T_b_c: np.ndarray, rate: int, depth: bool = False) -> str:
    head = "%YAML:1.0\n# General sensor definitions.\n" + (
        "sensor_type: depth\ncomment: ground-truth z-depth of cam0 (same pixel grid), rendered by dit-sim\n"
        if depth
        else "sensor_type: camera\ncomment: VI-Sensor cam0 (MT9M034), rendered by dit-sim\n"
    )
    body = (
        "\n# Sensor extrinsics wrt. the body-frame.\nT_BS:\n  cols: 4\n  rows: 4\n"
        f"  data: {_yaml_matrix(T_b_c)}\n\n# Camera specific definitions.\nrate_hz: {rate}\n"
        f"resolution: [{cam.width}, {cam.height}]\ncamera_model: pinhole\n"
        f"intrinsics: [{cam.fx!r}, {cam.fy!r}, {cam.cx!r}, {cam.cy!r}] #fu, fv, cu, cv\n"
        f"distortion_model: {'equidistant' if cam.is_fisheye else 'radial-tangential'}\n"
        f"distortion_coefficients: [{', '.join(repr(float(d)) for d in cam.dist)}]\n"
    )
    if cam.line_delay_s > 0 and not depth:
        body += f"line_delay_s: {cam.line_delay_s!r}  # rolling shutter: s between rows, the middle row at the stamp\n"
    if depth:
        body += f"depth_scale: {DEPTH_SCALE!r}  # PNG value = depth [m] * depth_scale, 0 = invalid\n"
    return head + body


def _imu_yaml(noise: ImuNoise) -> str:
    return (
        "#Default imu sensor yaml file\nsensor_type: imu\n"
        "comment: VI-Sensor IMU (ADIS16448), simulated by dit-sim\n\n"
        "# Sensor extrinsics wrt. the body-frame.\nT_BS:\n  cols: 4\n  rows: 4\n"
        f"  data: {_yaml_matrix(np.eye(4))}\nrate_hz: {IMU_RATE_HZ}\n\n"
        "# inertial sensor noise model parameters (static)\n"
        f"gyroscope_noise_density: {noise.gyro_noise_density!r}  # [ rad / s / sqrt(Hz) ] (white noise)\n"
        f"gyroscope_random_walk: {noise.gyro_random_walk!r}  # [ rad / s^2 / sqrt(Hz) ] (bias diffusion)\n"
        f"accelerometer_noise_density: {noise.accel_noise_density!r}  # [ m / s^2 / sqrt(Hz) ] (white)\n"
        f"accelerometer_random_walk: {noise.accel_random_walk!r}  # [ m / s^3 / sqrt(Hz) ] (bias diffusion)\n"
    )


def _write_csv(path: Path, header: str, ts: np.ndarray, values: np.ndarray) -> None:
    """int64 timestamps and float64 values (shortest exact round-trip text via %.17g)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    vals = np.asarray(values, dtype=np.float64)
    fmt = ",".join(["%.17g"] * vals.shape[1])
    lines = [header]
    lines += [f"{int(t)}," + (fmt % tuple(row)) for t, row in zip(ts, vals, strict=True)]
    path.write_text("\n".join(lines) + "\n")


def _write_file_list(path: Path, ts: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("#timestamp [ns],filename\n" + "".join(f"{int(t)},{int(t)}.png\n" for t in ts))


# --------------------------------------------------------------------------- rendering (maybe in workers)
_WORKER: dict = {}


def _init_render(
    key: tuple, cam: Camera, noise_sigma: float, cam_dir: str, depth_dir: str, physics: CameraPhysics | None = None
) -> None:
    """Build the scene and renderer of ``key = (seed, preset)`` once per process (unless already there)."""
    cv2.setNumThreads(1)
    if _WORKER.get("key") != (key, cam):
        seed, preset = key
        _WORKER.update(key=(key, cam), renderer=Renderer(make_scene(seed, preset, rgb=False), cam))
    _WORKER.update(noise_sigma=noise_sigma, cam_dir=Path(cam_dir), depth_dir=Path(depth_dir), seed=key[0])
    _WORKER.update(
        physics=physics, vig=None if physics is None else vignetting((cam.height, cam.width), physics.vignetting)
    )


def _render_frame(job: tuple) -> int:
    """Render frame ``k`` (timestamp ``ts``, pose ``T_w_c``), write its image and depth PNGs; returns 1.

    A job with camera physics also holds ``(T_c1_c0 over PHYSICS_DT, exposure [s], gain, illumination)``.
    """
    k, ts = job[:2]
    w = _WORKER
    img, depth = render_job(job)
    d = np.rint(depth.astype(np.float64) * DEPTH_SCALE)
    d[(d > 65535) | ~np.isfinite(d)] = 0  # beyond 13.1 m: invalid
    write_png(w["cam_dir"] / f"{ts}.png", img)
    write_png(w["depth_dir"] / f"{ts}.png", d.astype(np.uint16))
    return 1


def render_job(job: tuple) -> tuple[np.ndarray, np.ndarray]:
    """Image (uint8) and depth (float32 [m]) of one frame job, with the renderer :func:`_init_render` built."""
    k, ts, T_w_c = job[:3]
    w = _WORKER
    rng = np.random.default_rng(np.random.SeedSequence([w["seed"], 0xCA0, int(k)]))
    if len(job) == 3:
        img, depth = w["renderer"].render(T_w_c, rng, w["noise_sigma"])
    else:
        T_c1_c0, exposure_s, gain, illum = job[3:]
        r, phys = w["renderer"], w["physics"]
        rad, depth = r.radiance(T_w_c)
        vel = pixel_velocity(depth, r.camera, (r.rx, r.ry), T_c1_c0, PHYSICS_DT)
        img = expose(rad, vel, exposure_s, gain, illum, phys, w["vig"], rng, phys.readout_s / r.camera.height)
    return img, depth


def run_jobs(jobs: list, init, init_args: tuple, fn, workers: int, progress: bool, desc: str, total: int) -> None:
    """Run ``fn`` over ``jobs`` here (workers <= 1) or in spawned processes; ``fn`` returns the frames it wrote.

    ``init(*init_args)`` prepares each process; the tqdm bar counts frames up to ``total``. A worker process that
    dies (killed, out of memory, or a calling script without a ``__main__`` guard, which a spawned process runs
    again) raises ``RuntimeError`` here: ``multiprocessing.Pool`` would start a new worker for ever instead.
    """
    from concurrent.futures import ProcessPoolExecutor, as_completed
    from concurrent.futures.process import BrokenProcessPool

    bar = tqdm(total=total, desc=desc, unit="frame", disable=not progress, dynamic_ncols=True)
    try:
        if workers <= 1 or len(jobs) < 2:
            init(*init_args)
            for job in jobs:
                bar.update(fn(job))
        else:
            ctx = multiprocessing.get_context("spawn")
            with ProcessPoolExecutor(min(workers, len(jobs)), ctx, initializer=init, initargs=init_args) as ex:
                try:
                    for fut in as_completed([ex.submit(fn, job) for job in jobs]):
                        bar.update(fut.result())
                except BrokenProcessPool as e:
                    raise RuntimeError(
                        f"a {desc} rendering process died ({e}); if a script of yours called this, put its code "
                        'under `if __name__ == "__main__":` (each rendering process imports that script again), '
                        "or pass workers=1"
                    ) from None
                except BaseException:  # a failed job, Ctrl-C, SIGTERM: stop the others now, as Pool's exit did
                    for p in list((getattr(ex, "_processes", None) or {}).values()):
                        p.terminate()
                    ex.shutdown(wait=False, cancel_futures=True)
                    raise
    finally:
        bar.close()


def write_euroc_sequence(
    out: str | Path,
    preset: str = "textured",
    duration: float = 10.0,
    seed: int = 0,
    imu_noise: bool = True,
    progress: bool = True,
    *,
    scale: float = 1.0,
    workers: int = 1,
    noise_sigma: float = 1.0,
    realism: bool | None = None,
    ideal: bool = False,
    camera: str = "pinhole",
) -> Path:
    """Render a sequence and write it in the EuRoC ASL layout (plus ``depth0``).

    Args:
        out: folder to write (it will contain ``mav0`` and ``sim_info.json``); earlier dit-sim output there is
            replaced (a partial one too: ``sim_info.json`` says ``"complete": false`` until the end, when it is
            replaced by the full one, which has no ``complete`` key), anything
            else raises ``FileExistsError``. An interrupted or failed run removes its partial output; every PNG
            is written atomically.
        preset: ``textured`` or ``whitewall`` (needs ``duration >= 24`` s; ``sim_info.json`` gives the
            white-wall window).
        duration: length [s]; ``round(duration * 200)`` IMU / ground-truth samples, one frame per 10.
        seed: same seed, same bytes.
        imu_noise: white noise + bias random walk (EuRoC ADIS16448 densities); else exact IMU and zero biases.
        progress: show a tqdm bar.
        scale: image resolution factor (tests only; 1.0 is EuRoC's 752x480, intrinsics are scaled with it).
        workers: rendering processes (1 = in this process).
        noise_sigma: image noise [grey levels] (without camera physics).
        realism: real sensors: camera physics (:mod:`sim.camera`: exposure, motion blur, auto-exposure with
            sudden light changes, shot / read noise, gamma, vignetting, rolling shutter on hand-held presets, a
            camera-IMU time offset, a calibration error in ``cam0/sensor.yaml``) and a real IMU (instantaneous
            samples, turn-on biases, rotor vibration). None: on (every preset is realistic by default;
            ``realism=false`` gives the earlier synthetic data, ``ideal=true`` exact data).
        ideal: exact data for known-answer tests: no physics, exact IMU, zero biases, no image noise.
        camera: ``pinhole`` (EuRoC's cam0, radial-tangential) or ``fisheye`` (:data:`FISHEYE_CAM0`, equidistant).

    Returns:
        ``out`` as a Path (the folder that contains ``mav0``).
    """
    _check_args(preset, duration, seed)
    check_scale(scale, workers)
    if ideal:
        realism, imu_noise, noise_sigma = False, False, 0.0
    elif realism is None:
        realism = True
    out = Path(out)
    if camera not in CAMERAS:
        raise ValueError(f"camera={camera!r} is not one of {', '.join(CAMERAS)}")
    cam = scaled_camera(scale, CAMERAS[camera])
    data = simulate_sequence(preset, duration, int(seed), imu_noise, realism=bool(realism))
    with sim_output(out, ("mav0", "sim_frames.csv"), "euroc", preset=preset, seed=int(seed)):
        _write_euroc(
            out, data, cam, camera, preset, duration, seed, imu_noise, scale, workers, noise_sigma, realism, ideal,
            progress,
        )  # fmt: skip
    return out


def _write_euroc(
    out, data, cam, camera, preset, duration, seed, imu_noise, scale, workers, noise_sigma, realism, ideal, progress
):
    """The files of :func:`write_euroc_sequence` (``out`` prepared, the simulation done)."""
    mav0 = out / "mav0"
    cam_dir, depth_dir = mav0 / "cam0" / "data", mav0 / "depth0" / "data"
    cam_dir.mkdir(parents=True)
    depth_dir.mkdir(parents=True)
    imu_dir, gt_dir = mav0 / "imu0", mav0 / "state_groundtruth_estimate0"

    cam_rate = IMU_RATE_HZ // CAM_EVERY
    physics = camera_physics_for(preset) if realism else None
    written_cam = cam
    if physics is not None:
        rng_cam = np.random.default_rng(np.random.SeedSequence([int(seed), 0xCA2]))
        written_cam = perturbed_calibration(cam, physics, rng_cam, scale)
        if physics.readout_s > 0:
            written_cam = replace(written_cam, line_delay_s=physics.readout_s / cam.height)
    (mav0 / "cam0" / "sensor.yaml").write_text(_cam_yaml(written_cam, EUROC_T_B_C0, cam_rate))
    (mav0 / "depth0" / "sensor.yaml").write_text(_cam_yaml(cam, EUROC_T_B_C0, cam_rate, depth=True))
    imu_dir.mkdir(parents=True)
    (imu_dir / "sensor.yaml").write_text(_imu_yaml(EUROC_ADIS16448))
    _write_csv(imu_dir / "data.csv", IMU_HEADER, data.ts, np.concatenate([data.gyro, data.accel], 1))
    q = R_to_quat_wxyz(data.R_w_b)
    gt = np.concatenate([data.p_w_b, q, data.v_w, data.bg, data.ba], 1)
    _write_csv(gt_dir / "data.csv", GT_HEADER, data.ts, gt)
    frame_ts = data.ts[data.frame_idx]
    _write_file_list(mav0 / "cam0" / "data.csv", frame_ts)
    _write_file_list(mav0 / "depth0" / "data.csv", frame_ts)

    T_w_c = data.T_w_b(data.frame_idx) @ EUROC_T_B_C0
    jobs = [(int(k), int(ts), T) for k, ts, T in zip(data.frame_idx, frame_ts, T_w_c, strict=True)]
    if physics is not None:
        jobs, exposure_s, gain, illum = physics_jobs(data, physics, duration, scale, rng_cam)
        rows = [
            f"{int(ts)},{float(e)!r},{float(g)!r},{float(li)!r}"
            for ts, e, g, li in zip(frame_ts, exposure_s, gain, illum, strict=True)
        ]
        (out / "sim_frames.csv").write_text("#timestamp [ns],exposure [s],gain,illumination\n" + "\n".join(rows) + "\n")
    if workers <= 1:  # reuse the scene built above instead of building it again
        _WORKER.update(key=((int(seed), preset), cam), renderer=Renderer(data.scene, cam))
    init_args = ((int(seed), preset), cam, float(noise_sigma), str(cam_dir), str(depth_dir))
    if physics is not None:
        init_args = init_args + (physics,)
    run_jobs(
        jobs,
        _init_render,
        init_args,
        _render_frame,
        workers,
        progress,
        f"euroc {preset}",
        len(jobs),
    )
    window = data.window
    info = {
        "generator": GENERATOR,
        "job": "euroc",
        "preset": preset,
        "seed": int(seed),
        "duration_s": float(duration),
        "imu_noise": bool(imu_noise),
        "scale": float(scale),
        "noise_sigma": float(noise_sigma),
        "resolution": [cam.width, cam.height],
        **({"camera": camera} if camera != "pinhole" else {}),
        "frames": int(len(frame_ts)),
        "imu_samples": int(len(data.ts)),
        "t0_ns": int(data.ts[0]),
        "imu_rate_hz": IMU_RATE_HZ,
        "cam_rate_hz": cam_rate,
        "rest_s": float(data.trajectory.t_rest),
        "whitewall_window_s": None if window is None else [float(window[0]), float(window[1])],
        "whitewall_window_ns": None
        if window is None
        else [int(data.ts[0] + round(window[0] * 1e9)), int(data.ts[0] + round(window[1] * 1e9))],
        "room_size_m": [float(x) for x in data.scene.size],
        "boxes": len(data.scene.names),
        "imu_convention": "sample k holds over [t_k, t_k+1); gyro then accel (specific force), body frame",
    }
    if physics is not None or preset in ROOM_PRESETS or ideal:
        info["realism"] = bool(realism)
        info["ideal"] = bool(ideal)
    if physics is not None:
        info["camera_physics"] = asdict(physics)
        info["time_offset_s"] = physics.time_offset_s
        info["render_camera"] = [cam.fx, cam.fy, cam.cx, cam.cy, *cam.dist]
        info["written_camera"] = [written_cam.fx, written_cam.fy, written_cam.cx, written_cam.cy, *written_cam.dist]
        info["imu_errors"] = asdict(imu_errors_for(preset)) if imu_noise else None
        info["frame_settings"] = "sim_frames.csv (exposure, gain, illumination per frame)"
    write_info(out, info)  # the final sim_info.json has no "complete" key: bytes as before
