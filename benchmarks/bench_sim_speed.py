"""Rendering time per frame with and without camera physics, measured in one process (ratio on the same frames).

    python benchmarks/bench_sim_speed.py [--presets textured flight] [--frames 24] [--repeats 3]

"Today" is :meth:`sim.render.Renderer.render` (what ``textured`` / ``whitewall`` write by default); "realism" is
``radiance`` + per-pixel flow + :func:`sim.camera.expose` at an 8 ms exposure (motion blur and, for hand-held
presets, a rolling shutter), at 752x480. The two alternate frame by frame; the median of the per-frame ratios
is reported. Prints a table and writes ``benchmarks/results/bench_sim_speed.json``.
"""

from __future__ import annotations

import argparse
import platform
import time

import numpy as np

from benchmarks.common import REPO, write_json


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--presets", nargs="+", default=["textured", "flight"])
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "bench_sim_speed.json"))
    args = ap.parse_args(argv)
    import cv2

    from sim.camera import expose, pixel_velocity, vignetting
    from sim.euroc import EUROC_CAM0, EUROC_T_B_C0, PHYSICS_DT, camera_physics_for, simulate_sequence
    from sim.render import Renderer

    cv2.setNumThreads(1)
    res = {"cpu": platform.processor(), "presets": {}}
    print(f"{'preset':10s} {'today [ms]':>11s} {'realism [ms]':>13s} {'ratio':>6s}")
    for preset in args.presets:
        d = simulate_sequence(preset, 30.0, 0, True, realism=preset in ("flight", "handheld", "tabletop"))
        r = Renderer(d.scene, EUROC_CAM0)
        idx = d.frame_idx[np.linspace(60, len(d.frame_idx) - 1, args.frames).astype(int)]
        T = d.T_w_b(idx) @ EUROC_T_B_C0
        T1 = d.trajectory.camera_T(idx * 0.005 + PHYSICS_DT)
        phys = camera_physics_for(preset)
        vig = vignetting((EUROC_CAM0.height, EUROC_CAM0.width), phys.vignetting)
        rng = np.random.default_rng(0)
        ta, tb = [], []
        for _ in range(args.repeats):
            for Tk, T1k in zip(T, T1, strict=True):
                t0 = time.perf_counter()
                r.render(Tk, rng, 1.0)
                ta.append(time.perf_counter() - t0)
                t0 = time.perf_counter()
                rad, depth = r.radiance(Tk)
                vel = pixel_velocity(depth, r.camera, (r.rx, r.ry), np.linalg.inv(T1k) @ Tk, PHYSICS_DT)
                expose(rad, vel, 0.008, 1.0, 1.0, phys, vig, rng, phys.readout_s / EUROC_CAM0.height)
                tb.append(time.perf_counter() - t0)
        ratio = float(np.median(np.asarray(tb) / np.asarray(ta)))
        res["presets"][preset] = {
            "today_ms": float(np.median(ta) * 1e3),
            "realism_ms": float(np.median(tb) * 1e3),
            "ratio_median": ratio,
            "frames": len(ta),
        }
        print(f"{preset:10s} {np.median(ta) * 1e3:11.1f} {np.median(tb) * 1e3:13.1f} {ratio:6.2f}")
    write_json(args.out, res)
    print(f"wrote {args.out}")
    return res


if __name__ == "__main__":
    main()
