# %% [markdown]
# # 01 · Depth network ablation: the shape of Table 1, and Fig. 7 / 8
#
# The paper's Table 1 compares four light-weight depth networks, **FastDepth**, **CodeVIO (32D)**,
# **CodeVIO (8D)** and **ours (DiT: CBAM + SK-like fusion, 8D code)**, on four input modalities: RGB,
# grey (G), RGB + sparse depth (RGB-S) and grey + sparse depth (G-S), with RMSE, iRMSE, AbsRel, MAE, MAPE,
# δ1/δ2/δ3 and the inference time per frame. Fig. 7 (RGB) and Fig. 8 (G-S) show input, ground truth, the
# sparse FAST points, the predicted depth and its uncertainty on validation frames.
#
# This notebook produces the same table and figures with the project's own code: `train.ablation.run_ablation`
# trains every cell with `python train/fit.py experiment=<variant>_<modality>` under one shared budget and
# evaluates it with `train.evaluate` (validation transform, exactly 125 noise-free FAST samples for the
# `*s` modalities, code = prior mean 0). The figures use the trained `dit/rgb` and `dit/grays` cells
# (torch), and the **shipped default model** `runtime/assets/default_model` through ONNX Runtime when it is
# present.
#
# **Budget of the committed run (not the paper's setting).** **96x96** input, **240** optimisation steps of batch
# **8** per cell, **300** synthetic training and **50** synthetic validation frames rendered by `dit-sim nyu`
# (seed 0), width multiplier 1.0, one torch thread per cell, **2 training seeds** (0 and 1). The paper trains on
# real NYU Depth V2 at 224x224 to convergence; the numbers here only show the *shape* of the comparison on
# synthetic rooms after a short schedule. The committed run (2026-11-27, AMD EPYC with AVX-512, 2 cores) trained
# the two seeds side by side, beside two other training runs for part of the time: about 70 minutes in all. Its
# ms/frame column (torch batch-1 forward passes at 96x96) was measured under that load and is not a speed figure.
#
# **What the committed run shows.**
# - Without sparse depth (RGB, G) no variant gets near the per-image median-GT reference (0.362 m): RMSE
#   0.69-0.76 m, and the order of the four variants changes between the two seeds. This budget cannot rank them.
# - With sparse depth (RGB-S, G-S) DiT is first on both seeds and FastDepth second. DiT predicts a correction of
#   the interpolation of its points. After 240 steps it has barely moved from it: 0.995-0.998x the interpolation's
#   RMSE (0.108-0.109 m). The three variants that regress absolute depth are at 3.4-6.3x the interpolation's RMSE.
# - So no budget a CPU notebook can afford makes the sparse-input variants beat interpolation: the one that does
#   it at all is DiT with its relative output. The shipped default model (600 steps of batch 16 on 1000 realistic
#   frames at 128x128) beats interpolation on realistic rooms (0.79x, its README). On these plainer 50 frames it
#   scores 0.112 m, and the interpolation of the same points at 96x96 0.109 m (last section).
#
# Re-run (from the repository root, venv active; writes under `OUT`, here
# `outputs/notebooks/01_depth_modalities/`):
#
# ```
# python -m tests.notebooks.run notebooks/01_depth_modalities.ipynb --inplace
# ```
#
# Every size is in the parameter cell below; the test `tests/notebooks/test_notebooks.py` runs this notebook
# end to end with tiny values injected after it. The same table from the command line:
# `python -m train.ablation --out OUT/ablation_seed0 <the overrides printed below> seed=0` (and `seed=1`).

# %% tags=["parameters"]
OUT = "outputs/notebooks/01_depth_modalities"  # output folder (relative to the repository root)
VARIANTS = ["fastdepth", "codevio32", "codevio8", "dit"]  # Table 1 rows
MODALITIES = ["rgb", "gray", "rgbs", "grays"]  # Table 1 blocks
SIZE = 96  # network input height = width [px], a multiple of 32 (paper: 224)
WIDTH_MULT = 1.0  # MobileNet width multiplier of every variant
STEPS = 240  # optimisation steps per cell (same for all cells)
BATCH = 8  # training and validation batch
VAL_EVERY = 40  # validation every N steps; the best checkpoint (val RMSE) is evaluated
N_TRAIN = 300  # synthetic training frames (dit-sim nyu)
N_VAL = 50  # synthetic validation frames (different rooms)
DATA_SEED = 0  # seed of the synthetic rooms
SEEDS = [0, 1]  # training seeds: the table is the first seed's; the ordering is compared over all of them
THREADS = 1  # torch threads per training process (0 = torch's default)
TIMING_FRAMES = 20  # batch-1 forward passes timed per cell (ms/frame)
FIG_FRAMES = 4  # validation frames shown in Fig. 7 / Fig. 8
FORCE = False  # re-train cells whose eval_depth.json exists already

# %%
import json
import os
import time
from pathlib import Path

import hydra
import matplotlib.pyplot as plt
import numpy as np
import torch
from benchmarks.common import cpu_model, start_notebook
from IPython.display import Image, Markdown, display
from runtime.io.nyu import list_nyu_h5, read_nyu_h5
from runtime.network import DepthNetwork, default_model_dir
from train.ablation import MODALITIES as MODALITY_LABELS
from train.ablation import VARIANTS as VARIANT_LABELS
from train.ablation import run_ablation
from train.augment import FrameTransform
from train.data import ensure_synthetic_nyu
from train.evaluate import load_network
from train.metrics import DepthMetrics, format_table, image_metrics

REPO, out, t_start = start_notebook(OUT)
print(f"machine    {cpu_model()}, {os.cpu_count()} cores, load {os.getloadavg()}, torch {torch.__version__}")

# %% [markdown]
# ## Data
#
# Synthetic NYU-layout frames (`rgb` 480x640, metric `depth`), rendered once into `OUT/data` by
# `train.data.ensure_synthetic_nyu` (the same function `python train/fit.py` uses for its default data).
# Training and validation frames come from different rooms.

# %%
t0 = time.time()
data_root = ensure_synthetic_nyu(out / "data", N_TRAIN, N_VAL, DATA_SEED, progress=False)
n_tr, n_va = len(list_nyu_h5(data_root, "train")), len(list_nyu_h5(data_root, "val"))
print(f"{n_tr} train + {n_va} val frames in {data_root} ({time.time() - t0:.0f} s)")

# %% [markdown]
# ## Table 1: 4 variants x 4 modalities, one budget
#
# Every cell runs `python train/fit.py experiment=<variant>_<modality> <overrides>` in its own process
# (log: `OUT/ablation/<variant>_<modality>.log`), then the best checkpoint is evaluated on all validation
# frames. A cell that finished before (its `eval_depth.json` exists) is not trained again unless
# `FORCE = True`. The *median GT* rows score a constant prediction equal to each image's median ground-truth
# depth (a reference that knows the scale). `train.ablation` now also adds, for the sparse modalities, the
# *interpolation* of each cell's own 125 points (linear, nearest outside their hull), the bar a sparse-input
# network has to clear. The first table is seed 0's; the next cell compares the seeds.

# %%
overrides = [
    f"data.root={data_root}",
    f"data.sim.n_train={N_TRAIN}",
    f"data.sim.n_val={N_VAL}",
    f"data.sim.seed={DATA_SEED}",
    f"data.height={SIZE}",
    f"data.width={SIZE}",
    f"data.batch_size={BATCH}",
    f"data.val_batch_size={BATCH}",
    f"model.net.width_mult={WIDTH_MULT}",
    f"trainer.max_steps={STEPS}",
    f"trainer.val_check_interval={VAL_EVERY}",
    "trainer.enable_model_summary=false",
    "logger.tensorboard=null",
    "validate=false",
] + ([f"num_threads={THREADS}"] if THREADS else [])
print("overrides:", " ".join(overrides))
t0 = time.time()
summaries = {
    seed: run_ablation(
        out / f"ablation_seed{seed}",
        overrides + [f"seed={seed}"],
        VARIANTS,
        MODALITIES,
        force=FORCE,
        timing_frames=TIMING_FRAMES,
    )
    for seed in SEEDS
}
summary = summaries[SEEDS[0]]
cells = summary["cells"]
print(f"ablation: {len(cells)} cells x {len(SEEDS)} seeds in {time.time() - t0:.0f} s (finished cells are reused)")
display(Markdown(f"Training seed {SEEDS[0]}. " + summary["header"] + "\n\n" + summary["table"]))

# %% [markdown]
# Does the budget rank the variants? Per modality and training seed: the variants from best to worst RMSE, and
# each sparse-input cell's RMSE as a ratio to the interpolation of its own 125 points (below 1: the network adds
# to its input). An ordering that changes between seeds is not a result at this budget.

# %%
mods = [m for m in MODALITY_LABELS if m in MODALITIES]
vars_ = [v for v in VARIANT_LABELS if v in VARIANTS]
order, ratio = {}, {}
for seed, summ in summaries.items():
    for m in mods:
        got = {v: summ["cells"][f"{v}_{m}"] for v in vars_ if f"{v}_{m}" in summ["cells"]}
        order[(m, seed)] = sorted(got, key=lambda v: got[v]["metrics"]["rmse"])
        for v, c in got.items():
            if "interpolation" in c:
                ratio[(v, m, seed)] = c["metrics"]["rmse"] / c["interpolation"]["rmse"]


def md_table(head: list[str], rows: list[list[str]]) -> Markdown:
    """A markdown table of string cells."""
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"] + ["| " + " | ".join(r) + " |" for r in rows]
    return Markdown("\n".join(lines))


rows = []
for m in mods:
    orders = [order[(m, s)] for s in SEEDS]
    same = "yes" if all(o == orders[0] for o in orders) else "no"
    rows.append([MODALITY_LABELS[m]] + [", ".join(VARIANT_LABELS[v] for v in o) for o in orders] + [same])
display(md_table(["modality"] + [f"seed {s}: best to worst" for s in SEEDS] + ["same order"], rows))
if ratio:
    rows = [
        [f"{MODALITY_LABELS[m]} / {VARIANT_LABELS[v]}"] + [f"{ratio[(v, m, s)]:.3f}" for s in SEEDS]
        for m in mods
        for v in vars_
        if (v, m, SEEDS[0]) in ratio
    ]
    display(md_table(["cell"] + [f"RMSE / interpolation, seed {s}" for s in SEEDS], rows))
stability = {
    "seeds": SEEDS,
    "order": {f"{m}_seed{s}": o for (m, s), o in order.items()},
    "rmse_over_interpolation": {f"{v}_{m}_seed{s}": r for (v, m, s), r in ratio.items()},
}
(out / "table1_seeds.json").write_text(json.dumps(stability, indent=2))

# %% [markdown]
# Training wall time per cell (same number of steps for all; the variants differ in cost per step):

# %%
rows = [
    f"| {MODALITY_LABELS[c['modality']]} / {VARIANT_LABELS[c['model']]} | {c['train_wall_s']:.0f} | "
    f"{c['ms']:.2f} | {c['frames']} |"
    for c in cells.values()
]
display(Markdown("| cell | train wall [s] | ms/frame | val frames |\n|---|---|---|---|\n" + "\n".join(rows)))

# %% [markdown]
# The same numbers as bars (lower RMSE is better, higher δ1 is better); the dashed line is the median-GT
# reference of each modality.

# %%
fig, axes = plt.subplots(1, 2, figsize=(11, 3.6))
w = 0.8 / max(len(vars_), 1)
for ax, key, label in ((axes[0], "rmse", "RMSE [m]"), (axes[1], "delta1", "δ1 (fraction < 1.25)")):
    for j, v in enumerate(vars_):
        vals = [cells[f"{v}_{m}"]["metrics"][key] if f"{v}_{m}" in cells else np.nan for m in mods]
        ax.bar(np.arange(len(mods)) + (j - (len(vars_) - 1) / 2) * w, vals, w, label=VARIANT_LABELS[v])
    for i, m in enumerate(mods):
        med = next((c["median"][key] for k, c in cells.items() if k.endswith(f"_{m}") and "median" in c), None)
        if med is not None:
            ax.hlines(med, i - 0.45, i + 0.45, colors="k", linestyles="--", lw=1)
    ax.set_xticks(np.arange(len(mods)), [MODALITY_LABELS[m] for m in mods])
    ax.set_ylabel(label)
    ax.grid(axis="y", alpha=0.3)
axes[0].legend(fontsize=8)
fig.suptitle(f"Table 1 shape on synthetic data, {SIZE}x{SIZE}, {STEPS} steps x batch {BATCH} per cell", fontsize=9)
fig.tight_layout()
fig.savefig(out / "table1_bars.png", dpi=110)
plt.close(fig)
display(Image(filename=out / "table1_bars.png"))  # the saved PNG, whatever the backend

# %% [markdown]
# Does metric sparse depth help? The quality bar asks for `grays` to beat `gray` on RMSE by at least
# 30 % (and `dit`/`grays` to beat the median-GT reference by a wide margin) after the *default* training
# schedule; with this notebook's shorter budget the figures below are indicative only.

# %%
lines = []
for v in vars_:
    for dense, sparse in (("gray", "grays"), ("rgb", "rgbs")):
        a, b = cells.get(f"{v}_{dense}"), cells.get(f"{v}_{sparse}")
        if a and b:
            ra, rb = a["metrics"]["rmse"], b["metrics"]["rmse"]
            pair = f"{MODALITY_LABELS[dense]} → {MODALITY_LABELS[sparse]}"
            lines.append(f"| {VARIANT_LABELS[v]} | {pair} | {ra:.3f} | {rb:.3f} | {100 * (1 - rb / ra):+.0f} % |")
    if f"{v}_grays" in cells:
        ra, rb = cells[f"{v}_grays"]["median"]["rmse"], cells[f"{v}_grays"]["metrics"]["rmse"]
        lines.append(f"| {VARIANT_LABELS[v]} | G-S vs median GT | {ra:.3f} | {rb:.3f} | {100 * (1 - rb / ra):+.0f} % |")
head = "| variant | comparison | RMSE before [m] | RMSE after [m] | RMSE reduction |\n|---|---|---|---|---|\n"
display(Markdown(head + "\n".join(lines)) if lines else Markdown("(no gray/grays pair in this run)"))

# %% [markdown]
# ## Fig. 7 / Fig. 8: predictions on validation frames
#
# The trained `dit` cells (torch, code = 0, the prior mean, as in `train.evaluate`) on validation frames
# spread over the validation rooms, through the evaluation transform (resize + centre crop; for G-S the 125
# noise-free FAST samples, drawn as red points). Depth maps share the ground truth's colour range per row;
# the title of the prediction gives the frame's RMSE. Uncertainty is the network's per-pixel scale `B` [m]
# (Eq. 6).


# %%
def predict_cell(cell: str, n: int) -> list[dict]:
    """Validation frames of one trained cell: image, ground truth, sparse input, depth and uncertainty."""
    net, net_cfg, run_cfg = load_network(cells[cell]["checkpoint"])
    dm = hydra.utils.instantiate(run_cfg["data"])
    ds = dm.make_dataset(dm.val_split, train=False)
    frames = []
    for i in np.unique(np.linspace(0, len(ds) - 1, n).round().astype(int)):
        s = ds[int(i)]
        with torch.inference_mode():
            o = net(torch.from_numpy(s["image"])[None])
        depth, gt = o["depth"][0, 0].numpy(), s["depth"][0]
        rmse = float(image_metrics(o["depth"], torch.from_numpy(s["depth"])[None])["rmse"][0])
        sparse_in = net_cfg["modality"].endswith("s")
        img = s["image"][:-1] if sparse_in else s["image"]
        frames.append(
            {
                "name": str(ds.files[int(i)].relative_to(data_root)),
                "image": img[0] if img.shape[0] == 1 else img.transpose(1, 2, 0),
                "gt": gt,
                "sparse": s["image"][-1] if sparse_in else None,
                "depth": depth,
                "uncertainty": None if o["uncertainty"] is None else o["uncertainty"][0, 0].numpy(),
                "rmse": rmse,
            }
        )
    return frames


def show_frames(frames: list[dict], title: str, path: Path) -> None:
    """Rows of input / GT / (sparse) / depth / uncertainty, saved as PNG."""
    has_sparse = frames[0]["sparse"] is not None
    cols = ["input", "ground truth"] + (["sparse FAST points"] if has_sparse else []) + ["depth", "uncertainty"]
    fig, axes = plt.subplots(len(frames), len(cols), figsize=(2.0 * len(cols), 2.0 * len(frames)), squeeze=False)
    for r, f in enumerate(frames):
        valid = f["gt"] > 0
        lo, hi = np.percentile(f["gt"][valid], [1, 99]) if valid.any() else (0.5, 5.0)
        gray = f["image"].ndim == 2
        panels = [("input", f["image"], {"cmap": "gray" if gray else None, "vmin": 0, "vmax": 1})]
        panels.append(("ground truth", np.where(valid, f["gt"], np.nan), {"cmap": "viridis", "vmin": lo, "vmax": hi}))
        if has_sparse:
            panels.append(("sparse FAST points", f["image"], {"cmap": "gray" if gray else None, "vmin": 0, "vmax": 1}))
        panels.append((f"depth (RMSE {f['rmse']:.2f} m)", f["depth"], {"cmap": "viridis", "vmin": lo, "vmax": hi}))
        if f["uncertainty"] is not None:
            panels.append(("uncertainty B [m]", f["uncertainty"], {"cmap": "magma"}))
        for c, (name, im, kw) in enumerate(panels):
            ax = axes[r, c]
            h = ax.imshow(im, **kw)
            if name.startswith("sparse"):
                v, u = np.nonzero(f["sparse"])
                ax.scatter(u, v, s=4, c="r", marker="o", linewidths=0)
                name = f"sparse FAST points ({len(u)})"
            if name.startswith("uncertainty"):
                fig.colorbar(h, ax=ax, fraction=0.046, pad=0.02)
            ax.set_title(name if r == 0 or name.startswith("depth") else "", fontsize=8)
            ax.set_xticks([])
            ax.set_yticks([])
        axes[r, 0].set_ylabel("/".join(Path(f["name"]).with_suffix("").parts[-2:]), fontsize=7)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=72)  # ~native resolution of the 96-128 px network images; keeps the notebook small
    plt.close(fig)
    display(Image(filename=path))  # the saved PNG, whatever the backend


# %%
for cell, fig_name, label in (
    ("dit_rgb", "fig7_dit_rgb.png", "Fig. 7 (RGB)"),
    ("dit_grays", "fig8_dit_grays.png", "Fig. 8 (G-S)"),
):
    if cell not in cells:
        print(f"{label}: cell {cell} not in this run (VARIANTS / MODALITIES), skipped")
        continue
    show_frames(
        predict_cell(cell, FIG_FRAMES),
        f"{label}: trained {cell} cell ({SIZE}x{SIZE}, {STEPS} steps), synthetic validation frames",
        out / fig_name,
    )
    print(f"saved {out / fig_name}")

# %% [markdown]
# ## The shipped default model (ONNX Runtime)
#
# `runtime/assets/default_model` is what `dit-slam` uses when no model is given (trained with `python train/fit.py`,
# the default preset with 2400 steps on 2000 frames, exported with `dit-export`; its README). Here it runs through
# `runtime.network.DepthNetwork` (ONNX Runtime, no torch): `prior(image, sparse)` once per frame, then the
# decoder at the zero code. Inputs come from the same validation frames via the evaluation transform at the
# model's own input size (125 noise-free FAST samples for `*s`). With `DATA_SEED = 0` these are rooms the
# default model did not see in training (it was trained on the seed-0 *training* rooms; train and validation
# rooms are disjoint). Its recorded `val_metrics.json` comes from other frames and another sparse sampling
# (`benchmarks/eval_onnx_depth.py`), so the figures agree only roughly.

# %%
model_dir = default_model_dir()
if not (model_dir / "manifest.json").is_file():
    print(f"no shipped default model at {model_dir}: skipped (it appears once the export issue ships it)")
    dn = None
else:
    dn = DepthNetwork(model_dir)
    man = dn.manifest
    print(f"{model_dir}: {man.get('model', '?')} {dn.modality} {dn.height}x{dn.width}, C={dn.code_dim}")
    print(f"source checkpoint: {man.get('source')}")
    print(f"export parity (torch vs ONNX Runtime): {json.dumps(man.get('parity'))}")
    if (model_dir / "val_metrics.json").is_file():
        print(f"recorded validation metrics (val_metrics.json): {(model_dir / 'val_metrics.json').read_text()}")

# %%
if dn is not None:
    tf = FrameTransform(dn.height, dn.width, dn.modality, train=False)
    files = list_nyu_h5(data_root, "val")
    acc, shown = DepthMetrics(), []
    pick = set(np.unique(np.linspace(0, len(files) - 1, FIG_FRAMES).round().astype(int)).tolist())
    zero = np.zeros(dn.code_dim, np.float32)
    t_ort = []
    for i, f in enumerate(files):
        rgb, depth = read_nyu_h5(f)
        s = tf(rgb, depth, np.random.default_rng([DATA_SEED, 0, i]))
        x = s["image"]
        img = x[:-1] if dn.uses_sparse else x
        img = img[0] if img.shape[0] == 1 else img.transpose(1, 2, 0)
        sparse = x[-1] if dn.uses_sparse else None
        t0 = time.perf_counter()
        kf = dn.prior(img, sparse)
        pred = kf.depth(zero)
        t_ort.append(1e3 * (time.perf_counter() - t0))
        m = acc.update(torch.from_numpy(pred)[None, None], torch.from_numpy(s["depth"])[None])
        if i in pick:
            shown.append(
                {
                    "name": str(f.relative_to(data_root)),
                    "image": img,
                    "gt": s["depth"][0],
                    "sparse": sparse,
                    "depth": pred,
                    "uncertainty": kf.uncertainty,
                    "rmse": float(m["rmse"][0]),
                }
            )
    res = acc.compute()
    res["ms"] = float(np.median(t_ort))
    display(
        Markdown(
            f"Shipped default model on {acc.count} synthetic validation frames (ONNX Runtime, "
            f"{dn.height}x{dn.width}; ms/frame = prior + one decode, median, "
            f"{dn.session_config.threads} ORT thread(s)):\n\n"
            + format_table({f"{dn.modality} / shipped default (ONNX)": res}, first="modality / method")
        )
    )
    show_frames(
        shown,
        f"Shipped default model ({dn.modality}, {dn.height}x{dn.width}, ONNX Runtime, code 0)",
        out / "fig8_default_model.png",
    )
    (out / "default_model_eval.json").write_text(
        json.dumps({"frames": acc.count, "metrics": res, "manifest_source": dn.manifest.get("source")}, indent=2)
    )

# %%
print(f"outputs in {out}: " + ", ".join(sorted(p.name for p in out.iterdir() if p.suffix in (".png", ".json", ".md"))))
print(f"ablation table: {out / f'ablation_seed{SEEDS[0]}' / 'ablation.md'}")
print(f"notebook wall time {time.time() - t_start:.0f} s")
