"""Synthetic RGB + metric depth frames in the NYU-Depth-v2 h5 layout of sparse-to-dense.

Layout written under ``out``::

    out/sim_info.json
    out/train/<scene>/<frame>.h5     rgb uint8 (3, 480, 640) channels-first, depth float32 (480, 640) [m]
    out/val/<scene>/<frame>.h5

Each scene is a procedural room (:mod:`sim.scenes`, RGB textures) seen from random viewpoints inside its free
region through a Kinect-like pinhole camera (:data:`KINECT_RGB`, no distortion); depth is the z-depth
registered to the RGB pixels. Train and val scenes are different rooms: their seeds come from disjoint
seed-sequence branches and their names differ (``sim_train_0000`` ... vs ``sim_val_0000`` ...).
"""

from __future__ import annotations

import math
from pathlib import Path

import h5py
import numpy as np

from runtime.geometry import Camera, make_T
from runtime.outputs import atomic_write
from sim.euroc import run_jobs
from sim.output import GENERATOR, sim_output, write_info
from sim.render import Renderer
from sim.scenes import make_scene
from sim.trajectory import euler_to_R_w_c

__all__ = ["KINECT_RGB", "SPLITS", "scene_seeds", "random_viewpoints", "write_nyu_dataset"]

#: Kinect-like RGB camera of NYU-Depth v2 (no distortion), 640x480.
KINECT_RGB = Camera(518.86, 519.47, 325.58, 253.74, 640, 480)
SPLITS = ("train", "val")


def scene_seeds(seed: int, split: str, n_scenes: int) -> list[int]:
    """64-bit scene seeds of a split from the seed-sequence branch ``(seed, split)``: disjoint splits."""
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r}; expected one of {SPLITS}")
    ss = np.random.SeedSequence([int(seed), 0x4E59, SPLITS.index(split)])
    return [int(x) for x in ss.generate_state(n_scenes, np.uint64)] if n_scenes else []


def random_viewpoints(scene, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` camera poses ``T_w_c`` (n, 4, 4) inside the scene's free region, looking roughly horizontally."""
    p = scene.free_lo + rng.uniform(0.0, 1.0, (n, 3)) * (scene.free_hi - scene.free_lo)
    yaw = rng.uniform(-np.pi, np.pi, n)
    pitch = np.clip(rng.normal(0.05, 0.15, n), -0.4, 0.5)
    roll = np.clip(rng.normal(0.0, 0.05, n), -0.15, 0.15)
    R = euler_to_R_w_c(yaw, pitch, roll)
    return np.stack([make_T(R[i], p[i]) for i in range(n)])


def write_frame(path: Path, img: np.ndarray, depth: np.ndarray, compression: str | None) -> Path:
    """One frame as h5 (``rgb`` channels-first uint8, ``depth`` float32 [m]), written atomically: never half a file."""

    def write(tmp: Path) -> None:
        with h5py.File(tmp, "w") as f:
            f.create_dataset("rgb", data=np.ascontiguousarray(img.transpose(2, 0, 1)), compression=compression)
            f.create_dataset("depth", data=depth.astype(np.float32), compression=compression)

    return atomic_write(path, write)


def _render_scene(job: tuple) -> int:
    """Build one scene, render its frames and write them as h5 files; returns the number of frames."""
    import cv2

    cv2.setNumThreads(1)
    if len(job) == 6 and job[5]:
        return _render_scene_realistic(job)
    out_dir, scene_seed, n_frames, noise_sigma, compression = job[:5]
    scene = make_scene(scene_seed, "textured", rgb=True)
    renderer = Renderer(scene, KINECT_RGB)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    for j in range(n_frames):  # frame j depends only on (scene seed, j), not on how many frames are written
        rng = np.random.default_rng(np.random.SeedSequence([scene_seed, 0x5EE, j]))
        T_w_c = random_viewpoints(scene, 1, rng)[0]
        img, depth = renderer.render(T_w_c, rng, noise_sigma, exposure=float(rng.uniform(0.85, 1.15)))
        write_frame(out_dir / f"{j:05d}.h5", img, depth, compression)
    return n_frames


def _render_scene_realistic(job: tuple) -> int:
    """A realistic room (:mod:`sim.rooms`) seen along a hand-held trajectory, through the camera physics."""
    from sim.camera import auto_exposure, expose, illumination, pixel_velocity, vignetting
    from sim.euroc import camera_physics_for
    from sim.motion import make_motion_trajectory

    out_dir, scene_seed, n_frames, _, compression = job[:5]
    preset = ("handheld", "tabletop")[scene_seed % 2]
    scene = make_scene(scene_seed, preset, rgb=True)
    physics = camera_physics_for(preset)
    traj = make_motion_trajectory(scene, 120.0, scene_seed % (2**32), preset)
    renderer = Renderer(scene, KINECT_RGB)
    preview = Renderer(
        scene,
        Camera(
            KINECT_RGB.fx / 8,
            KINECT_RGB.fy / 8,
            KINECT_RGB.cx / 8,
            KINECT_RGB.cy / 8,
            KINECT_RGB.width // 8,
            KINECT_RGB.height // 8,
        ),
    )
    vig = vignetting((KINECT_RGB.height, KINECT_RGB.width), physics.vignetting)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    for j in range(n_frames):
        rng = np.random.default_rng(np.random.SeedSequence([scene_seed, 0x5EF, j]))
        t = float(rng.uniform(0.0, 120.0))
        T_w_c, T_w_c1 = traj.camera_T(np.array([t, t + 1e-3]))
        illum = illumination(np.array([0.0]), 1.0, physics, rng)
        rad_lo = preview.radiance(T_w_c)[0].mean(-1)[None]
        exposure_s, gain = auto_exposure(rad_lo, illum, physics)  # settled on this view
        rad, depth = renderer.radiance(T_w_c)
        vel = pixel_velocity(depth, KINECT_RGB, (renderer.rx, renderer.ry), np.linalg.inv(T_w_c1) @ T_w_c, 1e-3)
        img = expose(
            rad,
            vel,
            float(exposure_s[0]),
            float(gain[0]),
            float(illum[0]),
            physics,
            vig,
            rng,
            physics.readout_s / KINECT_RGB.height,
        )
        write_frame(out_dir / f"{j:05d}.h5", img, depth, compression)
    return n_frames


def _noop() -> None:
    pass


def write_nyu_dataset(
    out: str | Path,
    n_train: int = 40,
    n_val: int = 10,
    seed: int = 0,
    progress: bool = True,
    *,
    frames_per_scene: int = 10,
    workers: int = 1,
    noise_sigma: float = 1.5,
    compression: str | None = "gzip",
    realism: bool = False,
) -> Path:
    """Render ``n_train`` + ``n_val`` RGB-D frames and write them in the NYU h5 layout.

    Args:
        out: output folder (gets ``train/``, ``val/`` and ``sim_info.json``); earlier dit-sim output there is
            replaced (a partial one too), anything else raises ``FileExistsError``. Each h5 file is written
            atomically; an interrupted or failed run removes its partial output (:func:`sim.output.sim_output`).
        n_train, n_val: number of frames per split (>= 0); ``ceil(n / frames_per_scene)`` scenes each.
        seed: same seed, same data.
        progress: show a tqdm bar.
        frames_per_scene: viewpoints per room.
        workers: rendering processes (1 = in this process).
        noise_sigma: RGB noise [levels of 255].
        realism: realistic rooms (:mod:`sim.rooms`, ``handheld`` and ``tabletop`` alternating), views along a
            hand-held trajectory, and the camera physics of :mod:`sim.camera` (exposure, motion blur, rolling
            shutter, noise, gamma, vignetting); ``noise_sigma`` is then unused. Off: the data stay as they were.
        compression: h5py dataset compression (``"gzip"``, ``"lzf"`` or None; gzip is a standard HDF5 filter,
            about 25 % smaller than raw here); h5py reads any of them transparently.

    Returns:
        ``out`` as a Path.
    """
    for name, v in (("n_train", n_train), ("n_val", n_val), ("seed", seed)):
        if int(v) != v or v < 0:
            raise ValueError(f"{name} must be a non-negative integer, got {v}")
    if int(frames_per_scene) != frames_per_scene or frames_per_scene < 1:
        raise ValueError(f"frames_per_scene must be a positive integer, got {frames_per_scene}")
    if n_train + n_val == 0:
        raise ValueError("n_train + n_val must be positive")
    out = Path(out)
    jobs, scenes = [], {}
    for split, n in (("train", int(n_train)), ("val", int(n_val))):
        n_scenes = math.ceil(n / frames_per_scene)
        names = []
        for i, s in enumerate(scene_seeds(seed, split, n_scenes)):
            name = f"sim_{split}_{i:04d}"
            count = min(frames_per_scene, n - i * frames_per_scene)
            job = (str(out / split / name), s, count, float(noise_sigma), compression)
            jobs.append(job + (True,) if realism else job)
            names.append(name)
        scenes[split] = names
    info = {
        "generator": GENERATOR,
        "job": "nyu",
        "seed": int(seed),
        "n_train": int(n_train),
        "n_val": int(n_val),
        "frames_per_scene": int(frames_per_scene),
        **({"realism": True} if realism else {}),
        "camera": {
            "fx": KINECT_RGB.fx,
            "fy": KINECT_RGB.fy,
            "cx": KINECT_RGB.cx,
            "cy": KINECT_RGB.cy,
            "width": KINECT_RGB.width,
            "height": KINECT_RGB.height,
        },
        "scenes": scenes,
    }
    with sim_output(out, SPLITS, "nyu", seed=int(seed), n_train=int(n_train), n_val=int(n_val)):
        for split in SPLITS:
            (out / split).mkdir(parents=True, exist_ok=True)
        run_jobs(jobs, _noop, (), _render_scene, workers, progress, "nyu", int(n_train) + int(n_val))  # job per scene
        write_info(out, info)
    return out
