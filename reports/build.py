"""Regenerate ``reports/README.md``, the collected current figures, from the committed result files.

    python reports/build.py            # rewrite reports/README.md and reports/peers.md
    python reports/build.py --check    # exit 1 when reports/README.md differs from what the sources give

Sources (all committed): the benchmark JSON in ``benchmarks/results/`` (``models.json``, ``bench_train.json``,
``bench_dense_*.json``, ``bench_coast.json``, ``jacobian.json`` / ``network.json`` and their copies in
sub-folders, ``slam/bench_slam.json``), the shipped model's ``runtime/assets/default_model/val_metrics.json``, and the
outputs of the committed notebooks ``notebooks/01_depth_modalities.ipynb`` and
``notebooks/03_trajectories.ipynb`` (the tables they display). Every section names the command that produced
its source, the machine (from the JSON or the notebook's printout) and the date.

The JSON files carry no date: the date given is the committer date of the last commit that changed the source
file (``git log -1 --format=%cI -- FILE``); notebook 03 prints the date of its run, which is used instead. A
source that is not committed yet (or has local changes) is dated by its file modification time and marked *not
committed*: commit the sources, run this script again and commit ``reports/README.md``
(``tests/test_reports.py`` checks that the committed README equals this script's output, so it cannot drift
from the results).
"""

from __future__ import annotations

import argparse
import datetime as dt
import functools
import hashlib
import json
import math
import re
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results"
README = REPO / "reports" / "README.md"

__all__ = ["build", "records", "source_files", "file_date", "main"]


# ------------------------------------------------------------------------------------------------ helpers
def _git(*args: str) -> str | None:
    try:
        r = subprocess.run(["git", *args], cwd=REPO, capture_output=True, text=True, timeout=30, check=False)
    except (OSError, subprocess.SubprocessError):
        return None
    return r.stdout.strip() if r.returncode == 0 else None


def file_date(path: Path) -> str:
    """``YYYY-MM-DD HH:MM UTC`` of the last commit that changed ``path`` (or its mtime, marked)."""
    rel = path.relative_to(REPO).as_posix()
    dirty = _git("status", "--porcelain", "--", rel)
    stamp = None if dirty else _git("log", "-1", "--format=%cI", "--", rel)
    if stamp:
        t = dt.datetime.fromisoformat(stamp).astimezone(dt.timezone.utc)
        return t.strftime("%Y-%m-%d %H:%M UTC") + " (commit)"
    t = dt.datetime.fromtimestamp(path.stat().st_mtime, dt.timezone.utc)
    return t.strftime("%Y-%m-%d %H:%M UTC") + " (file mtime: **not committed**)"


def _load(path: Path) -> dict:
    # the benchmarks write NaN for missing metrics (json.dumps default); json.loads reads it back as nan
    return json.loads(path.read_text())


def _num(x, digits: int = 3, scale: float = 1.0, suffix: str = "") -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "–"
    return f"{x * scale:.{digits}f}{suffix}"


def _mean_std(values, digits: int = 1, scale: float = 1.0) -> str:
    v = [x * scale for x in values if x is not None and math.isfinite(x)]
    if not v:
        return "–"
    m = sum(v) / len(v)
    if len(v) == 1:
        return f"{m:.{digits}f}"
    s = math.sqrt(sum((x - m) ** 2 for x in v) / len(v))
    return f"{m:.{digits}f} ± {s:.{digits}f}"


def _rel_path(p) -> str:
    """Paths inside this repository's results folder shown relative to the repository (machine-independent)."""
    s = str(p)
    m = re.search(r"(benchmarks/results(/.*)?)$", s)
    return m.group(1) if m else s


def _machine(m: dict | None) -> str:
    """One line from the machine fields the benchmarks record (their names differ between scripts)."""
    if not m:
        return "not recorded"
    cpu = m.get("cpu") or m.get("processor") or m.get("machine")
    cores = m.get("cores") or m.get("cpus") or m.get("cpu_count")
    parts = [cpu, f"{cores} cores" if cores else None, m.get("platform")]
    if m.get("torch"):
        parts.append(f"torch {m['torch']}")
    if m.get("onnxruntime"):
        parts.append(f"onnxruntime {m['onnxruntime']}")
    load = m.get("loadavg") or m.get("loadavg_start") or m.get("load_avg_1min")
    if isinstance(load, list):
        load = load[0]
    if load is not None:
        parts.append(f"load {load:.1f} at the start")
    return ", ".join(str(p) for p in parts if p)


def _flags(cfg: dict, spec: list[tuple[str, str]]) -> list[str]:
    """Command-line flags from a saved argparse namespace: ``spec`` = [(key, flag)]; lists expand, booleans
    become the flag when true, None is left out."""
    out: list[str] = []
    for key, flag in spec:
        v = cfg.get(key)
        if v is None or v is False or (isinstance(v, list) and not v):
            continue
        if v is True:
            out.append(flag)
        elif isinstance(v, list):
            out += [flag, *map(str, v)]
        else:
            out += [flag, _rel_path(v) if isinstance(v, str) else f"{v:g}" if isinstance(v, float) else str(v)]
    return out


def _source_block(files: list[Path], command: str, machine: str, note: str = "", date: str | None = None) -> str:
    src = ", ".join(f"[`{p.relative_to(REPO).as_posix()}`](../{p.relative_to(REPO).as_posix()})" for p in files)
    dates = date or "; ".join(file_date(p) for p in files)
    lines = [f"- source: {src}", f"- command: `{command}`", f"- machine: {machine}", f"- date: {dates}"]
    if note:
        lines.append(f"- note: {note}")
    return "\n".join(lines)


def _table(head: list[str], rows: list[list[str]]) -> str:
    return "\n".join(
        ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)] + ["| " + " | ".join(r) + " |" for r in rows]
    )


# ------------------------------------------------------------------------------------------------ notebooks
def _nb_outputs(path: Path) -> list[dict]:
    nb = json.loads(path.read_text())
    return [o for c in nb.get("cells", []) if c.get("cell_type") == "code" for o in c.get("outputs", [])]


def _text(x) -> str:
    return "".join(x) if isinstance(x, list) else str(x or "")


def _nb_markdown(path: Path, marker: str) -> str | None:
    """The first markdown output of a notebook that contains ``marker``."""
    for o in _nb_outputs(path):
        md = _text(o.get("data", {}).get("text/markdown"))
        if marker in md:
            return md.strip()
    return None


def _nb_line(path: Path, prefix: str) -> str | None:
    """The first printed line of a notebook that starts with ``prefix`` (without it)."""
    for o in _nb_outputs(path):
        if o.get("output_type") == "stream":
            for line in _text(o.get("text")).splitlines():
                if line.startswith(prefix):
                    return line[len(prefix) :].strip()
    return None


# ------------------------------------------------------------------------------------------------ sections
def _protocol_tables(path: Path, what: str) -> list[str]:
    """The shipped model against the interpolation of its own sparse points and the median GT, per frame set."""
    d = _load(path)
    p = d.get("protocol", {})
    out = [
        f"The shipped default model, {what} ({p.get('points')} FAST points, noise {p.get('noise_std_m')} m, "
        f"outliers {_num(p.get('outlier_frac'), 0, 100, ' %')}, code c = 0), against the linear interpolation of "
        "the same points (nearest outside their hull) and the per-image median of the true depth:",
        "",
    ]
    rows = []
    for name, r in d.get("sets", {}).items():
        for row, m in r.get("rows", {}).items():
            rows.append(
                [f"{name} ({r.get('frames')})", row, _num(m.get("rmse")), _num(m.get("abs_rel")), _num(m.get("mae"))]
                + [_num(m.get(k), 1, 100, " %") for k in ("delta1", "delta2", "delta3")]
                + [_num(m.get("max_frame_abs_rel"))]
            )
    out += [
        _table(["frames", "method", "RMSE [m]", "AbsRel", "MAE [m]", "δ1", "δ2", "δ3", "max frame AbsRel"], rows),
        "",
        _source_block(
            [path],
            "dit-eval depth model_dir=runtime/assets/default_model real=../shared/data/rgbd_real sim.n_val=40 "
            f"protocol={p.get('name', 'gs')} out={path.relative_to(REPO).as_posix()}",
            "see runtime/assets/default_model/README.md",
        ),
        "",
    ]
    return out


def _table1_gpu(path: Path) -> list[str]:
    """Table 1 at a GPU budget on two training seeds (``train.ablation --seeds``), with each modality's order."""
    d = _load(path)
    seeds = list(d.get("seeds", {}))
    st = d.get("setting", {})
    out = [
        f"### Table 1 at a GPU budget, training seeds {' and '.join(seeds)}",
        "",
        f"{st.get('steps')} steps x batch {st.get('batch')} per cell at {st.get('size')}, {st.get('train_frames')} "
        f"realistic training frames, {st.get('val_frames')} validation frames, protocol {st.get('protocol')}; best "
        f"checkpoint: {st.get('best_checkpoint')}. Relative formulation: {st.get('relative')}.",
        "",
    ]
    first = d["seeds"][seeds[0]]["rows"]
    rows = []
    for name in first:
        cells = [d["seeds"][s]["rows"].get(name, {}) for s in seeds]
        rows.append(
            [name]
            + [_num(c.get("rmse")) for c in cells]
            + [_num(c.get("abs_rel")) for c in cells]
            + [_num(c.get("delta1"), 1, 100, " %") for c in cells]
        )
    head = (
        ["modality / method"]
        + [f"RMSE [m], seed {s}" for s in seeds]
        + [f"AbsRel, seed {s}" for s in seeds]
        + [f"δ1, seed {s}" for s in seeds]
    )
    out += [_table(head, rows), ""]
    order_rows = [
        [m, *(" < ".join(d["order"][m][s]) for s in seeds), "yes" if d["same_order"][m] else "no"]
        for m in d.get("order", {})
    ]
    out += [
        "The order of the variants by RMSE (best first) on each seed:",
        "",
        _table(["modality", *(f"seed {s}" for s in seeds), "same order"], order_rows),
        "",
    ]
    f = d.get("followup_l1_depth_loss")
    if f:
        g = f["g_s_rmse_m"]
        ks = sorted(g["dit_nll"], key=int)
        out += [
            f"G-S RMSE [m] over training seeds {', '.join(ks)} (the follow-up run added seeds 2 and 3, and DiT with "
            "an L1 depth loss, which lost):",
            "",
            _table(
                ["method", *(f"seed {k}" for k in ks)],
                [
                    [label, *(_num(g[key][k]) for k in ks)]
                    for key, label in (
                        ("fastdepth", "FastDepth"),
                        ("dit_nll", "Ours (DiT), Eq. 6"),
                        ("dit_l1", "Ours (DiT), L1 depth + Eq. 6 for the uncertainty"),
                        ("interpolation", "interpolation (reference)"),
                    )
                ],
            ),
            "",
        ]
    out += [_source_block([path], d.get("command", ""), d.get("device", "not recorded")), ""]
    return out


def _table1() -> list[str]:
    out = ["## Table 1: depth networks x input modalities", ""]
    nb = REPO / "notebooks" / "01_depth_modalities.ipynb"
    table = _nb_markdown(nb, "| modality / method |") if nb.is_file() else None
    if table:
        head, _, body = table.partition("\n\n")
        out += [
            "Accuracy on synthetic validation frames after a short CPU training budget per cell (the committed run "
            "of notebook 01, training seed 0; its intro states the budget, and the notebook compares the order of "
            "the variants over two training seeds). Without sparse depth the order changes between seeds: this "
            "budget cannot rank those variants.",
            "",
            body.strip() if body else head,
            "",
            _source_block(
                [nb],
                "python -m tests.notebooks.run notebooks/01_depth_modalities.ipynb --inplace",
                _nb_line(nb, "machine") or "not printed",
                f"the notebook's setting: {head.strip()}" if body else "",
            ),
            "",
        ]
        shipped = _nb_markdown(nb, "shipped default (ONNX)")
        if shipped:
            out += ["The default model shipped when notebook 01 last ran, through ONNX Runtime, same frames:", ""]
            out += [shipped.partition("\n\n")[2].strip() or shipped, ""]
    gpu = RESULTS / "depth_ablations" / "table1_gpu.json"
    if gpu.is_file():
        out += _table1_gpu(gpu)
    vm = REPO / "runtime" / "assets" / "default_model" / "val_metrics.json"
    if vm.is_file():
        m = _load(vm)
        man = _load(vm.parent / "manifest.json") if (vm.parent / "manifest.json").is_file() else {}
        out += [
            f"The shipped default model (`{man.get('model', '?')}` / `{man.get('modality', '?')}`, "
            f"{man.get('height', '?')}x{man.get('width', '?')}, ONNX Runtime, code 0) on {m.get('frames', '?')} "
            "regenerated synthetic validation frames (checked by `tests/test_default_model.py`):",
            "",
            _table(
                ["RMSE [m]", "iRMSE [1/m]", "AbsRel", "MAE [m]", "δ1", "δ2", "δ3", "ms/frame"],
                [
                    [_num(m.get("rmse")), _num(m.get("irmse")), _num(m.get("abs_rel")), _num(m.get("mae"))]
                    + [_num(m.get(k), 1, 100, " %") for k in ("delta1", "delta2", "delta3")]
                    + [_num(m.get("ms"), 1)]
                ],
            ),
            "",
            _source_block(
                [vm],
                "python benchmarks/eval_onnx_depth.py --model runtime/assets/default_model --n-val 20 "
                + ("--realism " if m.get("realism") else "")
                + "--out runtime/assets/default_model/val_metrics.json",
                "not recorded in the JSON (see runtime/assets/default_model/README.md: 2-core AMD EPYC, CPU only)",
            ),
            "",
        ]
    for name, what in (("protocol_gs.json", "G-S protocol"), ("protocol_slam.json", "SLAM-like sparse input")):
        pj = REPO / "runtime" / "assets" / "default_model" / name
        if pj.is_file():
            out += _protocol_tables(pj, what)
    mj = RESULTS / "models.json"
    if mj.is_file():
        d = _load(mj)
        c = d.get("config", {})
        rows = [
            [
                r["model"],
                r["modality"],
                _num(r.get("params"), 2, 1e-6),
                _num(r.get("infer_params"), 2, 1e-6),
                _num(r.get("gflops"), 2),
                _num(r.get("forward_ms_median"), 1),
                _num(r.get("ratio_vs_fastdepth"), 2, suffix="x"),
                _num(r.get("prior_ms"), 1),
                _num(r.get("decoder_b8_ms"), 1),
            ]
            for r in d.get("rows", [])
        ]
        spec = [
            ("models", "--models"),
            ("modalities", "--modalities"),
            ("height", "--height"),
            ("width", "--width"),
            ("width_mult", "--width-mult"),
            ("runs", "--runs"),
            ("warmup", "--warmup"),
            ("threads", "--threads"),
            ("channels_last", "--channels-last"),
            ("out", "--out"),
        ]
        cmd = " ".join(
            ["python benchmarks/bench_models.py", *_flags(c, spec)] + ([] if c.get("parts", True) else ["--no-parts"])
        )
        out += [
            f"Inference cost (torch eager, batch 1, {c.get('height')}x{c.get('width')}, {c.get('threads')} threads; "
            "forward = median; decoder b8 = the batch of 8 codes of the FD Jacobian):",
            "",
            _table(
                [
                    "model",
                    "modality",
                    "params [M]",
                    "inference params [M]",
                    "GFLOPs",
                    "forward [ms]",
                    "vs FastDepth",
                    "prior [ms]",
                    "decoder b8 [ms]",
                ],
                rows,
            ),
            "",
            _source_block([mj], cmd, _machine(d.get("machine"))),
            "",
        ]
    bt = RESULTS / "bench_train.json"
    if bt.is_file():
        d = _load(bt)
        env = d.get("env", {})
        rows = d.get("rows", [])
        cmd = " ".join(
            [
                "python benchmarks/bench_train.py",
                "--variants",
                *dict.fromkeys(r["variant"] for r in rows),
                "--modalities",
                *dict.fromkeys(r["modality"] for r in rows),
            ]
            + _flags(
                {
                    "size": env.get("size"),
                    "batch": env.get("batch"),
                    "steps": env.get("steps"),
                    "threads": env.get("threads"),
                },
                [("size", "--size"), ("batch", "--batch"), ("steps", "--steps"), ("threads", "--threads")],
            )
        )
        out += [
            f"Training throughput ({'x'.join(map(str, env.get('size', [])))}, batch {env.get('batch')}; step = "
            "forward + loss + backward + AdamW; data = h5 read + augmentation + sparse sampling):",
            "",
            _table(
                ["variant", "modality", "step [ms]", "images/s (step)", "data [ms/image]", "images/s (serial)"],
                [
                    [
                        r["variant"],
                        r["modality"],
                        _num(r.get("step_ms"), 0),
                        _num(r.get("step_img_s"), 2),
                        _num(r.get("data_ms_per_img"), 1),
                        _num(r.get("combined_img_s"), 2),
                    ]
                    for r in rows
                ],
            ),
            "",
            _source_block([bt], cmd, _machine(env), "command reconstructed from the JSON's `env` and rows"),
            "",
        ]
    return out


DENSE_LABEL = {
    "sparse": "sparse",
    "dense_eq13": "dense, Eq. 13",
    "dense_eq13_14": "dense, Eq. 13 + 14",
    "dense_gt_eq13_14": "dense, Eq. 13 + 14, rendered depth",
    "dense_gt_eq13": "dense, Eq. 13, rendered depth",
    "dense_gt_eq14": "dense, Eq. 14, rendered depth",
}


@functools.cache
def _shipped_sha256(name: str) -> str | None:
    """SHA-256 of one file of the shipped model (None when it is missing), read once per build."""
    f = REPO / "runtime" / "assets" / "default_model" / name
    return hashlib.sha256(f.read_bytes()).hexdigest() if f.is_file() else None


def _dense_model(d: dict) -> str:
    """Which depth network a ``bench_dense`` result used (its ``model``, written since ``--model`` exists)."""
    m = d.get("model")
    if m is None:  # written before the runs named their model: the first shipped model was the only one
        return "the first shipped depth model (2026-11-21, 600 steps; regenerated-val RMSE 0.293 m)"
    sha = m.get("sha256") or {}
    same = bool(sha) and all(_shipped_sha256(f) == h for f, h in sha.items())
    if same:
        return "the shipped depth model"
    if str(m.get("dir", "")).rstrip("/").endswith("runtime/assets/default_model"):
        return "an earlier shipped depth model (its files differ from today's)"
    return f"the depth model in `{m.get('dir')}`"


def _table3() -> list[str]:
    out = ["## Table 3: sparse vs dense (tight coupling)", ""]
    for f in sorted(RESULTS.glob("bench_dense*.json")):
        d = _load(f)
        a = d.get("args", {})
        rows = d.get("rows", [])
        groups: dict[tuple[str, str], list[dict]] = {}
        for r in rows:
            groups.setdefault((r["preset"], r["mode"]), []).append(r)
        stages = "abc" + ("i" if any("rmse_i" in r for r in rows) else "")  # (i): results since 2026-11-28
        body = []
        for (preset, mode), rs in groups.items():
            body.append(
                [
                    preset,
                    DENSE_LABEL.get(mode, mode),
                    str(len(rs)),
                    _mean_std([r["ate"] for r in rs], 1, 1e3),
                    " / ".join(_num(r["ate"], 1, 1e3) for r in rs),
                    _mean_std([r["fps"] for r in rs], 0),
                ]
                + [_mean_std([r.get(f"rmse_{k}") for r in rs], 3) for k in stages]
            )
        spec = [
            ("presets", "--presets"),
            ("sequences", "--sequences"),
            ("seeds", "--seeds"),
            ("duration", "--duration"),
            ("scale", "--scale"),
            ("modes", "--modes"),
            ("set", "--set"),
            ("slam_set", "--slam-set"),
            ("model", "--model"),
            ("data", "--data"),
            ("out", "--out"),
        ]
        # only bars whose modes ran (results written before bench_dense.bars skipped the others hold NaN there)
        bars = {
            k: v
            for k, v in d.get("bars", {}).items()
            if all(math.isfinite(x) for x in v.values() if isinstance(x, float))
        }
        where = (
            f"The sequence folders given ({len(a['sequences'])}, seed from the folder name; the note says what they "
            "are)"
            if a.get("sequences")
            else f"Synthetic `sim/` sequences, {a.get('duration', '?'):g} s, seeds {a.get('seeds')}, scale "
            f"{a.get('scale', 1.0):g}"
        )
        out += [
            f"{where}, {_dense_model(d)}; mean ± std over seeds (ATE: SE(3)-aligned RMSE; depth "
            "RMSE on the keyframes that held a code: (a) sparse map points, (b) prior c = 0, (c) optimised code"
            + (", (i) the network's sparse input interpolated, the reference it has to beat" if "i" in stages else "")
            + "):",
            "",
            _table(
                [
                    "sequence",
                    "mode",
                    "seeds",
                    "ATE [mm]",
                    "ATE per seed [mm]",
                    "FPS",
                    *(f"RMSE ({k}) [m]" for k in stages),
                ],
                body,
            ),
            "",
            *(
                [
                    "Quality bars of the tight-coupling issue: "
                    + "; ".join(f"{k} {'met' if v.get('met') else '**not met**'}" for k, v in bars.items()),
                    "",
                ]
                if bars
                else []
            ),
            _source_block(
                [f],
                " ".join(
                    [
                        "python benchmarks/bench_dense.py",
                        *(["--presets"] if a.get("presets") == [] else []),
                        *_flags(a, spec),
                    ]
                ),
                _machine(d.get("machine")),
                note=d.get("note", ""),
            ),
            "",
        ]
    nb = REPO / "notebooks" / "03_trajectories.ipynb"
    table = _nb_markdown(nb, "Table 3 shape") if nb.is_file() else None
    if table:
        head, _, body = table.partition("\n\n")
        wall = _nb_line(nb, "notebook wall time")
        out += [
            f"The committed run of notebook 03 ({head.strip().rstrip(':')}; Fig. 10 is in the notebook):",
            "",
            body.strip(),
            "",
            _source_block(
                [nb],
                "nice -n 5 python -m tests.notebooks.run notebooks/03_trajectories.ipynb --inplace",
                _nb_line(nb, "machine") or "not printed",
                "; ".join(
                    x
                    for x in (f"notebook wall time {wall}" if wall else "", f"code: {_nb_line(nb, 'code')}")
                    if x and not x.endswith("None")
                ),
                date=f"{_nb_line(nb, 'date')} (printed by the run)" if _nb_line(nb, "date") else None,
            ),
            "",
        ]
    return out


def _dense_map() -> list[str]:
    """Accuracy and completeness of the fused dense map (``benchmarks/results/dense_map.json``)."""
    f = RESULTS / "dense_map.json"
    if not f.is_file():
        return []
    d = _load(f)
    thr = 100 * d.get("threshold_m", 0.05)
    body = []
    for name, seq in d.get("sequences", {}).items():
        where = f"{name} ({seq.get('kind', '?')}" + (
            f", ATE {_num(seq['ate_se3_rmse_m'], 3)} m)" if "ate_se3_rmse_m" in seq else ")"
        )
        for row, r in seq.get("rows", {}).items():
            body.append(
                [
                    where,
                    row,
                    f"{r['n_map']:,}",
                    _num(r["accuracy"], 3),
                    _num(r["acc_median_m"], 3),
                    _num(r["completeness"], 3),
                    _num(r["comp_median_m"], 3),
                ]
            )
            where = ""
    return [
        "## The fused dense map: accuracy and completeness",
        "",
        f"Fraction of map points within {thr:g} cm of the ground-truth surface (accuracy) and of ground-truth "
        f"points within {thr:g} cm of the map (completeness), with the median distances [m]. Synthetic: "
        "`dit-slam`'s `dense_map.ply`, SE(3)-aligned to the ground truth as the ATE, against the rendered depth of "
        "its keyframes; real (`../shared/data/rgbd_real`): the network's prior (125 FAST points of true depth, "
        "the G-S protocol) fused at the recorded poses, against the recorded depth; the rows below the first "
        "fuse the interpolated sparse points or the true depth with the same fusion. Mesh rows: the surface of the "
        "TSDF of the same depth maps (`dense_mesh.ply`, `runtime/dense/tsdf.py`), scored by points sampled "
        "uniformly on its triangles (the points column counts them):",
        "",
        _table(["sequence", "map", "points", "accuracy", "acc. median", "completeness", "compl. median"], body),
        "",
        _source_block([f], d.get("command", "python benchmarks/bench_dense_map.py"), _machine(d.get("machine"))),
        "",
    ]


def _jacobian() -> list[str]:
    out = ["## The code Jacobian (Eq. 17): accuracy against autograd (Fig. 6) and speed ratios", ""]
    jfiles = sorted(RESULTS.rglob("jacobian.json"), key=lambda p: (len(p.parts), str(p)))
    rows = []
    for f in jfiles:
        d = _load(f)
        b, fx = d["best"]["all_dims"], d["best"]["at_fixed_delta"]
        m = d.get("model", {})
        rows.append(
            [
                f"`{f.relative_to(RESULTS).as_posix()}`",
                f"{m.get('source')} {m.get('height')}x{m.get('width')}",
                f"{b['delta']:.2g}",
                _num(b["mean_abs"], 2, 1e3),
                _num(b["rel_mean"], 1, 100, " %"),
                _num(fx["mean_abs"], 2, 1e3),
                _num(fx["rel_mean"], 1, 100, " %"),
                _num(fx["over_best"], 2, suffix="x"),
            ]
        )
    if rows:
        out += [
            "Finite differences through ONNX Runtime against `torch.autograd` (forward mode) on the same "
            "weights, mean |error| over pixels, dimensions, frames and codes:",
            "",
            _table(
                [
                    "result",
                    "model",
                    "best δ",
                    "error at best [mm/unit]",
                    "of mean abs(J)",
                    "error at δ = 1e-2 [mm/unit]",
                    "of mean abs(J)",
                    "vs best",
                ],
                rows,
            ),
            "",
        ]
    spec_j = [
        ("model", "--model"),
        ("ckpt", "--ckpt"),
        ("data", "--data"),
        ("frames", "--frames"),
        ("random_codes", "--random-codes"),
        ("delta_min", "--delta-min"),
        ("delta_max", "--delta-max"),
        ("per_decade", "--per-decade"),
        ("fixed_delta", "--fixed-delta"),
        ("threads", "--threads"),
        ("seed", "--seed"),
        ("out", "--out"),
    ]
    standin = [("modality", "--modality"), ("height", "--height"), ("width", "--width"), ("width_mult", "--width-mult")]
    for f in jfiles:
        d = _load(f)
        c = d.get("config", {})
        flags = _flags(c, spec_j + ([] if c.get("model") else standin))
        flags += [] if c.get("per_dim", True) else ["--no-per-dim"]
        out += [f"`{f.relative_to(RESULTS).as_posix()}`: {d.get('model', {}).get('description', '')}", ""]
        out += [
            _source_block([f], " ".join(["python benchmarks/bench_jacobian.py", *flags]), _machine(d.get("machine"))),
            "",
        ]

    nfiles = sorted(RESULTS.rglob("network.json"), key=lambda p: (len(p.parts), str(p)))
    keys = [
        ("torch_fd", "torch eager FD"),
        ("torch_autograd", "torch autograd (fwd)"),
        ("torch_jacfwd", "torch `jacfwd`"),
        ("ort_exact", "exact ONNX graph"),
        ("torch_reverse", "reverse mode (extrap.)"),
    ]
    rows = []
    for f in nfiles:
        d = _load(f)
        st, ra, m = d["comparison"]["stats"], d.get("ratios_to_ort_fd", {}), d.get("model", {})
        rows.append(
            [
                f"`{f.relative_to(RESULTS).as_posix()}`",
                f"{m.get('source')} {m.get('height')}x{m.get('width')}",
                str(d.get("machine", {}).get("ort_threads", d.get("config", {}).get("threads"))),
                _num(st["ort_fd"]["median_ms"], 1),
                _num(st.get("ort_prior", {}).get("median_ms"), 1),
            ]
            + [_num(ra.get(k), 0 if k == "torch_reverse" else 1, suffix="x") for k, _ in keys]
        )
    if rows:
        out += [
            "Time of one Jacobian (nominal + 8 perturbed codes) as ratios to the runtime's ONNX Runtime FD, measured "
            "in one run (the paper: 4.5 ms FD on a GTX 1660 Ti; DeepFactors' autograd 340 ms, i.e. 76x):",
            "",
            _table(["result", "model", "threads", "ORT FD [ms]", "ORT prior [ms]"] + [n for _, n in keys], rows),
            "",
        ]
    spec_n = [
        ("model", "--model"),
        ("ckpt", "--ckpt"),
        ("data", "--data"),
        ("threads", "--threads"),
        ("runs", "--runs"),
        ("torch_runs", "--torch-runs"),
        ("sweep_runs", "--sweep-runs"),
        ("warmup", "--warmup"),
        ("rounds", "--rounds"),
        ("rev_chunk", "--rev-chunk"),
        ("seed", "--seed"),
        ("out", "--out"),
    ]
    for f in nfiles:
        d = _load(f)
        c = d.get("config", {})
        flags = _flags(c, spec_n + ([] if c.get("model") else standin))
        flags += ([] if c.get("exact", True) else ["--no-exact"]) + ([] if c.get("sweep", True) else ["--no-sweep"])
        out += [f"`{f.relative_to(RESULTS).as_posix()}`: {d.get('model', {}).get('description', '')}", ""]
        out += [
            _source_block([f], " ".join(["python benchmarks/bench_network.py", *flags]), _machine(d.get("machine"))),
            "",
        ]
    return out


def _coast() -> list[str]:
    f = RESULTS / "bench_coast.json"
    if not f.is_file():
        return []
    d = _load(f)
    a = d.get("args", {})
    spec = [("seeds", "--seeds"), ("duration", "--duration"), ("runs", "--runs")]
    return [
        "## What decides the `whitewall` ATE",
        "",
        "The IMU-only coast in front of the bare wall, smoothed from exact end states (oracles: the bound on any "
        "system there; `+ wall distance` adds a perfect depth sensor on the wall), and each Table 3 run's ATE split "
        "around the coast: before / over / after it under the whole alignment, each side aligned alone, and how far "
        "apart the two sides' alignments put the relocalised pose (jump):",
        "",
        "```",
        d.get("table", "").rstrip(),
        "```",
        "",
        _source_block(
            [f],
            " ".join(["python benchmarks/bench_coast.py", *_flags(a, spec)]),
            _machine(d.get("machine")),
            note=d.get("note", ""),
        ),
        "",
    ]


def _slam() -> list[str]:
    out = ["## Sparse VI-SLAM: accuracy and speed", ""]
    f = RESULTS / "slam" / "bench_slam.json"
    if not f.is_file():
        return []
    d = _load(f)
    summ = d.get("summary", {})
    out += [
        f"`dit-slam` (sparse, runtime preset `{d.get('runtime', 'default')}`) on synthetic `sim/` sequences, "
        f"{d.get('duration_s', '?'):g} s, IMU noise {'on' if d.get('imu_noise') else 'off'}; ATE after SE(3) "
        "alignment, RPE over 1 s, FPS = frames / wall time of the whole run:",
        "",
        _table(
            [
                "sequence",
                "runs",
                "ATE mean [mm]",
                "ATE max [mm]",
                "RPE trans [mm]",
                "RPE rot [deg]",
                "FPS mean",
                "FPS min",
            ],
            [
                [
                    p,
                    str(s.get("runs")),
                    _num(s.get("ate_se3_rmse_m_mean"), 1, 1e3),
                    _num(s.get("ate_se3_rmse_m_max"), 1, 1e3),
                    _num(s.get("rpe_trans_rmse_m_mean"), 1, 1e3),
                    _num(s.get("rpe_rot_rmse_deg_mean"), 3),
                    _num(s.get("fps_mean"), 0),
                    _num(s.get("fps_min"), 0),
                ]
                for p, s in summ.items()
            ],
        ),
        "",
        "Per run:",
        "",
        _table(
            ["sequence", "seed", "ATE SE(3) [mm]", "ATE Sim(3) [mm]", "scale", "keyframes", "FPS"],
            [
                [
                    r["preset"],
                    str(r["seed"]),
                    _num(r.get("ate_se3_rmse_m"), 1, 1e3),
                    _num(r.get("ate_sim3_rmse_m"), 1, 1e3),
                    _num(r.get("sim3_scale"), 3),
                    str(r.get("keyframes")),
                    _num(r.get("fps"), 0),
                ]
                for r in d.get("runs", [])
            ],
        ),
        "",
        _source_block([f], "python benchmarks/" + d.get("command", "bench_slam.py"), _machine(d.get("machine"))),
        "",
    ]
    return out


def _slam_realistic(name: str = "bench_slam_realistic.json") -> list[str]:
    """The realistic benchmark's table and bars (``bench_slam.py``; its ``--dense`` runs in ``*_dense.json``)."""
    f = RESULTS / "slam" / name
    if not f.is_file():
        return []
    d = _load(f)
    cmds = d.get("command")
    cmd = " ; ".join("python benchmarks/" + c for c in (cmds if isinstance(cmds, list) else [cmds]))
    rows = []
    for r in d.get("runs", []):
        pct = (
            100 * r["ate_se3_rmse_m"] / r["path_length_m"] if r.get("path_length_m") and "ate_se3_rmse_m" in r else None
        )
        init = (
            f"{r.get('init_method')} after {r['init_after_s']:.1f} s" if r.get("init_after_s") is not None else "never"
        )
        rows.append(
            [
                r["preset"],
                str(r["seed"]),
                _num(r.get("ate_se3_rmse_m"), 1, 1e3),
                _num(r.get("ate_sim3_rmse_m"), 1, 1e3),
                _num(pct, 2),
                _num(100 * r.get("posed_frac", float("nan")), 1),
                init,
                str(r.get("tracking_losses")),
                f"{_num(r.get('rest_drift_m'), 1, 1e3)} over {r['rest_s']:.1f} s"
                if r.get("rest_drift_m") is not None
                else "-",
                _num(r.get("fps"), 1),
                _num(r.get("cpu_ms_per_frame"), 1),
            ]
        )
    head = ["sequence", "seed", "ATE SE(3) [mm]", "ATE Sim(3) [mm]", "% of path", "% posed", "initialised"]
    bars = [
        f"- `{fam}`: **{'met' if b['met'] else 'not met'}** ({b['bar']}"
        + (f"; {b['runs_met']} of {b['runs']} runs" if "runs_met" in b else "")
        + (f"; missed by seeds {', '.join(map(str, b['seeds_missed']))}" if b.get("seeds_missed") else "")
        + ")"
        for fam, b in d.get("bars", {}).items()
    ]
    dense = d.get("system") == "dense"
    system = "dense, the default system" if dense else "sparse, default settings"
    return [
        f"## {'Dense' if dense else 'Sparse'} VI-SLAM on realistic sensors",
        "",
        f"`dit-slam` ({system}) on the realistic presets (camera physics, vibrating IMU; 30 s) "
        "and on the real MH_05 excerpt completed with a vibrating IMU by `dit-sim imu` (`mh05`: real timing, "
        "starts in flight; `mh05_still2`: a 2 s still period prepended; seed = the IMU noise seed of `dit-sim imu`):",
        "",
        _table(head + ["losses", "drift at rest [mm]", "frames/s", "CPU ms/frame"], rows),
        "",
        *(["The real-sensor issue's bars, as the benchmark judges them:", "", *bars, ""] if bars else []),
        _source_block([f], cmd, _machine(d.get("machine")), d.get("note", "")),
        "",
    ]


PEERS_PAGE = REPO / "reports" / "peers.md"
_PEER_ORDER = ("dit-slam-sparse", "dit-slam-dense", "orbslam3-mono", "orbslam3-mono-inertial", "cuvslam-mono")


def _mm_range(r: dict) -> str:
    if r.get("runs", 1) <= 1 or not math.isfinite(r.get("ate_min_m", math.nan)):
        return ""
    return f" ({_num(r['ate_min_m'], 1, 1e3)}-{_num(r['ate_max_m'], 1, 1e3)})"


def _peers_diagnosis() -> list[str]:
    """The ``benchmarks.peers.diagnose`` tables of ``benchmarks/results/peers_diagnosis_*.json`` (one a sequence)."""
    out = []
    for f in sorted(RESULTS.glob("peers_diagnosis_*.json")):
        d = _load(f)
        seq = f.stem[len("peers_diagnosis_") :]
        w = d.get("common_window_s") or [math.nan, math.nan]
        rows = []
        for label, r in d.get("systems", {}).items():
            d1, d5 = r.get("drift_1s", {}), r.get("drift_5s", {})
            rows.append(
                [
                    label,
                    _num(r.get("ate_sim3_m"), 1, 1e3),
                    _num(r.get("ate_sim3_common_m"), 1, 1e3),
                    _num(r.get("window_ate_median_m"), 1, 1e3),
                    _num(r.get("window_scale_spread"), 1, 100, " %"),
                    _num(d1.get("trans_rmse_m"), 1, 1e3),
                    _num(d5.get("trans_rmse_m"), 1, 1e3),
                    _num(d5.get("yaw_median_deg"), 2),
                ]
            )
        imu = d.get("imu_only", {})
        rows.append(
            ["IMU only, from the ground-truth state", "", "", "", ""]
            + [_num(imu.get(k, {}).get("trans_rmse_m"), 1, 1e3) for k in ("drift_1s", "drift_5s")]
            + [_num(imu.get("drift_5s", {}).get("yaw_median_deg"), 2)]
        )
        out += [
            f"Where the error on `{seq}` comes from (`benchmarks.peers.diagnose`, camera frame; common window "
            f"{_num(w[0], 2)}-{_num(w[1], 2)} s; window = each 6 s fitted alone with Sim(3); drift = RMSE of the "
            "relative motion over 1 s / 5 s after the global Sim(3) scale):",
            "",
            _table(
                [
                    "run",
                    "ATE Sim3 [mm]",
                    "on common window",
                    "6 s windows: median ATE [mm]",
                    "window scale spread",
                    "1 s drift [mm]",
                    "5 s drift [mm]",
                    "5 s yaw drift [deg]",
                ],
                rows,
            ),
            "",
            f"- source: [`{f.relative_to(REPO).as_posix()}`](../{f.relative_to(REPO).as_posix()}); "
            f"command: `{d.get('command', 'python -m benchmarks.peers.diagnose')}`",
            "",
        ]
    return out


def peers_page() -> str | None:
    """``reports/peers.md``: the side-by-side table of ``benchmarks/results/peers.json`` (None without it)."""
    f = RESULTS / "peers.json"
    if not f.is_file():
        return None
    d = _load(f)
    rows = sorted(
        d.get("rows", []),
        key=lambda r: (
            r["sequence"],
            _PEER_ORDER.index(r["system"]) if r["system"] in _PEER_ORDER else 9,
            r["alignment"],
        ),
    )
    table = _table(
        [
            "sequence",
            "system",
            "alignment",
            "ATE [mm] median (range)",
            "tracked",
            "losses / resets",
            "frames/s",
            "CPU ms/frame",
            "runs",
            "note",
        ],
        [
            [
                r["sequence"],
                r["system"],
                f"{r['alignment']} vs {r.get('reference_frame', '?')}",
                _num(r.get("ate_m"), 1, 1e3) + _mm_range(r),
                _num(r.get("tracked_frac"), 0, 100, " %"),
                f"{_num(r.get('losses'), 0)} / {_num(r.get('resets'), 0)}",
                _num(r.get("fps"), 1),
                _num(r.get("cpu_ms_per_frame"), 1),
                str(r.get("runs")),
                (r.get("note") or "").replace("|", "/"),
            ]
            for r in rows
        ],
    )
    ratio_rows = [
        [
            q["sequence"],
            f"{q['ours']} / {q['peer']}",
            q["alignment"],
            _num(q.get("ate_ratio"), 2),
            _num(q.get("fps_ratio"), 2),
            _num(q.get("cpu_ratio"), 2),
            _num(q.get("peer_tracked_frac"), 0, 100, " %"),
        ]
        for q in d.get("ratios", [])
    ]
    parts = [
        "# Side by side with the peers: ORB-SLAM3 and cuVSLAM",
        "",
        "Generated by `python reports/build.py` from "
        "[`benchmarks/results/peers.json`](../benchmarks/results/peers.json) (written by "
        "`benchmarks/bench_peers.py`). Do not edit by hand. Every system ran on the same sequences on the same "
        "machine in one run and was scored by the same evo call: " + str(d.get("scoring", "")) + ".",
        "",
        f"ORB-SLAM3 runs with a **{d.get('vocabulary') or 'vocabulary not recorded'}**; it is not deterministic "
        "(median and range over its runs). cuVSLAM runs with `use_gpu: False`. " + str(d.get("timing", "")) + ".",
        "",
        table,
        "",
    ]
    if ratio_rows:
        parts += [
            "Ours over each peer (below 1: ours is more accurate / uses less CPU; above 1 for frames/s: ours is "
            "faster). Compare only where both track most frames:",
            "",
            _table(
                ["sequence", "ours / peer", "alignment", "ATE ratio", "frames/s ratio", "CPU ratio", "peer tracked"],
                ratio_rows,
            ),
            "",
        ]
    if d.get("notes"):
        parts += ["Notes:", ""] + [f"- {n}" for n in d["notes"]] + [""]
    parts += _peers_diagnosis()
    for png in sorted(PEERS_PAGE.parent.glob("peers_*.png")):
        seq = png.stem[len("peers_") :]
        parts += [
            f"Per-frame error on `{seq}` (log scale; `python -m benchmarks.peers.plot_errors --sequence {seq} ...`):",
            "",
            f"![{seq}]({png.name})",
            "",
        ]
    parts.append(_source_block([f], d.get("command", "python benchmarks/bench_peers.py"), _machine(d.get("machine"))))
    return "\n".join(parts).rstrip() + "\n"


def source_files() -> list[Path]:
    """Every file the report is built from (for the test's committed-sources check)."""
    files = sorted(RESULTS.rglob("*.json"))
    files += [REPO / "runtime" / "assets" / "default_model" / n for n in ("val_metrics.json", "manifest.json")]
    files += [REPO / "notebooks" / n for n in ("01_depth_modalities.ipynb", "03_trajectories.ipynb")]
    return [f for f in files if f.is_file()]


def records() -> list[tuple[str, str]]:
    """The hand-written records beside the report (``reports/*.md`` but the README): ``[(file name, title)]``,
    the title being the page's first ``# `` heading."""
    out = []
    for f in sorted(README.parent.glob("*.md")):
        if f not in (README, PEERS_PAGE):
            title = next((ln[2:].strip() for ln in f.read_text().splitlines() if ln.startswith("# ")), f.stem)
            out.append((f.name, title))
    return out


def build() -> str:
    """The report's Markdown text."""
    parts = [
        "# Current figures",
        "",
        "Generated by `python reports/build.py` from the committed results: benchmark JSON in "
        "[`benchmarks/results/`](../benchmarks/results/), the shipped model's metrics and the committed "
        "notebooks' outputs. Do not edit by hand; `tests/test_reports.py` checks that this file equals the "
        "script's output. Dates are those of the last commit that changed each source (the JSON files hold no "
        "date), or the date a notebook's run printed. All accuracy figures are on **synthetic** data rendered by "
        "`sim/`; all timings are on the CPU machines named with each source (2 cores shared with other jobs: "
        "compare ratios measured in one run, not absolute times across runs).",
        "",
        "Contents: [Table 1](#table-1-depth-networks-x-input-modalities) · "
        "[Table 3](#table-3-sparse-vs-dense-tight-coupling) · "
        "[dense map](#the-fused-dense-map-accuracy-and-completeness) · "
        "[whitewall](#what-decides-the-whitewall-ate) · "
        "[Jacobian](#the-code-jacobian-eq-17-accuracy-against-autograd-fig-6-and-speed-ratios) · "
        "[SLAM](#sparse-vi-slam-accuracy-and-speed) · [peers: ORB-SLAM3, cuVSLAM](peers.md) · notebooks: "
        "[01](../notebooks/01_depth_modalities.ipynb), [02](../notebooks/02_code_jacobian.ipynb), "
        "[03](../notebooks/03_trajectories.ipynb), [04](../notebooks/04_textureless.ipynb)",
        "",
        "Records written by hand beside this report (the history behind these figures): "
        + " · ".join(f"[{title}]({name})" for name, title in records()),
        "",
    ]
    for section in (_table1, _table3, _dense_map, _coast, _jacobian, _slam, _slam_realistic):
        parts += section()
    parts += _slam_realistic("bench_slam_realistic_dense.json")
    return "\n".join(parts).rstrip() + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--check", action="store_true", help="compare with reports/README.md, write nothing")
    a = ap.parse_args(argv)
    pages = [(README, build())]
    peers = peers_page()
    if peers is not None:
        pages.append((PEERS_PAGE, peers))
    if any("not committed" in text for _, text in pages):
        print("note: some sources are not committed; commit them, re-run this script and commit the pages")
    if a.check:
        ok = True
        for path, text in pages:
            same = path.is_file() and path.read_text() == text
            ok &= same
            print(f"{path}: {'up to date' if same else 'OUT OF DATE (run python reports/build.py)'}")
        return 0 if ok else 1
    for path, text in pages:
        path.write_text(text)
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
