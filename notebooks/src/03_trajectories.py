# %% [markdown]
# # 03 · Sparse against dense: the shape of Table 3, and trajectories against ground truth (Fig. 10)
#
# The paper's Table 3 compares the sparse visual-inertial system with the tightly coupled dense one, with
# the geometric depth residual only (Eq. 13) and with the depth consistency residual added (Eq. 13 + 14),
# on EuRoC sequences: ATE and frames per second. Its Fig. 10 draws the estimated trajectories over the
# ground truth.
#
# Here the same ablation runs on the synthetic `textured` and `whitewall` sequences of `sim/` (60 s,
# EuRoC's camera and IMU at 752x480 / 200 Hz, IMU noise, three seeds each; `whitewall` hovers 6 s in front
# of a bare wall, see notebook 04), through the functions of the Table 3 benchmark
# (`benchmarks/bench_dense.py`: `sequence` renders and caches the sequences, `MODES` and `dense_config` give
# each mode's `DenseConfig` on top of the package defaults, `run_row` / `fmt_table` / `bars` tabulate) and
# `runtime.run.run_sequence`, which writes each run's `trajectory.txt` (TUM) and `metrics.json`; the tables
# and figures below are read back from those files. Besides ATE and FPS the table carries the depth RMSE of
# Table 2 on the keyframes that held a code: (a) the sparse map points, (b) the network prior at c = 0,
# (c) the optimised code (dense modes only).
#
# **Budget of the committed run.** The setting: 60 s sequences (1200 frames at 752x480, IMU noise), seeds 0,
# 1, 2 of both presets, all four modes (24 runs, one after another; the fourth is the upper bound below), the shipped
# depth model (`runtime/assets/default_model`, 128x128; the second one, 2026-11-25), the package's default
# `DenseConfig` (printed below: `sigma_per_b` = 8√2, the depth-edge test `edge_rel` = 0.05, codes and depth factors
# from `start_after_s` = 5 s after the first keyframe) and default `SlamConfig` (the coast kept in the smoother). The
# sequences were already cached in `DATA`. The committed run took 12 min (695 s in the notebook; 2026-11-25, AMD
# EPYC, 2 cores shared with other jobs, `nice -n 5`). Runs on one machine are deterministic: the same seeds' runs
# of `python benchmarks/bench_dense.py` on the same day and machine gave the same ATEs
# (`benchmarks/results/bench_dense_60s_16seeds_model2_*.json`, seeds 0-2 of 0-15).
#
# **The upper bound** (`dense_gt_eq13_14`): the same dense system with the rendered depth in place of the network's
# prior (`runtime.diagnostics.oracle_depth`: `D(c) = D_gt + D_net(c) − D_net(0)`, `B` = 2 cm, Laplace sigma
# `√2 B`). It tells what a perfect depth network would buy on these sequences.
#
# **What the committed run shows.** On `textured` dense Eq. 13 + 14 is at 4.0 ± 1.5 mm against 4.3 ± 1.6 mm sparse
# (per seed 2.0 / 5.4 / 4.6 against 2.0 / 5.7 / 5.1 mm; Eq. 13 alone 4.6 mm), so on these three seeds the issue's
# bar (dense at most sparse) is met. Three seeds do not resolve it: over seeds 0-15 Eq. 13 + 14 is at 4.18 against
# 4.25 mm sparse, a paired difference of -0.07 ± 0.14 mm (better on 9 of 16), and Eq. 13 alone at 4.27 mm
# (`benchmarks/results/bench_dense_60s_16seeds_model2_textured_*.json`). The rendered depth with Eq. 13 + 14 is at
# 3.7 mm here (3.45 mm over seeds 0-7 with the first model): the factors work, and the network's depth (RMSE about
# 0.15 m, errors correlated over a map) is what limits them.
# On `whitewall` every run loses visual tracking in front of the bare wall for about 10 s, coasts on the IMU and is
# relocalised against the map. Dense is at 6.9 mm (Eq. 13 and Eq. 13 + 14) against 6.5 mm sparse, and the
# rendered depth at 5.8 mm, so the bar (10 % below sparse) is **not met** (over sixteen seeds: 8.06 against 7.90 mm,
# and even the rendered depth is only 4.7 % below sparse there, 7.53 mm: no depth source reaches the bar).
# The section *Where the `whitewall` ATE comes from* shows why: over the coast the runs average 10.2-11.7 mm against
# 7.2 mm for an IMU smoothed between exact end states (5.4 mm with a perfect wall-distance sensor), each side of the
# coast aligned on its own is 2.3-3.7 mm off, and what sets the ATE is the frame jump between the two sides
# at the relocalisation (2.0-11.3 mm, 0.22-0.37°): how the trajectory after it ties back to the old map. No depth
# residual of the network acts on that tie. The optimised codes lower the keyframes' depth RMSE: from the prior's
# 0.143 m to 0.137 m on `textured` and from 0.202 m to 0.196 m on `whitewall` (Eq. 13 alone: 0.142 to 0.137 m and
# 0.197 to 0.193 m). The sparse map points are more accurate (0.04-0.05 m) but cover under 1 % of the pixels. The
# dense system ran at 29-49 frames/s (means 32-43) against 87-128 for the sparse one on this shared CPU (bar: 15).
#
# Re-run (from the repository root, venv active; writes under `OUT`, here `outputs/notebooks/03_trajectories/`;
# the sequences are cached in `DATA`, rendering one 60 s sequence takes about 2 minutes):
#
# ```
# nice -n 5 python -m tests.notebooks.run notebooks/03_trajectories.ipynb --inplace
# ```
#
# The same table from the command line: `python benchmarks/bench_dense.py` with the arguments printed below.

# %% tags=["parameters"]
OUT = "outputs/notebooks/03_trajectories"  # output folder (relative to the repository root)
DATA = "data/sim/bench_dense"  # sequence cache, shared with benchmarks/bench_dense.py
PRESETS = ["textured", "whitewall"]  # sim presets (whitewall needs DURATION >= 24)
SEEDS = [0, 1, 2]  # sequence seeds
DURATION = 60.0  # sequence length [s]
SCALE = 1.0  # image scale of the rendered sequences (1.0: EuRoC's 752x480)
MODES = ["sparse", "dense_eq13", "dense_eq13_14", "dense_gt_eq13_14"]  # keys of bench_dense.MODES
DENSE_SET = []  # DenseConfig overrides "key=value" (as bench_dense --set); [] = the package defaults
FIG_SEED = 0  # the seed drawn in Fig. 10
REUSE = False  # reuse a run whose metrics.json in OUT has the same sequence, SlamConfig and DenseConfig

# %%
import dataclasses
import json
import logging
import os
import time

import matplotlib.pyplot as plt
import numpy as np
from benchmarks import bench_dense
from benchmarks.common import cpu_model, run_provenance, start_notebook
from IPython.display import Image, Markdown, display
from runtime.eval import trajectory_metrics
from runtime.io.euroc import read_euroc
from runtime.io.tum import read_tum
from runtime.slam import SlamConfig

REPO, out, t_start = start_notebook(OUT)
logging.getLogger("runtime").setLevel(logging.ERROR)  # the runs' events (tracking lost, ...) stay in metrics.json
print(run_provenance(REPO))  # machine, date, and which code ran
unknown = sorted(set(MODES) - set(bench_dense.MODES))
if unknown:
    raise ValueError(f"MODES {unknown} are not in bench_dense.MODES {list(bench_dense.MODES)}")

# %% [markdown]
# ## Settings of the three modes
#
# The sparse system runs with `SlamConfig()`; the dense modes add the package's default `DenseConfig`
# (`conf/slam/dense_settings/default.yaml`) with the residuals of the mode switched on, plus `DENSE_SET`.
# Per-keyframe depth maps are not saved (`save_maps=False`, as in the benchmark).

# %%
dense_cfgs = {mode: bench_dense.dense_config(mode, list(DENSE_SET)) for mode in MODES}
for mode, cfg in dense_cfgs.items():
    if cfg is None:
        print(f"{mode:14s} SlamConfig() only")
    else:
        print(f"{mode:14s} " + ", ".join(f"{k}={v}" for k, v in dataclasses.asdict(cfg).items()))
argv = ["--presets", *PRESETS, "--seeds", *map(str, SEEDS), "--duration", f"{DURATION:g}", "--scale", f"{SCALE:g}"]
argv += ["--modes", *MODES, "--data", DATA, "--out", str(out / "runs")] + (["--set", *DENSE_SET] if DENSE_SET else [])
print("\nthe same runs from the command line: python benchmarks/bench_dense.py " + " ".join(argv))

# %% [markdown]
# ## The runs
#
# One after another in this process, each a fresh system (FPS = frames / wall time of the whole run, image
# decoding included). The machine is shared: compare FPS within one run of this notebook.


# %%
def same_settings(saved: dict, seq, cfg) -> bool:
    """Does a saved metrics.json come from this sequence with these settings?"""
    slam = json.loads(json.dumps(dataclasses.asdict(SlamConfig())))
    dense = None if cfg is None else json.loads(json.dumps(dataclasses.asdict(cfg)))
    return saved.get("sequence") == str(seq.root) and saved.get("config") == slam and saved.get("dense_config") == dense


rows, run_dirs, roots = [], {}, {}
for preset in PRESETS:
    for seed in SEEDS:
        t0 = time.time()
        root = roots[preset, seed] = bench_dense.sequence(REPO / DATA, preset, DURATION, seed, SCALE)
        seq = read_euroc(root)
        for mode in MODES:
            run_dir = run_dirs[preset, seed, mode] = out / "runs" / f"{preset}_s{seed}_{mode}"
            saved = run_dir / "metrics.json"
            t0 = time.time()
            if REUSE and saved.is_file() and same_settings(json.loads(saved.read_text()), seq, dense_cfgs[mode]):
                m, how = json.loads(saved.read_text()), "reused"
            else:
                m = bench_dense.run_mode(seq, run_dir, mode, DENSE_SET)
                how = f"{time.time() - t0:.0f} s"
            rows.append(bench_dense.run_row(preset, seed, mode, m))
            r = rows[-1]
            print(
                f"{preset:9s} seed {seed} {mode:14s} ATE {1e3 * r['ate']:7.1f} mm  {r['fps']:5.1f} FPS  "
                f"RMSE a/b/c {r['rmse_a']:.3f}/{r['rmse_b']:.3f}/{r['rmse_c']:.3f} m  ({how})",
                flush=True,
            )

# %% [markdown]
# ## Table 3 (shape): mean ± standard deviation over seeds
#
# ATE: SE(3)-aligned RMSE of the body positions against the ground truth, over every frame after the
# initialisation (`runtime.eval`, evo). Depth RMSE on the keyframes that held a code, at network resolution,
# against the rendered depth: (a) sparse map points, (b) prior c = 0, (c) optimised code.


# %%
def stat(preset: str, mode: str, col: str, scale: float = 1.0, digits: int = 1) -> str:
    v = np.array([r[col] for r in rows if r["preset"] == preset and r["mode"] == mode], float) * scale
    v = v[np.isfinite(v)]
    if v.size == 0:
        return "–"
    return f"{v.mean():.{digits}f} ± {v.std():.{digits}f}" if v.size > 1 else f"{v[0]:.{digits}f}"


LABEL = {  # other bench_dense.MODES keep their key as label
    "sparse": "sparse",
    "dense_eq13": "dense, Eq. 13",
    "dense_eq13_14": "dense, Eq. 13 + 14",
    "dense_gt_eq13_14": "dense, Eq. 13 + 14, rendered depth",
}
head = (
    "| sequence | mode | seeds | ATE [mm] | ATE per seed [mm] | FPS | depth RMSE (a) sparse [m] | "
    "(b) prior c=0 [m] | (c) optimised [m] |\n|---|---|---|---|---|---|---|---|---|\n"
)
lines = []
for preset in PRESETS:
    for mode in MODES:
        per_seed = " / ".join(f"{1e3 * r['ate']:.1f}" for r in rows if r["preset"] == preset and r["mode"] == mode)
        lines.append(
            f"| {preset} | {LABEL.get(mode, mode)} | {len(SEEDS)} | {stat(preset, mode, 'ate', 1e3)} | {per_seed} | "
            f"{stat(preset, mode, 'fps', 1.0, 0)} | {stat(preset, mode, 'rmse_a', 1, 3)} | "
            f"{stat(preset, mode, 'rmse_b', 1, 3)} | {stat(preset, mode, 'rmse_c', 1, 3)} |"
        )
table3 = head + "\n".join(lines)
display(Markdown(f"Table 3 shape, synthetic sequences, {DURATION:g} s, scale {SCALE:g}:\n\n" + table3))

# %% [markdown]
# The quality bars on these means (`bench_dense.bars`; the committed outputs show the bars of the time: dense
# Eq. 13 + 14 ATE at most the sparse ATE on `textured` and at least 10 % lower on `whitewall`, optimised-code
# depth RMSE below the prior's, at least 15 frames/s; a new run shows today's: the paired ATE difference against
# sparse, at least 20 frames/s, optimised codes below the prior):

# %%
bars = bench_dense.bars(rows) if {"sparse", "dense_eq13_14"} <= set(MODES) else {}
lines = []
for key, b in bars.items():
    vals = ", ".join(f"{k} {v:.4g}" for k, v in b.items() if k != "met")
    lines.append(f"| {key} | {vals} | {'**met**' if b['met'] else 'not met'} |")
display(
    Markdown("| bar | values | |\n|---|---|---|\n" + "\n".join(lines) if lines else "(needs sparse and dense_eq13_14)")
)

# %% [markdown]
# ATE per run, by seed (each group of bars is one sequence):

# %%
fig, axes = plt.subplots(1, len(PRESETS), figsize=(5.5 * len(PRESETS), 3.4), squeeze=False)
w = 0.8 / len(MODES)
for ax, preset in zip(axes[0], PRESETS, strict=True):
    for j, mode in enumerate(MODES):
        ate = [next(r["ate"] for r in rows if (r["preset"], r["seed"], r["mode"]) == (preset, s, mode)) for s in SEEDS]
        ax.bar(
            np.arange(len(SEEDS)) + (j - (len(MODES) - 1) / 2) * w, 1e3 * np.array(ate), w, label=LABEL.get(mode, mode)
        )
    ax.set_xticks(np.arange(len(SEEDS)), [f"seed {s}" for s in SEEDS])
    ax.set_ylabel("ATE (SE3) [mm]")
    ax.set_title(preset)
    ax.grid(axis="y", alpha=0.3)
axes[0, 0].legend(fontsize=8)
fig.tight_layout()
fig.savefig(out / "table3_ate.png", dpi=100)
plt.close(fig)
display(Image(filename=out / "table3_ate.png"))

# %% [markdown]
# ## Fig. 10: trajectories against ground truth
#
# Top view (x-y, ground-truth frame) of seed `FIG_SEED`: the ground truth and each mode's estimate read back
# from its `trajectory.txt`, SE(3)-aligned to the ground truth (the alignment of the ATE). Below: the
# position error of each aligned estimate over time; on `whitewall` the grey band is the hold in front of
# the bare wall (`sim_info.json`).

# %%
fig, axes = plt.subplots(
    2, len(PRESETS), figsize=(5.8 * len(PRESETS), 9.0), squeeze=False, gridspec_kw={"height_ratios": [2.2, 1]}
)
for col, preset in enumerate(PRESETS):
    root = roots[preset, FIG_SEED]
    gt = read_euroc(root).gt
    info = json.loads((root / "sim_info.json").read_text())
    t0_ns = info["t0_ns"]
    ax, ax_e = axes[0, col], axes[1, col]
    ax.plot(gt.T_w_b[:, 0, 3], gt.T_w_b[:, 1, 3], "k-", lw=2.0, alpha=0.35, label="ground truth")
    for j, mode in enumerate(MODES):
        ts, T = read_tum(run_dirs[preset, FIG_SEED, mode] / "trajectory.txt")
        met = trajectory_metrics(ts, T, gt.ts, gt.T_w_b, return_aligned=True)
        p, ref = met["aligned_se3"], met["reference"]
        t = (ts[(ts >= gt.ts[0]) & (ts <= gt.ts[-1])] - t0_ns) * 1e-9
        lab = f"{LABEL.get(mode, mode)} (ATE {1e3 * met['ate_se3_rmse_m']:.1f} mm)"
        ax.plot(p[:, 0], p[:, 1], "-", color=f"C{j}", lw=0.9, label=lab)
        ax_e.plot(t, 1e3 * np.linalg.norm(p - ref, axis=1), "-", color=f"C{j}", lw=0.9, label=LABEL.get(mode, mode))
    if info.get("whitewall_window_s"):
        a, b = info["whitewall_window_s"]
        ax_e.axvspan(a, b, color="0.85", label="hold at the bare wall")
        hold = (gt.ts - t0_ns >= a * 1e9) & (gt.ts - t0_ns <= b * 1e9)
        ax.plot(
            gt.T_w_b[hold, 0, 3], gt.T_w_b[hold, 1, 3], "-", color="0.5", lw=5, alpha=0.5, label="hold (ground truth)"
        )
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(f"{preset}, seed {FIG_SEED} ({DURATION:g} s)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="best")
    ax_e.set_xlabel("time since the first frame [s]")
    ax_e.set_ylabel("position error [mm]")
    ax_e.grid(alpha=0.3)
    ax_e.legend(fontsize=7, loc="upper left")
fig.tight_layout()
fig.savefig(out / "fig10_trajectories.png", dpi=100)
plt.close(fig)
display(Image(filename=out / "fig10_trajectories.png"))

# %% [markdown]
# ## Where the `whitewall` ATE comes from
#
# `benchmarks/bench_coast.py` on these runs. **Oracles**: the coast (from the sparse run's "visual tracking lost" to
# "regained") smoothed over the sequence's noisy IMU from the exact state at the loss and, at the regain, the exact
# pose (`end pose`, what a relocalisation's PnP gives), pose and velocity (`end pose+vel`), and with the exact
# camera-to-wall distance at every keyframe as well (`+ wall distance`: a perfect depth sensor on the wall). Their
# position RMSE over the coast bounds what any system can do there; the wall distance observes the motion along the
# wall's normal only. **Runs**: each run's ATE split into the RMSE before, over and after the coast under the
# alignment of the whole trajectory, the part before and the part after each aligned on its own, and how far apart
# (mm, deg) those two alignments put the relocalised pose: a jump far larger than the one-sided errors means that the
# ATE is set by how the trajectory after the relocalisation ties back to the map before it.

# %%
from benchmarks import bench_coast
from runtime.diagnostics.coast import coast_row

coast_rows = []
if "whitewall" in PRESETS:
    for seed in SEEDS:
        runs = {mode: run_dirs["whitewall", seed, mode] for mode in MODES}
        coast_rows.append(coast_row(roots["whitewall", seed], seed, runs))
    print(bench_coast.fmt_tables(coast_rows))

# %%
result = {
    "presets": PRESETS,
    "seeds": SEEDS,
    "duration_s": DURATION,
    "scale": SCALE,
    "modes": MODES,
    "dense_set": DENSE_SET,
    "dense_configs": {m: (None if c is None else dataclasses.asdict(c)) for m, c in dense_cfgs.items()},
    "machine": {"cpu": cpu_model(), "cores": os.cpu_count(), "loadavg_end": list(os.getloadavg())},
    "rows": rows,
    "bars": bars,
    "table": table3,
    "bench_dense_table": bench_dense.fmt_table(rows),
    "coast": coast_rows,
}
(out / "table3.json").write_text(json.dumps(result, indent=2, default=float))
print(bench_dense.fmt_table(rows, per_run=False))
print(f"\noutputs in {out}: " + ", ".join(sorted(p.name for p in out.iterdir() if p.suffix in (".png", ".json"))))
print(f"notebook wall time {time.time() - t_start:.0f} s")
