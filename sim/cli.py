"""``dit-sim``: render synthetic data in the real formats.

    dit-sim euroc out=DIR preset=textured|whitewall|flight|handheld|tabletop duration=SECONDS seed=S
        [imu_noise=true|false] [realism=true|false] [ideal=true] [camera=pinhole|fisheye] [format=asl|bag|ros2|mcap]
    dit-sim nyu out=DIR n_train=N n_val=M seed=S [realism=true]
    dit-sim imu source=DIR out=DIR [still=SECONDS] [vibration=true|false] [ideal=true] [imu_sensor=PATH] seed=S

The first bare word selects the job (it is turned into the override ``job=...``); everything else is a Hydra
override of ``conf/sim.yaml`` (``--cfg job`` prints the composed config). Expected failures print one line and
exit with status 2 (``--debug`` or ``HYDRA_FULL_ERROR=1`` adds the traceback). Every job owns its output folder
the same way (:mod:`sim.output`): Ctrl-C or SIGTERM removes the partial output and exits with status 130, and a
rerun into a folder that an earlier run left (complete, or partial after a kill) replaces it and says which.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import hydra
from omegaconf import DictConfig

__all__ = ["JOBS", "main"]

JOBS = ("euroc", "nyu", "imu")
_DEBUG = {"on": False}


def _sequence_kwargs(cfg: DictConfig) -> dict:
    """The rendering settings of ``dit-sim euroc`` (ASL folder and bags alike)."""
    return dict(
        camera=str(cfg.get("camera", "pinhole")),
        preset=str(cfg.preset),
        duration=float(cfg.duration),
        seed=int(cfg.seed),
        imu_noise=bool(cfg.imu_noise),
        progress=bool(cfg.progress),
        scale=float(cfg.scale),
        workers=int(cfg.workers),
        noise_sigma=float(cfg.image_noise),
        realism=None if cfg.realism is None else bool(cfg.realism),
        ideal=bool(cfg.ideal),
    )


def _out(cfg: DictConfig) -> str:
    """The output folder of the job: ``out=`` or the job's default."""
    if cfg.out is not None:
        return str(cfg.out)
    if cfg.job == "euroc":
        return f"data/sim/euroc_{cfg.preset}_s{cfg.seed}"
    if cfg.job == "nyu":
        return f"data/sim/nyu_s{cfg.seed}"
    if cfg.source is None:
        raise ValueError("dit-sim imu needs source=DIR (an EuRoC-layout sequence with images and ground truth)")
    return f"data/sim/imu_{Path(str(cfg.source)).resolve().name}"


def _euroc(cfg: DictConfig) -> str:
    from sim.euroc import write_euroc_sequence

    out = _out(cfg)
    fmt = str(cfg.get("format", "asl"))
    if fmt != "asl":
        return _euroc_bag(cfg, out, fmt)
    root = write_euroc_sequence(out, **_sequence_kwargs(cfg))
    info = json.loads((root / "sim_info.json").read_text())
    w, h = info["resolution"]
    mav0 = root / "mav0"
    lines = [
        f"  {mav0 / 'cam0'}: {info['frames']} frames {w}x{h} grey @ {info['cam_rate_hz']} Hz "
        "(data.csv, data/, sensor.yaml)",
        f"  {mav0 / 'depth0'}: {info['frames']} depth PNGs (uint16, metres * 5000, 0 = invalid)",
        f"  {mav0 / 'imu0'}: {info['imu_samples']} samples @ {info['imu_rate_hz']} Hz, imu_noise={info['imu_noise']}",
        f"  {mav0 / 'state_groundtruth_estimate0'}: {info['imu_samples']} states (p, q wxyz, v, biases)",
        f"  {root / 'sim_info.json'}: preset={info['preset']} seed={info['seed']} rest={info['rest_s']:.3g} s",
    ]
    if info.get("realism") is not None:
        lines.append(
            f"  realism={info['realism']} ideal={info['ideal']}"
            + (" (camera physics: sim_frames.csv, sim_info.json camera_physics)" if info["realism"] else "")
        )
    if info["whitewall_window_s"] is not None:
        a, b = info["whitewall_window_s"]
        lines.append(f"  white-wall window: {a:.1f} s .. {b:.1f} s after the first frame")
    return f"dit-sim euroc: wrote {root}\n" + "\n".join(lines)


def _euroc_bag(cfg: DictConfig, out: str, fmt: str) -> str:
    from sim.bag import write_bag_sequence

    bag = write_bag_sequence(out, fmt, **_sequence_kwargs(cfg))
    info = json.loads((Path(out) / "sim_info.json").read_text())
    return (
        f"dit-sim euroc: wrote {bag} ({fmt}): /cam0/image_raw {info['frames']} frames, /imu0 "
        f"{info['imu_samples']} samples, /ground_truth/pose\n  calibration: {Path(out) / 'calib'} "
        f"(run: dit-slam sequence={bag} calib={Path(out) / 'calib'})"
    )


def _nyu(cfg: DictConfig) -> str:
    from sim.nyu import write_nyu_dataset

    out = _out(cfg)
    root = write_nyu_dataset(
        out,
        n_train=int(cfg.n_train),
        n_val=int(cfg.n_val),
        seed=int(cfg.seed),
        progress=bool(cfg.progress),
        frames_per_scene=int(cfg.frames_per_scene),
        workers=int(cfg.workers),
        realism=bool(cfg.realism) if cfg.realism is not None else False,
    )
    info = json.loads((root / "sim_info.json").read_text())
    lines = [
        f"  {root / split}: {info['n_' + split]} frames in {len(info['scenes'][split])} scenes "
        "(<scene>/<frame>.h5: rgb uint8 (3,480,640), depth float32 (480,640) m)"
        for split in ("train", "val")
    ]
    return f"dit-sim nyu: wrote {root}\n" + "\n".join(lines)


def _imu(cfg: DictConfig) -> str:
    from sim.complete import complete_imu, steps_line
    from sim.imu import FLIGHT_IMU, ImuNoise

    out = _out(cfg)
    noise = None
    if cfg.imu_sensor is not None:
        from runtime.io.euroc import read_imu_yaml

        ip = read_imu_yaml(cfg.imu_sensor)
        noise = ImuNoise(ip.gyro_noise_density, ip.gyro_random_walk, ip.accel_noise_density, ip.accel_random_walk)
    info = complete_imu(
        cfg.source,
        out,
        seed=int(cfg.seed),
        noise=noise,
        errors=FLIGHT_IMU if bool(cfg.vibration) else None,
        still=float(cfg.still),
        ramp=float(cfg.ramp),
        ideal=bool(cfg.ideal),
    )
    f = info["fit"]
    mav0 = Path(out) / "mav0"
    return (
        f"dit-sim imu: wrote {out}\n"
        f"  {mav0 / 'cam0'}: {info['frames']} frames linked from {info['source']} "
        f"({info['repeated_first_frames']} repeats of the first image, still {info['still_s']:g} s, "
        f"ramp {info['ramp_s']:g} s)\n"
        f"  {mav0 / 'imu0'}: {info['imu_samples']} samples @ {info['imu_rate_hz']} Hz, vibration={info['vibration']}"
        f"{', ideal (exact samples, zero biases)' if info['ideal'] else ''}\n"
        f"  {mav0 / 'state_groundtruth_estimate0'}: the fitted trajectory at the IMU timestamps\n"
        f"  fit vs the source ground truth: position median {f['pos_err_median_mm']:.3f} mm "
        f"(p95 {f['pos_err_p95_mm']:.3f}), rotation median {f['rot_err_median_deg']:.4f} deg "
        f"(p95 {f['rot_err_p95_deg']:.4f})\n"
        f"  {steps_line(info)}; largest accelerometer sample {info['max_accel_mps2']:.1f} m/s^2"
    )


@hydra.main(version_base="1.3", config_path="pkg://conf", config_name="sim")
def _run(cfg: DictConfig) -> None:
    if cfg.job not in JOBS:
        sys.exit(f"dit-sim: unknown job {cfg.job!r}; expected one of {', '.join(JOBS)} (e.g. `dit-sim euroc`)")
    from runtime.errors import EXPECTED, report
    from sim.output import earlier

    t0 = time.perf_counter()
    try:
        before = earlier(_out(cfg))
        summary = {"euroc": _euroc, "nyu": _nyu, "imu": _imu}[cfg.job](cfg)
    except EXPECTED as e:  # bad settings, a foreign or unwritable output folder: say so, no traceback
        sys.exit(report(f"dit-sim {cfg.job}", e, _DEBUG["on"]))
    except KeyboardInterrupt:
        print(f"dit-sim {cfg.job}: interrupted; the partial output was removed (rerun to write it)", file=sys.stderr)
        sys.exit(130)
    if before == "partial":
        summary += "\n  replaced the partial output of an unfinished earlier run (its sim_info.json: complete=false)"
    elif before == "complete":
        summary += "\n  replaced the earlier dit-sim output in this folder"
    print(summary)
    print(f"  took {time.perf_counter() - t0:.1f} s")


def _sigterm(signum, frame) -> None:
    raise KeyboardInterrupt("SIGTERM")


def main(argv: list[str] | None = None) -> None:
    """Console entry point; ``argv`` (without the program name) defaults to ``sys.argv[1:]``."""
    import signal

    from runtime.errors import split_debug

    args, _DEBUG["on"] = split_debug(list(sys.argv[1:] if argv is None else argv))
    signal.signal(signal.SIGTERM, _sigterm)  # clean up as on Ctrl-C
    signal.signal(signal.SIGINT, signal.default_int_handler)  # also when started with SIGINT ignored (a background job)
    if args and args[0] in JOBS:
        args[0] = f"job={args[0]}"
    elif args and "=" not in args[0] and not args[0].startswith("-"):
        sys.exit(f"dit-sim: unknown job {args[0]!r}; usage: dit-sim {{{'|'.join(JOBS)}}} [key=value ...]")
    saved = sys.argv
    sys.argv = [Path(saved[0]).name if saved else "dit-sim", *args]
    try:
        _run()
    finally:
        sys.argv = saved


if __name__ == "__main__":
    main()
