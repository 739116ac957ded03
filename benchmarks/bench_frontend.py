"""The visual front end alone on real and synthetic imagery: tracks, lifetimes, spread, real pixel error, time.

    python benchmarks/bench_frontend.py [--real ../shared/data/euroc_MH_05_excerpt] [--synthetic DIR]
        [--max-features 180,300,400,600] [--frames N] [--out benchmarks/results/frontend.json]

No initialisation and no back end: the :class:`runtime.frontend.tracking.FeatureTracker` runs over every frame with
the ground-truth body rotation between consecutive frames as its KLT prediction (what the gyro gives the system).
New corners are detected as in the system: whenever fewer than ``--redetect`` x ``max_features`` tracks are left,
and at every ``--kf-every``-th frame (a keyframe's detection). Per frame it records the tracks kept, the new
detections, the fraction of the cells of a fixed 8 x 6 grid that hold a track (spatial spread) and the time of
``track`` + ``replenish`` (image reading excluded; wall time and the thread's CPU time, which a loaded machine
disturbs less; OpenCV runs on one thread). Track lifetimes are counted in frames.

Real pixel error: every track that lives ``--min-views`` frames or more is triangulated from all its observations
with the ground-truth camera poses (``T_w_b`` of the ground truth at the frame time @ ``T_b_c``; DLT, then
Gauss-Newton on the reprojection error), and its reprojection residuals [px, undistorted, fx] are collected; only
tracks with >= ``--min-parallax`` degrees of parallax count. The residuals hold the tracker's noise, the
calibration error and the ground truth's own error: the noise a chi-square test must expect. The sigma is robust
(1.4826 MAD per component, corrected for the 3 parameters fitted per track). Also measured: the frame-to-frame
epipolar distance of tracks under the ground-truth relative pose (what the RANSAC test sees) and the KLT
forward-backward error of the tracks kept.

Choice of ``max_features`` (rule written before measuring): the smallest cap whose tracks alive for >= 10 frames
(median per frame on the real sequence) reach 90 % of the largest cap's, provided that the front end takes
<= 10 ms per frame (a fifth of the 50 ms a frame may take at 20 frames/s); the full system is then checked at
>= 20 frames/s with ``dit-slam``.

The real sequence is completed with an IMU by ``dit-sim imu`` into a cache folder if it has no ``imu0`` (only its
image list and calibration are used; the ground truth is the source's own ``state_groundtruth_estimate0``). The
synthetic sequence is ``dit-sim euroc preset=flight`` (realistic sensors), rendered into the cache when
``--synthetic`` is not given. Prints a table and writes ``benchmarks/results/frontend.json``.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import asdict, fields, replace
from pathlib import Path

import numpy as np

from benchmarks.common import REPO, cache_dir, markdown_table, run_provenance, slam_machine, write_json

GRID = (8, 6)  # cells (cols, rows) of the spread measure, fixed so that settings compare


def load_real(src: Path):
    """``(sequence, ground truth)`` of a real EuRoC-layout folder (completed with an IMU in the cache if needed)."""
    from runtime.io.euroc import read_euroc, read_groundtruth

    mav = src / "mav0" if (src / "mav0").is_dir() else src
    root = src
    if not (mav / "imu0").is_dir():
        from sim.complete import complete_imu

        root = cache_dir() / "bench-frontend" / f"{src.resolve().name}_imu"
        if not (root / "mav0" / "imu0" / "data.csv").is_file():
            complete_imu(src, root, still=0.0)
    seq = read_euroc(root)
    gt = read_groundtruth(mav / "state_groundtruth_estimate0" / "data.csv")
    return seq, gt


def load_synthetic(path: str | None, duration: float, seed: int):
    from runtime.io.euroc import read_euroc

    if path is None:
        from sim.cache import cached_sequence

        path = cached_sequence("flight", duration, seed, True, cache_dir() / "bench-frontend", progress=False)
    seq = read_euroc(path)
    return seq, seq.gt


def run_tracker(seq, gt, feat_cfg, trk_cfg, n_frames: int, kf_every: int, redetect: float) -> dict:
    """Track over the sequence; per-frame figures and every track's observations."""
    from runtime.frontend.tracking import FeatureTracker

    tr = FeatureTracker(seq.camera, seq.T_b_c, feat_cfg, trk_cfg)
    ts_all = seq.frame_ts[:n_frames]
    R_w_b = gt.pose_at(ts_all)[:, :3, :3]
    per = {k: [] for k in ("tracks", "kept", "new", "spread", "ms", "cpu_ms", "fb_med")}
    obs: dict[int, list] = {}  # id -> [(frame, xn)]
    fb_all = []
    lost = dict.fromkeys(("klt_failed", "fb_rejected", "border", "ransac_rejected"), 0)
    W, H = seq.camera.width, seq.camera.height
    for i, ts in enumerate(ts_all):
        img = seq.image(i)
        R = None if i == 0 else R_w_b[i - 1].T @ R_w_b[i]
        t0, c0 = time.perf_counter(), time.thread_time()
        f = tr.track(int(ts), img, R)
        kept = f.ids.size
        if i % kf_every == 0 or kept < redetect * feat_cfg.max_features:
            f = tr.replenish(int(ts), img)
        ms = (time.perf_counter() - t0) * 1e3
        per["cpu_ms"].append((time.thread_time() - c0) * 1e3)
        st = getattr(tr, "last_stats", {}) if i else {}
        for k in ("klt_failed", "fb_rejected", "border", "ransac_rejected"):
            lost[k] += int(st.get(k, 0))
        fb = st.get("fb_px_kept")
        if fb is not None and fb.size:
            fb_all.append(fb)
        cx = np.clip((f.uv[:, 0] * GRID[0] / W).astype(int), 0, GRID[0] - 1)
        cy = np.clip((f.uv[:, 1] * GRID[1] / H).astype(int), 0, GRID[1] - 1)
        per["tracks"].append(int(f.ids.size))
        per["kept"].append(int(kept) if i else 0)
        per["new"].append(int(f.ids.size - kept))
        per["spread"].append(float(np.unique(cy * GRID[0] + cx).size / (GRID[0] * GRID[1])))
        per["ms"].append(ms)
        per["fb_med"].append(float(np.median(fb)) if fb is not None and fb.size else 0.0)
        for j, x in zip(f.ids.tolist(), f.xn, strict=True):
            obs.setdefault(j, []).append((i, x))
    fb = np.concatenate(fb_all) if fb_all else np.zeros(0)
    return {"per_frame": per, "obs": obs, "ts": ts_all, "fb": fb, "lost_by_cause": lost}


def _refine_points(X, idx, R_c_w, t_c, xn, iters: int = 5):
    """Gauss-Newton on the reprojection error of points X (M, 3); observations flat (idx into X)."""
    M = X.shape[0]
    for _ in range(iters):
        p = np.einsum("nij,nj->ni", R_c_w, X[idx]) + t_c
        z = np.maximum(p[:, 2], 1e-6)
        r = p[:, :2] / z[:, None] - xn  # (N, 2)
        J = np.zeros((p.shape[0], 2, 3))  # d(proj)/d(p) @ R
        J[:, 0, 0] = 1 / z
        J[:, 0, 2] = -p[:, 0] / z**2
        J[:, 1, 1] = 1 / z
        J[:, 1, 2] = -p[:, 1] / z**2
        J = J @ R_c_w
        A = np.zeros((M, 3, 3))
        b = np.zeros((M, 3))
        np.add.at(A, idx, np.einsum("nki,nkj->nij", J, J))
        np.add.at(b, idx, np.einsum("nki,nk->ni", J, r))
        A += np.eye(3) * 1e-12
        X = X - np.linalg.solve(A, b[..., None])[..., 0]
    p = np.einsum("nij,nj->ni", R_c_w, X[idx]) + t_c
    return X, p[:, :2] / np.maximum(p[:, 2:3], 1e-6) - xn, p[:, 2]


def _residual_stats(r: np.ndarray, obs_track: np.ndarray, n_tracks: int) -> dict:
    """Robust statistics of residuals r (N, 2) [px] of n_tracks points (3 parameters fitted per point)."""
    n_obs = np.bincount(obs_track, minlength=n_tracks)
    dof_corr = np.sqrt(2 * n_obs / np.maximum(2 * n_obs - 3, 1))[obs_track]
    rc = r * dof_corr[:, None]
    sigma = 1.4826 * float(np.median(np.abs(rc)))
    norm = np.linalg.norm(r, axis=1)
    per_track_max = np.zeros(n_tracks)
    np.maximum.at(per_track_max, obs_track, norm)
    bound = 3.035 * sigma  # sqrt(chi2_2(0.99)) sigma
    return {
        "sigma_px": sigma,
        "rms_px": float(np.sqrt(np.mean(rc**2))),
        "norm_p50_px": float(np.percentile(norm, 50)),
        "norm_p90_px": float(np.percentile(norm, 90)),
        "norm_p99_px": float(np.percentile(norm, 99)),
        "frac_obs_over_chi2_99": float(np.mean(norm > bound)),
        "frac_tracks_max_over_chi2_99": float(np.mean(per_track_max > bound)),
    }


def pixel_error(run: dict, gt, T_b_c, K, min_views: int, min_parallax: float, max_v: int = 40) -> dict:
    """Triangulate long tracks with ground-truth poses; residual statistics [px]. Then the same after the
    frames' poses are refined against the points (two rounds of motion-only refinement and re-triangulation,
    a bundle adjustment by alternation): what remains once the estimator absorbs a pose error common to a frame
    (the ground truth's own error, a camera-to-ground-truth time offset)."""
    from runtime.backend.factors import refine_pose
    from runtime.frontend.triangulation import TriangulationConfig, triangulate

    fx = float(K[0, 0])
    T_w_b = gt.pose_at(run["ts"])
    T_w_c = T_w_b @ T_b_c
    long = [(j, o) for j, o in run["obs"].items() if len(o) >= min_views]
    if not long:
        return {"n_tracks": 0}
    V = min(max_v, max(len(o) for _, o in long))
    M = len(long)
    T = np.tile(np.eye(4), (M, V, 1, 1))
    xn = np.zeros((M, V, 2))
    mask = np.zeros((M, V), bool)
    frame = np.zeros((M, V), int)
    for m, (_, o) in enumerate(long):
        sel = np.unique(np.linspace(0, len(o) - 1, min(V, len(o))).round().astype(int))
        for v, k in enumerate(sel):
            frame[m, v] = o[k][0]
            T[m, v] = T_w_c[o[k][0]]
            xn[m, v] = o[k][1]
            mask[m, v] = True
    loose = TriangulationConfig(min_parallax_deg=0.0, min_depth=0.05, max_depth=200.0)
    names = {f.name for f in fields(loose)}
    loose = replace(loose, **{k: 1e3 for k in ("pixel_sigma", "max_reproj_px") if k in names})  # no error test
    X, ok, diag = triangulate(T, xn, mask, focal=fx, cfg=loose)
    use = ok & (diag["parallax_deg"] >= min_parallax)
    n = int(use.sum())
    mi, vi = np.nonzero(mask & use[:, None])
    remap = -np.ones(M, int)
    remap[np.nonzero(use)[0]] = np.arange(n)
    trk, fr, x_obs = remap[mi], frame[mi, vi], xn[mi, vi]

    def solve(Tc, X0):
        R_c_w = np.swapaxes(Tc[fr, :3, :3], -1, -2)
        t_c = -np.einsum("nij,nj->ni", R_c_w, Tc[fr, :3, 3])
        return _refine_points(X0, trk, R_c_w, t_c, x_obs)

    Xr, r, z = solve(T_w_c, X[use])
    out = {"n_tracks": n, "n_obs": int(trk.size), "behind": int((z <= 0).sum())}
    out.update(_residual_stats(r * fx, trk, n))
    norm = np.linalg.norm(r * fx, axis=1)
    per_frame = np.full(len(run["ts"]), np.nan)
    for f in np.unique(fr):
        per_frame[f] = float(np.median(norm[fr == f]))
    out["per_frame_median_px"] = per_frame
    # bundle adjustment by alternation: poses refined against the points, points re-triangulated
    T_b = T_w_b.copy()
    uv_u = x_obs * np.diag(K)[:2] + K[:2, 2]  # undistorted pixels
    for _ in range(2):
        for f in np.unique(fr):
            s = fr == f
            if s.sum() >= 8:
                T_b[f], _, _ = refine_pose(T_b[f], Xr[trk[s]], uv_u[s], K, T_b_c, pixel_sigma=1.0, iterations=5)
        Xr, r, _ = solve(T_b @ T_b_c, Xr)
    out["after_pose_refinement"] = _residual_stats(r * fx, trk, n)
    return out


def epipolar_error(run: dict, gt, T_b_c, fx: float) -> dict:
    """Distance [px] of each track to its epipolar line in the next frame under the ground-truth relative pose."""
    from runtime.geometry import inv_T

    T_w_c = gt.pose_at(run["ts"]) @ T_b_c
    by_frame: dict[int, dict] = {}
    for j, o in run["obs"].items():
        for f, x in o:
            by_frame.setdefault(f, {})[j] = x
    d = []
    for f in range(1, len(run["ts"])):
        a, b = by_frame.get(f - 1, {}), by_frame.get(f, {})
        common = [j for j in b if j in a]
        if len(common) < 8:
            continue
        T = inv_T(T_w_c[f]) @ T_w_c[f - 1]  # c0 -> c1
        t = T[:3, 3]
        if np.linalg.norm(t) < 1e-3:
            continue
        tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
        E = tx @ T[:3, :3]
        x0 = np.array([np.r_[a[j], 1.0] for j in common])
        x1 = np.array([np.r_[b[j], 1.0] for j in common])
        l1 = x0 @ E.T  # lines in image 1
        l0 = x1 @ E  # lines in image 0
        e = np.einsum("ni,ni->n", x1, l1)
        # symmetric point-to-line distance (normalised -> px), averaged over the two images
        d.append(0.5 * fx * np.abs(e) * (1 / np.hypot(l1[:, 0], l1[:, 1]) + 1 / np.hypot(l0[:, 0], l0[:, 1])))
    d = np.concatenate(d) if d else np.zeros(0)
    if not d.size:
        return {"n": 0}
    return {
        "n": int(d.size),
        "sigma_px": float(1.4826 * np.median(d)),  # |N(0, s)| has median 0.674 s
        "p50_px": float(np.percentile(d, 50)),
        "p90_px": float(np.percentile(d, 90)),
        "p99_px": float(np.percentile(d, 99)),
    }


def summarise(run: dict, pe: dict, ep: dict, fb: np.ndarray) -> dict:
    per = run["per_frame"]
    life = np.array([len(o) for o in run["obs"].values()])
    n = len(run["ts"])
    alive10 = np.zeros(n)
    for o in run["obs"].values():  # a track counts in the frames where it is >= 10 frames old
        if len(o) >= 10:
            alive10[o[9][0] : o[-1][0] + 1] += 1
    ms = np.array(per["ms"][1:])
    cpu = np.array(per["cpu_ms"][1:])
    return {
        "frames": n,
        "tracks_median": float(np.median(per["tracks"])),
        "tracks_min": int(np.min(per["tracks"][1:])),
        "kept_median": float(np.median(per["kept"][1:])),
        "new_mean": float(np.mean(per["new"][1:])),
        "tracks_age10_median": float(np.median(alive10[10:])),
        "tracks_age10_min": int(np.min(alive10[10:])),
        "lifetime_mean": float(life.mean()),
        "lifetime_p50": float(np.percentile(life, 50)),
        "lifetime_p90": float(np.percentile(life, 90)),
        "frac_tracks_ge10": float(np.mean(life >= 10)),
        "frac_tracks_ge20": float(np.mean(life >= 20)),
        "spread_median": float(np.median(per["spread"])),
        "spread_min": float(np.min(per["spread"])),
        "ms_mean": float(ms.mean()),
        "ms_p90": float(np.percentile(ms, 90)),
        "cpu_ms_mean": float(cpu.mean()),
        "cpu_ms_p90": float(np.percentile(cpu, 90)),
        "fb_p50_px": float(np.percentile(fb, 50)) if fb.size else None,
        "fb_p99_px": float(np.percentile(fb, 99)) if fb.size else None,
        "lost_by_cause": run["lost_by_cause"],
        "reproj": {k: v for k, v in pe.items() if k != "per_frame_median_px"},
        "epipolar": ep,
        "per_frame": {
            **{k: np.round(v, 2).tolist() for k, v in per.items()},
            "age10": alive10.astype(int).tolist(),
            "reproj_median_px": [
                None if np.isnan(x) else round(float(x), 2) for x in pe.get("per_frame_median_px", [])
            ],
        },
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--real", default=str(REPO.parent / "shared" / "data" / "euroc_MH_05_excerpt"))
    ap.add_argument("--synthetic", default=None, help="dit-sim euroc preset=flight output (default: render)")
    ap.add_argument("--synthetic-duration", type=float, default=20.0)
    ap.add_argument("--max-features", default="180,300,400,600")
    ap.add_argument("--frames", type=int, default=None, help="first N frames only")
    ap.add_argument("--kf-every", type=int, default=5)
    ap.add_argument("--redetect", type=float, default=0.6)
    ap.add_argument("--min-views", type=int, default=10)
    ap.add_argument("--min-parallax", type=float, default=3.0)
    ap.add_argument("--no-synthetic", action="store_true")
    ap.add_argument("--set", nargs="*", default=[], help="tracker/features overrides, e.g. tracker.normalize=false")
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "frontend.json"))
    a = ap.parse_args(argv)
    import cv2

    cv2.setNumThreads(1)
    from runtime.frontend.features import FeatureConfig
    from runtime.frontend.tracking import TrackerConfig

    fcfg, tcfg = FeatureConfig(), TrackerConfig()
    for s in a.set:
        k, v = s.split("=", 1)
        grp, key = k.split(".", 1)
        obj = fcfg if grp == "features" else tcfg
        typ = type(getattr(obj, key))
        val = (v.lower() == "true") if typ is bool else typ(v)
        if grp == "features":
            fcfg = replace(fcfg, **{key: val})
        else:
            tcfg = replace(tcfg, **{key: val})
    seqs = {}
    real = Path(a.real)
    if (real / "mav0" / "cam0").is_dir() or (real / "cam0").is_dir():
        seqs["MH_05 (real)"] = load_real(real)
    else:
        print(f"{real}: no EuRoC sequence, real imagery skipped", file=sys.stderr)
    if not a.no_synthetic:
        seqs["flight (synthetic)"] = load_synthetic(a.synthetic, a.synthetic_duration, 0)
    caps = [int(x) for x in a.max_features.split(",")]
    results = []
    rows = []
    for name, (seq, gt) in seqs.items():
        n = len(seq) if a.frames is None else min(a.frames, len(seq))
        for cap in caps:
            fc = replace(fcfg, max_features=cap)
            run = run_tracker(seq, gt, fc, tcfg, n, a.kf_every, a.redetect)
            pe = pixel_error(run, gt, seq.T_b_c, seq.camera.K, a.min_views, a.min_parallax)
            ep = epipolar_error(run, gt, seq.T_b_c, seq.camera.fx)
            s = summarise(run, pe, ep, run["fb"])
            s.update(sequence=name, max_features=cap)
            results.append(s)
            r = s["reproj"]
            rows.append(
                [
                    name,
                    cap,
                    f"{s['tracks_median']:.0f} / {s['tracks_min']}",
                    f"{s['new_mean']:.1f}",
                    f"{s['tracks_age10_median']:.0f} / {s['tracks_age10_min']}",
                    f"{s['lifetime_p50']:.0f} / {s['lifetime_p90']:.0f}",
                    f"{s['spread_median']:.2f} / {s['spread_min']:.2f}",
                    f"{r.get('sigma_px', float('nan')):.2f} / "
                    f"{r.get('after_pose_refinement', {}).get('sigma_px', float('nan')):.2f} ({r.get('n_tracks', 0)})",
                    f"{r.get('norm_p90_px', float('nan')):.2f} / {r.get('norm_p99_px', float('nan')):.2f}",
                    f"{ep.get('sigma_px', float('nan')):.2f}",
                    f"{s['fb_p50_px'] or 0:.2f} / {s['fb_p99_px'] or 0:.2f}",
                    f"{s['ms_mean']:.1f} / {s['cpu_ms_mean']:.1f}",
                ]
            )
            print(" | ".join(str(x) for x in rows[-1]), flush=True)
    head = [
        "sequence",
        "max feat",
        "tracks med/min",
        "new/frame",
        "age>=10 med/min",
        "life p50/p90",
        "spread med/min",
        "reproj sigma px gt/refined (tracks)",
        "|r| p90/p99 px",
        "epipolar sigma px",
        "FB p50/p99 px",
        "ms wall/cpu",
    ]
    print(markdown_table(head, rows))
    out = {
        "machine": slam_machine(),
        "code": run_provenance(REPO).splitlines()[-1].split(None, 1)[-1],
        "settings": {
            "features": asdict(fcfg),
            "tracker": {**asdict(tcfg), **{k: getattr(tcfg, k) for k in ("fb_threshold_px", "ransac_threshold_px")}},
            **{k: v for k, v in vars(a).items()},
        },
        "grid": GRID,
        "results": results,
    }
    p = write_json(a.out, out)
    print(f"wrote {p}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
