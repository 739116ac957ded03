"""The Table 1 ablation in one command: 4 variants x 4 modalities, same budget, one table.

    python -m train.ablation                                   # default budget (conf/trainer, conf/data)
    python -m train.ablation --out outputs/ablation trainer.max_steps=3000 data.height=224 data.width=224
    python -m train.ablation --variants dit codevio8 --modalities gray grays trainer=gpu
    python -m train.ablation --seeds 0 1 --jobs 8 --device cuda trainer=gpu data.num_workers=1 model.net.relative=true

Every cell trains ``python train/fit.py experiment=<variant>_<modality>`` in its own process with the same
Hydra overrides (the budget: ``trainer.max_steps``, ``data.*``, ``trainer=...``), into
``<out>/<variant>_<modality>``, then the best checkpoint (lowest ``val/rmse``; else ``last.ckpt``) is
evaluated with :mod:`train.evaluate` on the validation split (125 noise-free FAST samples for ``*s``). A cell
whose ``eval_depth.json`` exists is not run again (``--force`` re-runs), so an interrupted ablation continues
where it stopped. Writes ``<out>/ablation.md`` (the table) and ``<out>/ablation.json``.

``--jobs N`` trains up to N cells at once (each its own process; on a GPU machine give each a data loader worker).
``--seeds S ...`` runs the whole table once per training seed (``seed=S``) into ``<out>/seed<S>/`` and adds, per
modality, the order of the variants by RMSE on each seed and whether the seeds agree on it (``<out>/ablation.md``,
``<out>/ablation.json``). Every cell gets the same data, which the first cell renders when it is missing: with
``--jobs`` above 1 render it first (``data.root``), or the cells race to write it.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # see train/fit.py: idle OpenMP threads must not spin

import argparse  # noqa: E402
import json  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from concurrent.futures import ThreadPoolExecutor  # noqa: E402
from pathlib import Path  # noqa: E402

from train.metrics import format_table  # noqa: E402

__all__ = ["main", "parse_args", "run_ablation", "run_seeds", "variant_order", "VARIANTS", "MODALITIES"]

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


def _check_names(variants: list[str] | None, modalities: list[str] | None) -> tuple[list[str], list[str]]:
    """Validated variants and modalities, in Table 1 order."""
    for v in variants or ():
        if v not in VARIANTS:
            raise ValueError(f"variant {v!r} not in {list(VARIANTS)}")
    for m in modalities or ():
        if m not in MODALITIES:
            raise ValueError(f"modality {m!r} not in {list(MODALITIES)}")
    variants, modalities = variants or list(VARIANTS), modalities or list(MODALITIES)
    return [v for v in VARIANTS if v in variants], [m for m in MODALITIES if m in modalities]


def run_ablation(
    out: str | Path,
    overrides: list[str] | None = None,
    variants: list[str] | None = None,
    modalities: list[str] | None = None,
    force: bool = False,
    timing_frames: int = 30,
    device: str = "cpu",
    jobs: int = 1,
) -> dict:
    """Train and evaluate every (variant, modality) cell; returns ``{"table": markdown, "cells": ...}``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    variants, modalities = _check_names(variants, modalities)
    overrides = list(overrides or [])
    eval_args = {"split": "val", "device": device, "timing_frames": timing_frames, "median_baseline": True}
    cells = [(v, m) for m in modalities for v in variants]  # Table 1 order
    with ThreadPoolExecutor(max(1, int(jobs))) as pool:
        done = dict(zip(cells, pool.map(lambda vm: _cell(out, *vm, overrides, force, eval_args), cells), strict=True))
    results, rows = {}, {}
    for m in modalities:
        for v in variants:
            r = done[(v, m)]
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


def variant_order(cells: dict, modality: str) -> list[str]:
    """The variants of ``modality`` in ``cells`` (``{"<variant>_<modality>": result}``), best RMSE first."""
    have = [v for v in VARIANTS if f"{v}_{modality}" in cells]
    return sorted(have, key=lambda v: cells[f"{v}_{modality}"]["metrics"]["rmse"])


def run_seeds(
    out: str | Path,
    seeds: list[int],
    overrides: list[str] | None = None,
    variants: list[str] | None = None,
    modalities: list[str] | None = None,
    force: bool = False,
    timing_frames: int = 30,
    device: str = "cpu",
    jobs: int = 1,
) -> dict:
    """:func:`run_ablation` once per training seed (``<out>/seed<S>/``, ``seed=S``), the cells of every seed in one
    pool of ``jobs``; adds each modality's variant order per seed and whether the seeds agree on it."""
    out = Path(out)
    variants, modalities = _check_names(variants, modalities)
    if not seeds or len(set(seeds)) != len(seeds):
        raise ValueError(f"seeds must be distinct and at least one, got {seeds!r}")
    base = [o for o in overrides or [] if not o.startswith("seed=")]
    per_jobs = max(1, int(jobs) // len(seeds))
    with ThreadPoolExecutor(len(seeds)) as pool:
        runs = list(
            pool.map(
                lambda s: run_ablation(
                    out / f"seed{s}", base + [f"seed={s}"], variants, modalities, force, timing_frames, device, per_jobs
                ),
                seeds,
            )
        )
    order = {
        m: {str(s): variant_order(r["cells"], m) for s, r in zip(seeds, runs, strict=True)} for m in modalities
    }
    agree = {m: len({tuple(o) for o in order[m].values()}) == 1 for m in modalities}
    seed_list = ", ".join(map(str, seeds))
    lines = [f"Table 1 over training seeds {seed_list}; overrides: {' '.join(base) or '(defaults)'}.", ""]
    lines += ["| modality | " + " | ".join(f"order, seed {s} (best first)" for s in seeds) + " | same order |"]
    lines += ["|---" * (len(seeds) + 2) + "|"]
    for m in modalities:
        cols = [" < ".join(VARIANTS[v] for v in order[m][str(s)]) for s in seeds]
        lines.append(f"| {MODALITIES[m]} | " + " | ".join(cols) + f" | {'yes' if agree[m] else 'no'} |")
    for s, r in zip(seeds, runs, strict=True):
        lines += ["", f"### Training seed {s}", "", r["header"], "", r["table"]]
    text = "\n".join(lines) + "\n"
    (out / "ablation.md").write_text(text)
    summary = {"seeds": list(seeds), "overrides": base, "order": order, "same_order": agree, "runs": runs}
    (out / "ablation.json").write_text(json.dumps(summary, indent=2))
    return {**summary, "text": text}


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line; Hydra overrides (``key=value``) may stand anywhere, also after ``--variants`` or
    ``--seeds``, whose lists would otherwise swallow them.

    >>> a = parse_args(["--variants", "dit", "fastdepth", "trainer=gpu", "--seeds", "0", "1", "seed=3"])
    >>> a.variants, a.seeds, a.overrides
    (['dit', 'fastdepth'], [0, 1], ['trainer=gpu', 'seed=3'])
    >>> parse_args(["--out", "runs/lr=1e-3", "model.kl_weight=0"]).out
    'runs/lr=1e-3'
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    valued = ("--out", "--timing-frames", "--device", "--jobs")  # options that take one value (it may hold '=')
    is_override = [
        "=" in a and not a.startswith("-") and (i == 0 or argv[i - 1] not in valued) for i, a in enumerate(argv)
    ]
    overrides = [a for a, o in zip(argv, is_override, strict=True) if o]
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
    ap.add_argument("--jobs", type=int, default=1, help="cells trained at once (default 1)")
    ap.add_argument("--seeds", type=int, nargs="+", help="training seeds: the table once per seed, and their orders")
    a = ap.parse_args([x for x, o in zip(argv, is_override, strict=True) if not o])
    a.overrides = overrides
    return a


def main(argv: list[str] | None = None) -> None:
    a = parse_args(argv)
    if a.jobs < 1:
        sys.exit(f"ablation: --jobs must be at least 1, got {a.jobs}")
    try:
        if a.seeds:
            s = run_seeds(
                a.out, a.seeds, a.overrides, a.variants, a.modalities, a.force, a.timing_frames, a.device, a.jobs
            )
            print("\n" + s["text"])
        else:
            s = run_ablation(a.out, a.overrides, a.variants, a.modalities, a.force, a.timing_frames, a.device, a.jobs)
            print("\n" + s["header"] + "\n\n" + s["table"])
    except (RuntimeError, ValueError, FileNotFoundError) as e:
        sys.exit(f"ablation: {e}")
    print(f"\nwrote {Path(a.out) / 'ablation.md'} and {Path(a.out) / 'ablation.json'}")


if __name__ == "__main__":
    main()
