"""``dit-sim imu`` on a real sequence: how well the fit matches the ground truth, and the runtime's preintegration.

    python benchmarks/bench_imu_completion.py [--source ../shared/data/euroc_MH_05_excerpt] [--window 1.0]

Completes the source with an IMU five times: no noise at all (what remains is the fit and the runtime's
piecewise-constant integration of instantaneous samples, ``ImuStream.segment``); white noise + random walk only;
+ rotor vibration; + a 2 s still period with vibration; ``ideal`` (exact samples, the stated densities in
``sensor.yaml``, so that its NEES can be computed). Then integrates the written IMU as the runtime does
(``ImuStream.segment`` pieces into GTSAM) over consecutive ``--window`` second windows, starting each from the
written ground truth (with its biases), and compares the prediction with the written ground truth at the window's
end. The stated noise is the ``imu0/sensor.yaml`` densities: over T seconds position ``sigma_a sqrt(T^3 / 3)``,
velocity ``sigma_a sqrt(T)``, rotation ``sigma_g sqrt(T)`` (per axis; the 3-D norm is about ``sqrt(3)`` times
that). The NEES of the runtime's ``ImuFactor`` over the true states, with the white-noise densities as stated and
raised x5 (the cap of ``imu.max_noise_scale``), says whether the window's IMU noise model is consistent: 9 on
average if it is, above if the factor is too confident. Prints a table and writes
``benchmarks/results/bench_imu_completion.json``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.common import REPO, write_json


def preintegration_errors(root: Path, window_s: float = 1.0, raises: tuple[float, ...] = (1.0, 5.0)) -> dict:
    """The runtime's preintegration of ``root``'s IMU over consecutive windows against its ground truth."""
    import gtsam

    from runtime.backend.imu import ImuStream, integrate, make_bias, preintegration_params
    from runtime.geometry import inv_T, rotation_angle, to_pose3
    from runtime.io.euroc import read_euroc

    seq = read_euroc(root)
    ts, gt = seq.imu_ts, seq.gt
    if not np.array_equal(gt.ts, ts):
        raise ValueError("the ground truth must share the IMU timestamps")
    imu = ImuStream.from_sequence(seq)
    n = int(round(window_s * seq.imu.rate_hz))
    stated = seq.imu.gyro_noise_density > 0
    params = {r: preintegration_params(seq.imu, None, (r, r)) for r in raises} if stated else {}
    ep, ev, er, nees = [], [], [], {r: [] for r in raises}
    for i in range(0, len(ts) - n, n):
        j = i + n
        bias = make_bias(np.r_[gt.ba[i], gt.bg[i]])
        pieces = imu.segment(int(ts[i]), int(ts[j]))
        pim = gtsam.PreintegratedCombinedMeasurements(gtsam.PreintegrationCombinedParams.MakeSharedU(9.81), bias)
        integrate(pim, *pieces)
        pred = pim.predict(gtsam.NavState(gtsam.Pose3(gt.T_w_b[i]), gt.v_w[i]), bias)
        T = pred.pose().matrix()
        rel_p = inv_T(gt.T_w_b[i]) @ T
        rel_g = inv_T(gt.T_w_b[i]) @ gt.T_w_b[j]
        ep.append(np.linalg.norm(rel_p[:3, 3] - rel_g[:3, 3]))
        er.append(np.degrees(rotation_angle(rel_p[:3, :3].T @ rel_g[:3, :3])))
        ev.append(np.linalg.norm(pred.velocity() - gt.v_w[j]))
        if not stated:
            continue
        vals = gtsam.Values()  # the true states at the window's ends
        vals.insert(0, to_pose3(gt.T_w_b[i]))
        vals.insert(1, gt.v_w[i])
        vals.insert(2, to_pose3(gt.T_w_b[j]))
        vals.insert(3, gt.v_w[j])
        vals.insert(4, bias)
        for r, p in params.items():
            pim_r = gtsam.PreintegratedImuMeasurements(p, bias)
            integrate(pim_r, *pieces)
            e = gtsam.ImuFactor(0, 1, 2, 3, 4, pim_r).whitenedError(vals)
            nees[r].append(float(e @ e))
    ip = seq.imu
    T = window_s
    return {
        "windows": len(ep),
        "window_s": window_s,
        "pos_err_median_mm": float(np.median(ep) * 1e3),
        "pos_err_p95_mm": float(np.percentile(ep, 95) * 1e3),
        "vel_err_median_mm_s": float(np.median(ev) * 1e3),
        "rot_err_median_deg": float(np.median(er)),
        "rot_err_p95_deg": float(np.percentile(er, 95)),
        "stated_pos_sigma_mm": float(ip.accel_noise_density * np.sqrt(T**3 / 3) * 1e3),
        "stated_vel_sigma_mm_s": float(ip.accel_noise_density * np.sqrt(T) * 1e3),
        "stated_rot_sigma_deg": float(np.degrees(ip.gyro_noise_density * np.sqrt(T))),
        "nees_mean": {f"x{r:g}": float(np.mean(v)) for r, v in nees.items() if v},
    }


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--source", default=str(REPO.parent / "shared" / "data" / "euroc_MH_05_excerpt"))
    ap.add_argument("--window", type=float, default=1.0)
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "bench_imu_completion.json"))
    args = ap.parse_args(argv)

    from sim.complete import complete_imu, steps_line
    from sim.imu import FLIGHT_IMU, ImuNoise

    src = Path(args.source)
    if not (src / "mav0" / "state_groundtruth_estimate0" / "data.csv").is_file():
        sys.exit(f"bench_imu_completion: no EuRoC-layout sequence with ground truth at {src}")
    rows, infos = {}, {}
    with tempfile.TemporaryDirectory() as d:
        for name, kw in (
            ("noiseless", dict(errors=None, noise=ImuNoise(0.0, 0.0, 0.0, 0.0))),
            ("noise_only", dict(errors=None)),
            ("vibration", dict(errors=FLIGHT_IMU)),
            ("vibration_still2s", dict(errors=FLIGHT_IMU, still=2.0)),
            ("ideal", dict(ideal=True)),
        ):
            out = Path(d) / name
            infos[name] = info = complete_imu(src, out, **kw)
            rows[name] = {
                "fit": info["fit"],
                "preintegration": preintegration_errors(out, args.window),
                "frames": info["frames"],
                "imu_samples": info["imu_samples"],
                "ground_truth_steps": info["ground_truth_steps"],
                "max_accel_mps2": info["max_accel_mps2"],
            }
    fit = rows["noise_only"]["fit"]
    print(f"dit-sim imu on {src}")
    print(
        f"fit vs ground truth ({fit['samples']} samples): position median {fit['pos_err_median_mm']:.3f} mm "
        f"(p95 {fit['pos_err_p95_mm']:.3f}, max {fit['pos_err_max_mm']:.3f}), rotation median "
        f"{fit['rot_err_median_deg']:.4f} deg (p95 {fit['rot_err_p95_deg']:.4f}), velocity median "
        f"{fit['vel_err_median_mm_s']:.2f} mm/s"
    )
    print(steps_line(infos["noise_only"]))
    print("largest accelerometer sample: " + ", ".join(f"{k} {r['max_accel_mps2']:.1f} m/s^2" for k, r in rows.items()))
    print(f"GTSAM preintegration over {args.window:g} s windows vs the written ground truth (3-D error norms):")
    print(
        f"{'variant':20s} {'windows':>7s} {'pos med':>9s} {'pos p95':>9s} {'vel med':>9s} {'rot med':>9s} "
        f"{'rot p95':>9s} {'NEES x1':>9s} {'NEES x5':>9s}"
    )
    for name, r in rows.items():
        p = r["preintegration"]
        print(
            f"{name:20s} {p['windows']:7d} {p['pos_err_median_mm']:7.2f}mm {p['pos_err_p95_mm']:7.2f}mm "
            f"{p['vel_err_median_mm_s']:5.1f}mm/s {p['rot_err_median_deg']:7.4f}d {p['rot_err_p95_deg']:7.4f}d "
            + " ".join(f"{p['nees_mean'].get(k, float('nan')):9.2f}" for k in ("x1", "x5"))
        )
    p = rows["noise_only"]["preintegration"]
    print(
        f"stated noise per axis over {args.window:g} s: position {p['stated_pos_sigma_mm']:.2f} mm, velocity "
        f"{p['stated_vel_sigma_mm_s']:.2f} mm/s, rotation {p['stated_rot_sigma_deg']:.4f} deg "
        "(a 3-D norm's median is about 1.5 sigma)"
    )
    res = {"source": str(src), "window_s": args.window, "variants": rows}
    write_json(args.out, res)
    print(f"wrote {args.out}")
    return res


if __name__ == "__main__":
    main()
