"""The Table 1 ablation in one command: 4 variants x 4 modalities, same budget, one table.

    python -m train.ablation                                   # default budget (conf/trainer, conf/data)
    python -m train.ablation --out outputs/ablation trainer.max_steps=3000 data.height=224 data.width=224
    python -m train.ablation --variants dit codevio8 --modalities gray grays trainer=gpu

Every cell trains ``python train/fit.py experiment=<variant>_<modality>`` in its own process with the same
Hydra overrides (the budget: ``trainer.max_steps``, ``data.*``, ``trainer=...``), into
``<out>/<variant>_<modality>``, then the best checkpoint (lowest ``val/rmse``; else ``last.ckpt``) is
evaluated with :mod:`train.evaluate` on the validation split (125 noise-free FAST samples for ``*s``). A cell
whose ``eval_depth.json`` exists is not run again (``--force`` re-runs), so an interrupted ablation continues
where it stopped. Writes ``<out>/ablation.md`` (the table) and ``<out>/ablation.json``.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # see train/fit.py: idle OpenMP threads must not spin

import argparse  # noqa: E402
import json  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

from train.metrics import format_table  # noqa: E402

__all__ = ["main", "run_ablation", "VARIANTS", "MODALITIES"]

REPO = Path(__file__).resolve().parents[1]
#: Table 1 order and labels.
VARIANTS = {
    "fastdepth": "FastDepth",
    "codevio32": "CodeVIO (32D)",
    "codevio8": "CodeVIO (8D)",
    "dit": "Ours (DiT)",
}
MODALITIES = {"rgb": "RGB", "gray": "G", "rgbs": "RGB-S", "grays": "G-S"}


def _cell(out: Path, variant: str, modality: str, overrides: list[str], force: bool, eval_args: dict) -> dict:
    from train.evaluate import evaluate_checkpoint

    run = out / f"{variant}_{modality}"
    done = run / "eval_depth.json"
    if done.is_file() and not force:
        print(f"[ablation] {variant}/{modality}: done before, {done}")
        return json.loads(done.read_text())
    cmd = [
        sys.executable,
        str(REPO / "train" / "fit.py"),
        f"experiment={variant}_{modality}",
        f"hydra.run.dir={run}",
        "trainer.enable_progress_bar=false",
        *overrides,
    ]
    print(f"[ablation] {variant}/{modality}: {' '.join(cmd[1:])}", flush=True)
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    t0 = time.time()
    log_path = out / f"{run.name}.log"
    with open(log_path, "w") as logf:
        p = subprocess.run(cmd, cwd=REPO, env=env, stdout=logf, stderr=subprocess.STDOUT)
    if p.returncode != 0:
        raise RuntimeError(f"training {variant}/{modality} failed (exit {p.returncode}); see {log_path}")
    train_s = time.time() - t0
    ckpts = sorted((run / "checkpoints").glob("best-step*.ckpt")) or [run / "checkpoints" / "last.ckpt"]
    res = evaluate_checkpoint(ckpts[-1], None, **eval_args)
    res["train_wall_s"] = train_s
    res["overrides"] = overrides
    done.write_text(json.dumps(res, indent=2))
    return res


def run_ablation(
    out: str | Path,
    overrides: list[str] | None = None,
    variants: list[str] | None = None,
    modalities: list[str] | None = None,
    force: bool = False,
    timing_frames: int = 30,
    device: str = "cpu",
) -> dict:
    """Train and evaluate every (variant, modality) cell; returns ``{"table": markdown, "cells": ...}``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    variants = list(variants or VARIANTS)
    modalities = list(modalities or MODALITIES)
    for v in variants:
        if v not in VARIANTS:
            raise ValueError(f"variant {v!r} not in {list(VARIANTS)}")
    for m in modalities:
        if m not in MODALITIES:
            raise ValueError(f"modality {m!r} not in {list(MODALITIES)}")
    overrides = list(overrides or [])
    eval_args = {"split": "val", "device": device, "timing_frames": timing_frames, "median_baseline": True}
    results, rows = {}, {}
    for m in [m for m in MODALITIES if m in modalities]:  # Table 1 order
        for v in [v for v in VARIANTS if v in variants]:
            r = _cell(out, v, m, overrides, force, eval_args)
            results[f"{v}_{m}"] = r
            rows[f"{MODALITIES[m]} / {VARIANTS[v]}"] = {**r["metrics"], "ms": r["ms"]}
        itp = next(
            (r["interpolation"] for k, r in results.items() if k.endswith(f"_{m}") and "interpolation" in r), None
        )
        if itp is not None:
            rows[f"{MODALITIES[m]} / interpolation of the sparse input (reference)"] = itp
        med = next(r["median"] for k, r in results.items() if k.endswith(f"_{m}") and "median" in r)
        rows[f"{MODALITIES[m]} / median GT (reference)"] = med
    table = format_table(rows, first="modality / method")
    any_r = next(iter(results.values()))
    header = (
        f"Table 1 ablation on {any_r['data']['kind']} data ({any_r['data']['root']}, "
        f"{any_r['frames']} validation frames), overrides: {' '.join(overrides) or '(defaults)'}; "
        "ms/frame: batch 1, "
        f"{any_r['timing']['threads']} threads, {any_r['timing']['device']}."
    )
    (out / "ablation.md").write_text(header + "\n\n" + table + "\n")
    summary = {"overrides": overrides, "header": header, "table": table, "cells": results}
    (out / "ablation.json").write_text(json.dumps(summary, indent=2))
    return summary


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter
    )
    ap.add_argument("overrides", nargs="*", help="Hydra overrides applied to every cell (the shared budget)")
    ap.add_argument("--out", default="outputs/ablation", help="output folder (default: outputs/ablation)")
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--modalities", nargs="+", default=list(MODALITIES), choices=list(MODALITIES))
    ap.add_argument("--force", action="store_true", help="re-run cells that are already done")
    ap.add_argument("--timing-frames", type=int, default=30, help="batch-1 forward passes timed per cell")
    ap.add_argument("--device", default="cpu", help="evaluation device")
    a = ap.parse_args(argv)
    try:
        s = run_ablation(a.out, a.overrides, a.variants, a.modalities, a.force, a.timing_frames, a.device)
    except (RuntimeError, ValueError, FileNotFoundError) as e:
        sys.exit(f"ablation: {e}")
    print("\n" + s["header"] + "\n\n" + s["table"])
    print(f"\nwrote {Path(a.out) / 'ablation.md'} and {Path(a.out) / 'ablation.json'}")


if __name__ == "__main__":
    main()
