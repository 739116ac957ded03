"""Helpers of the Jacobian and network benchmarks: machine info, JSON, tables, timing, models, data.

The benchmark scripts, notebooks and tests import this module as ``benchmarks.common`` (``benchmarks`` is an
installed package). Everything here may import torch: benchmarks compare the ONNX runtime with torch on the same
weights.

Model sources (:func:`resolve_model`), in order:

* ``--model DIR`` (an exported model directory) and its torch weights from ``--ckpt`` or, failing that, the
  checkpoint named by the manifest's ``source``; the two are checked against each other (decoder parity);
* ``--ckpt`` alone: the checkpoint is exported on the fly into a cache folder;
* neither: a *stand-in* network built like ``tests/export/test_export.py::make_net`` (an untrained DiT whose
  decoder BatchNorm statistics are re-estimated so that the code visibly changes the depth), exported on the
  fly and cached under ``<cache>/bench-standin-*``. Every printout names which source was used.
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

# Torch's OpenMP threads wait actively by default. On a loaded 2-core machine that turned a 12 ms decoder call
# into 0.1-2.5 s (a spinning thread holds the core its partner needs); passive waiting kept it at 12 ms. This
# is torch's counterpart of ORT's allow_spinning=0 and must be set before torch is imported. An explicit
# OMP_WAIT_POLICY in the environment wins.
_TORCH_BEFORE_POLICY = "torch" in sys.modules  # then the setting below comes too late for this process
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results"

#: Jacobian timings reported by the paper (Sec. 5.3) and the systems it cites, for the printouts.
PAPER_FIGURES_MS = {
    "DiT-SLAM FD Jacobian, C=8 (GTX 1660 Ti + i7-9700)": 4.5,
    "CodeVIO FD Jacobian, C=32 (GTX 1080 Ti)": 10.0,
    "DeepFactors autograd Jacobian (GTX 1080)": 340.0,
}


# ------------------------------------------------------------------------------------------ machine, output
def cache_dir() -> Path:
    """``$DIT_SLAM_CACHE``, ``$XDG_CACHE_HOME/dit-slam`` or ``~/.cache/dit-slam`` (as in ``train.data``)."""
    if os.environ.get("DIT_SLAM_CACHE"):
        return Path(os.environ["DIT_SLAM_CACHE"]).expanduser()
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "dit-slam"


def cpu_model() -> str:
    """The CPU's model name from ``/proc/cpuinfo`` (plus family/model/MHz when the name is generic)."""
    fields: dict[str, str] = {}
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if ":" in line:
                k, v = (s.strip() for s in line.split(":", 1))
                fields.setdefault(k, v)
            elif fields:
                break  # first processor block only
    except OSError:
        return platform.processor() or platform.machine()
    name = fields.get("model name") or platform.processor() or platform.machine()
    extra = []
    if "cpu family" in fields:
        extra.append(f"family {fields['cpu family']} model {fields.get('model', '?')}")
    if "cpu MHz" in fields:
        extra.append(f"{float(fields['cpu MHz']):.0f} MHz")
    flags = fields.get("flags", "").split()
    simd = [f for f in ("avx512f", "avx2") if f in flags]
    if simd:
        extra.append(simd[0])
    return f"{name} ({', '.join(extra)})" if extra else name


def machine_info(**threads) -> dict:
    """Machine and library versions for a result JSON; ``threads`` records the thread settings used."""
    import onnxruntime as ort
    import torch

    try:
        usable = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        usable = os.cpu_count()
    return {
        "cpu": cpu_model(),
        "cores": os.cpu_count(),
        "usable_cores": usable,
        "platform": platform.platform(),
        "python": sys.version.split()[0],
        "numpy": np.__version__,
        "torch": torch.__version__,
        "onnxruntime": ort.__version__,
        "loadavg": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
        "torch_imported_before_policy": _TORCH_BEFORE_POLICY,
        **threads,
    }


def slam_machine(**extra) -> dict:
    """Machine fields of a SLAM benchmark's JSON (no torch), then ``extra``. The CPU model comes first: SLAM runs
    are chaotic, another CPU's floating point gives other trajectories."""
    return {
        "cpu": cpu_model(),
        "platform": platform.platform(),
        "cpus": os.cpu_count(),
        "python": platform.python_version(),
        **extra,
    }


def start_notebook(out: str | Path) -> tuple[Path, Path, float]:
    """Set a notebook up: the repository root as the working directory, its output folder, inline figure size.

    The root is found at or above the working directory (a notebook's kernel may start in ``notebooks/`` or in
    the root); the notebooks' relative paths (``OUT``, ``DATA``) are relative to it. Prints both folders.

    Args:
        out: the output folder, relative to the root (or absolute); created.

    Returns:
        ``(repo, out, t_start)``: the root, the output folder (absolute) and the start time (``time.time()``).

    Raises:
        RuntimeError: the working directory is not inside the dit-slam repository.
    """
    import matplotlib

    repo = Path.cwd().resolve()
    while not (repo / "pyproject.toml").is_file():
        if repo.parent == repo:
            raise RuntimeError("run this notebook from inside the dit-slam repository")
        repo = repo.parent
    os.chdir(repo)
    matplotlib.rcParams.update({"figure.dpi": 90, "font.size": 9})
    out_dir = (repo / out).resolve()
    out_dir.mkdir(parents=True, exist_ok=True)
    t_start = time.time()
    print(f"repository {repo}\noutputs    {out_dir}")
    return repo, out_dir, t_start


def describe_machine(m: dict) -> str:
    return (
        f"{m['cpu']}, {m['cores']} cores ({m['usable_cores']} usable), load {m['loadavg']}, "
        f"torch {m['torch']}, onnxruntime {m['onnxruntime']}, OMP_WAIT_POLICY={m.get('omp_wait_policy')}"
    )


def write_json(path: str | Path, obj: dict) -> Path:
    """Write ``obj`` as indented JSON (numpy scalars and arrays converted), creating the folder; atomically (a
    temporary file renamed over ``path``), so that an interruption leaves the old file or the new one."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)

    def default(o):
        if isinstance(o, np.generic):
            return o.item()
        if isinstance(o, np.ndarray):
            return o.tolist()
        if isinstance(o, Path):
            return str(o)
        raise TypeError(f"{type(o).__name__} is not JSON serialisable")

    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(obj, indent=2, default=default) + "\n")
    os.replace(tmp, path)
    return path


def resumable_rows(
    path: Path, args: dict, machine: dict, key: Callable[[dict], tuple], rows: str = "rows"
) -> dict[tuple, dict]:
    """The list ``rows`` of an earlier invocation's result file ``path`` by ``key(row)``, for ``--resume``; {} when
    there is none.

    Raises:
        ValueError: it was written with other arguments or on another CPU (runs are chaotic across CPUs).
    """
    if not path.exists():
        return {}
    old = json.loads(path.read_text())
    if old.get("args") != json.loads(json.dumps(args)):
        raise ValueError(f"{path} was written with other arguments ({old.get('args')}): another --out, or no --resume")
    cpu = old.get("machine", {}).get("cpu")
    if cpu != machine["cpu"]:
        raise ValueError(f"{path} was written on another CPU ({cpu}): runs differ between CPUs")
    return {key(r): r for r in old.get(rows, [])}


def markdown_table(headers: list[str], rows: list[list]) -> str:
    """A markdown table; floats are printed with 4 significant digits, None as ``-``."""

    def cell(v) -> str:
        if v is None:
            return "-"
        if isinstance(v, float):
            return f"{v:.4g}"
        return str(v)

    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    lines += ["| " + " | ".join(cell(v) for v in r) + " |" for r in rows]
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------- timing
def time_blocks(
    fns: dict[str, Callable[[], object]], runs: int, warmup: int, rounds: int = 3, pause_s: float = 0.02
) -> dict[str, dict]:
    """Time each function in blocks, the blocks interleaved over ``rounds`` (load drift hits all alike).

    Each round runs, for every function in turn, ``warmup`` untimed calls and ``ceil(runs / rounds)`` timed
    calls; a short pause between blocks lets spinning ORT threads settle. The warm-up is repeated in every
    block: the first torch call after another method's large allocations pays for page faults (measured: a
    50 ms decoder call took 1.2 s right after a ``jacfwd``), which is not the steady state of a SLAM loop.

    Returns:
        ``{name: {"median_ms", "mean_ms", "min_ms", "std_ms", "n"}}``.
    """
    if runs < 1 or rounds < 1 or warmup < 0:
        raise ValueError(f"need runs >= 1, rounds >= 1, warmup >= 0 (got {runs}, {rounds}, {warmup})")
    per_round = -(-runs // rounds)
    samples: dict[str, list[float]] = {k: [] for k in fns}
    for _ in range(rounds):
        for name, fn in fns.items():
            for _ in range(warmup):
                fn()
            for _ in range(per_round):
                t0 = time.perf_counter()
                fn()
                samples[name].append((time.perf_counter() - t0) * 1e3)
            time.sleep(pause_s)
    return {k: stats_ms(v) for k, v in samples.items()}


def stats_ms(ts: list[float]) -> dict:
    return {
        "median_ms": statistics.median(ts),
        "mean_ms": statistics.fmean(ts),
        "min_ms": min(ts),
        "std_ms": statistics.stdev(ts) if len(ts) > 1 else 0.0,
        "n": len(ts),
    }


# ---------------------------------------------------------------------------------------------- models
@dataclass
class BenchModel:
    """An exported model directory and the torch network with the same weights."""

    model_dir: Path
    net: object  # torch nn.Module (eval mode)
    source: str  # "stand-in" | "checkpoint" | "model-dir"
    description: str
    modality: str
    height: int
    width: int
    code_dim: int
    info: dict = field(default_factory=dict)

    def summary(self) -> dict:
        """The model's entry in a benchmark's JSON."""
        return {
            "source": self.source,
            "description": self.description,
            "dir": str(self.model_dir),
            "modality": self.modality,
            "height": self.height,
            "width": self.width,
            "code_dim": self.code_dim,
            **self.info,
        }


def run_provenance(repo: Path, code_paths: tuple[str, ...] = ("runtime", "conf", "sim", "benchmarks/*.py")) -> str:
    """Three lines saying where and on what a run happened: the machine (CPU, cores, load), the UTC date, and the
    code (the commit of ``repo`` plus any uncommitted changes under ``code_paths``; ``?`` without git)."""
    git = ["git", "-C", str(repo)]
    try:
        sha = subprocess.run([*git, "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
        st = subprocess.run([*git, "status", "--porcelain", "--", *code_paths], capture_output=True, text=True)
        changed = [ln[3:] for ln in st.stdout.splitlines()]
    except OSError:  # no git
        sha, changed = "", []
    return "\n".join(
        [
            f"machine    {cpu_model()}, {os.cpu_count()} cores, load {os.getloadavg()}",
            f"date       {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}",
            f"code       commit {sha or '?'}"
            + (f" + uncommitted changes in {', '.join(changed)}" if changed else ""),
        ]
    )


def standin_net(
    modality: str = "grays",
    height: int = 224,
    width: int = 224,
    width_mult: float = 0.25,
    seed: int = 0,
    bn_batches: int = 4,
    bn_batch: int = 8,
):
    """An untrained DiT whose decoder visibly depends on the code (also the export tests' network).

    Untrained, the decoder is nearly constant in the code; drawing the depth head from N(0, 0.3^2) and
    re-estimating the decoder's BatchNorm statistics over ``bn_batches`` train-mode passes of random inputs
    and codes (no gradient step) gives a code effect of the order of 0.5 m. Deterministic for a seed.
    """
    import torch

    from models import build_model

    torch.manual_seed(seed)
    net = build_model("dit", modality, width_mult=width_mult, height=height, width=width)
    with torch.no_grad():
        net.decoder.head.weight.normal_(0.0, 0.3)
        for m in net.decoder.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.momentum = None  # cumulative average over the passes below
        net.decoder.train()
        for _ in range(bn_batches):
            net(
                torch.rand(bn_batch, net.in_channels, height, width), code=torch.randn(bn_batch, net.code_dim)
            )
    return net.eval()


def decoder_parity(net, model_dir: Path, seed: int = 0) -> float:
    """Max |depth_ORT - depth_torch| [m] at batch 9 on one random input: the decoder on the same features, and
    prior + decoder end to end (so a prior built differently, e.g. without the graph's contrast matching, shows)."""
    import torch

    from runtime.network import DepthNetwork

    dn = DepthNetwork(model_dir)
    rng = np.random.default_rng(seed)
    img = rng.random((dn.height, dn.width, 3) if dn.modality.startswith("rgb") else (dn.height, dn.width))
    sparse = None
    if dn.uses_sparse:
        sparse = np.where(
            rng.random((dn.height, dn.width)) < 125 / (dn.height * dn.width),
            rng.uniform(0.5, 6.0, (dn.height, dn.width)),
            0.0,
        ).astype(np.float32)
    img = img.astype(np.float32)
    kf = dn.prior(img, sparse)
    codes = rng.normal(0.0, 0.5, (9, dn.code_dim)).astype(np.float32)
    x = torch.from_numpy(dn.make_input(img, sparse))  # the raw input prior.onnx was given
    with torch.no_grad():
        feats = [torch.from_numpy(kf.features[n]) for n in dn.feature_names]
        d_t = net.decoder(torch.from_numpy(codes), *feats)[:, 0].numpy()
        d_e2e = net.decoder(torch.from_numpy(codes), *net.prior(x)[1])[:, 0].numpy()
    d_o = dn.decode(codes, kf.features)
    return float(max(np.abs(d_o - d_t).max(), np.abs(d_o - d_e2e).max()))


def _export_quiet(net, out_dir: Path, **kw) -> dict:
    """``export_network`` with the exporter's chatter (warnings, progress) kept off the benchmark's output."""
    import contextlib
    import io
    import logging
    import warnings

    from export.onnx import export_network

    buf = io.StringIO()
    prev = logging.getLogger("torch").level
    logging.getLogger("torch").setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings(), contextlib.redirect_stdout(buf):
            warnings.simplefilter("ignore")
            return export_network(net, out_dir, **kw)
    finally:
        logging.getLogger("torch").setLevel(prev)


def standin_model(
    modality: str = "grays",
    height: int = 224,
    width: int = 224,
    width_mult: float = 0.25,
    seed: int = 0,
    out_dir: str | Path | None = None,
    log=print,
) -> BenchModel:
    """The stand-in network and its ONNX export (an earlier export in ``out_dir`` is reused if it matches)."""
    import torch

    spec = {
        "kind": "standin (make_net-like, untrained, decoder BN re-estimated)",
        "modality": modality,
        "height": height,
        "width": width,
        "width_mult": width_mult,
        "seed": seed,
    }
    key = hashlib.sha1(json.dumps(spec, sort_keys=True).encode()).hexdigest()[:8]
    out = (
        Path(out_dir)
        if out_dir
        else cache_dir() / f"bench-standin-{modality}-{height}x{width}-w{width_mult:g}-{key}"
    )
    with torch.random.fork_rng():
        net = standin_net(modality, height, width, width_mult, seed)
    reused = False
    manifest_path = out / "manifest.json"
    if manifest_path.is_file():
        try:
            cached = json.loads(manifest_path.read_text())
            reused = cached.get("standin") == spec and bool(cached.get("files"))  # no hashes: an older export
            reused = reused and decoder_parity(net, out) <= 1e-4
        except Exception:  # a broken or stale export is simply redone
            reused = False
    if not reused:
        log(f"exporting the stand-in network to {out} ...")
        with torch.random.fork_rng():
            torch.manual_seed(seed)
            _export_quiet(
                net,
                out,
                modality=modality,
                height=height,
                width=width,
                n_parity=2,
                source="benchmarks stand-in",
                extra={"standin": spec},
            )
    desc = (
        f"STAND-IN network (untrained DiT, width_mult={width_mult:g}, {modality}, {height}x{width}, decoder "
        f"BatchNorm re-estimated as in tests/export make_net, seed {seed}); exported to {out}"
        f"{' (reused)' if reused else ''}. Not the trained model."
    )
    return BenchModel(out, _frozen(net), "stand-in", desc, modality, height, width, int(net.code_dim), spec)


def _frozen(net):
    """Eval mode, float32, no parameter gradients: every Jacobian here is w.r.t. the code only."""
    net = net.eval().float()
    for q in net.parameters():
        q.requires_grad_(False)
    return net


def resolve_model(
    model_dir: str | Path | None,
    ckpt: str | Path | None,
    *,
    modality: str = "grays",
    height: int = 224,
    width: int = 224,
    width_mult: float = 0.25,
    seed: int = 0,
    standin_dir: str | Path | None = None,
    need_torch: bool = True,
    log=print,
) -> BenchModel:
    """Pick the model of a benchmark run (see the module docstring); raise ``ValueError`` with the reason."""
    import torch

    from runtime.network import DepthNetwork

    if model_dir is None and ckpt is None:
        return standin_model(modality, height, width, width_mult, seed, standin_dir, log=log)
    if model_dir is not None:
        model_dir = Path(model_dir)
        dn = DepthNetwork(model_dir)  # raises ModelError (a ValueError) for a bad directory
        if ckpt is None:
            src = dn.manifest.get("source")
            if src and Path(src).is_file():
                ckpt = src
        if ckpt is None:
            if need_torch:
                raise ValueError(
                    f"{model_dir}: the torch weights are needed too: pass --ckpt (the manifest's source "
                    f"{dn.manifest.get('source')!r} is not a file here)"
                )
            return BenchModel(
                model_dir,
                None,
                "model-dir",
                f"exported model {model_dir} (no torch weights)",
                dn.modality,
                dn.height,
                dn.width,
                dn.code_dim,
            )
    from export.checkpoint import load_checkpoint

    # the graphs' contrast matching may have been applied at export, not in training: build the torch net alike
    contrast = (dn.manifest.get("input_normalization") or {}).get("image_contrast") if model_dir is not None else None
    loaded = load_checkpoint(ckpt, contrast)
    net = _frozen(loaded.net)
    if model_dir is None:
        model_dir = (
            cache_dir() / f"bench-export-{hashlib.sha1(str(Path(ckpt).resolve()).encode()).hexdigest()[:8]}"
        )
        log(f"exporting {ckpt} to {model_dir} ...")
        with torch.random.fork_rng():
            torch.manual_seed(0)
            _export_quiet(
                net,
                model_dir,
                modality=loaded.modality,
                height=loaded.height,
                width=loaded.width,
                source=str(ckpt),
                train_config=loaded.train_config,
            )
        source = "checkpoint"
    else:
        source = "model-dir"
    dn = DepthNetwork(model_dir)
    got = (loaded.modality, loaded.height, loaded.width, int(net.code_dim))
    want = (dn.modality, dn.height, dn.width, dn.code_dim)
    if got != want:
        raise ValueError(f"checkpoint {ckpt} is (modality, H, W, C) = {got} but {model_dir} is {want}")
    parity = decoder_parity(net, model_dir)
    if parity > 1e-4:
        raise ValueError(
            f"checkpoint {ckpt} and {model_dir} are not the same weights: decoder outputs differ by "
            f"{parity:.3g} m (> 1e-4 m)"
        )
    desc = (
        f"TRAINED model {model_dir} ({dn.manifest.get('model', '?')}, {dn.modality}, {dn.height}x{dn.width}, "
        f"C={dn.code_dim}) with torch weights from {ckpt} (decoder parity {parity:.2g} m)"
    )
    return BenchModel(
        Path(model_dir),
        net,
        source,
        desc,
        dn.modality,
        dn.height,
        dn.width,
        dn.code_dim,
        {"ckpt": str(ckpt), "decoder_parity_m": parity},
    )


# ---------------------------------------------------------------------------------------------- data
def model_and_val_data(args, n_val: int, who: str) -> tuple[BenchModel, Path]:
    """The model and the validation frames a benchmark's parsed arguments name (``--model``, ``--ckpt``, the
    stand-in's ``--modality --height --width --width-mult --seed``, ``--standin-dir``, ``--data``); an error
    exits with one line that names the benchmark ``who``."""
    try:
        bm = resolve_model(
            args.model,
            args.ckpt,
            modality=args.modality,
            height=args.height,
            width=args.width,
            width_mult=args.width_mult,
            seed=args.seed,
            standin_dir=args.standin_dir,
        )
        return bm, ensure_val_data(args.data, n_val, seed=args.seed)
    except (ValueError, FileNotFoundError) as e:
        sys.exit(f"{who}: {e}")


def ensure_val_data(root: str | Path | None, n_val: int, seed: int = 0, log=print) -> Path:
    """A NYU-layout root with ``val/`` frames: ``root`` if given, else synthetic frames (rendered once)."""
    from runtime.io.nyu import list_nyu_h5

    if root is not None:
        root = Path(root)
        if not list_nyu_h5(root, "val"):
            raise FileNotFoundError(f"{root}: no val/<scene>/*.h5 frames")
        return root
    n_val = max(int(n_val), 8)  # one shared cache folder for the usual small counts
    root = cache_dir() / f"bench-nyu-val-{int(seed)}-{n_val}"
    try:
        if len(list_nyu_h5(root, "val")) >= n_val:
            return root
    except (FileNotFoundError, ValueError):
        pass
    from sim.nyu import write_nyu_dataset

    log(f"rendering {n_val} synthetic NYU-layout validation frames into {root} ...")
    tmp = Path(tempfile.mkdtemp(prefix=root.name + ".", dir=root.parent if root.parent.exists() else None))
    write_nyu_dataset(tmp / "data", n_train=0, n_val=n_val, seed=seed, progress=False)
    root.parent.mkdir(parents=True, exist_ok=True)
    if root.exists():
        import shutil

        shutil.rmtree(root)
    (tmp / "data").rename(root)
    tmp.rmdir()
    return root


@dataclass
class Frame:
    """A network input: ``image`` (H, W) grey or (H, W, 3) RGB in [0, 1], ``sparse`` (H, W) metres or None."""

    name: str
    image: np.ndarray
    sparse: np.ndarray | None


def val_frames(root: Path, modality: str, height: int, width: int, n: int, seed: int = 0) -> list[Frame]:
    """Up to ``n`` validation frames preprocessed as dit-export's parity frames.

    Resize + centre crop with ``runtime.geometry.NetworkMapping``, grey (BT.601) for the ``gray*`` modalities,
    and for ``*s`` 125 sparse samples of the ground-truth depth at uniformly drawn valid pixels (seeded):
    ``export.checkpoint.validation_inputs``, reused here.
    """
    from types import SimpleNamespace

    from export.checkpoint import validation_inputs
    from runtime.io.nyu import list_nyu_h5

    files = list_nyu_h5(root, "val")[:n]
    spec = SimpleNamespace(modality=modality, height=height, width=width)
    xs = validation_inputs(spec, root, n, seed=seed)
    frames = []
    for f, x in zip(files, xs, strict=True):
        x = x[0].numpy()  # (Cin, H, W)
        has_sparse = modality.endswith("s")
        img = x[:-1] if has_sparse else x
        img = img[0] if img.shape[0] == 1 else img.transpose(1, 2, 0)
        frames.append(
            Frame(
                f"{f.parent.name}/{f.stem}",
                np.ascontiguousarray(img),
                np.ascontiguousarray(x[-1]) if has_sparse else None,
            )
        )
    return frames


def bench_codes(
    code_dim: int, n_random: int, sigma: float = 0.5, seed: int = 0
) -> list[tuple[str, np.ndarray]]:
    """The zero code (the prior mean) and ``n_random`` draws from N(0, sigma^2 I), float32 (C,)."""
    rng = np.random.default_rng(seed)
    codes = [("zeros", np.zeros(code_dim, np.float32))]
    codes += [
        (f"N(0,{sigma:g}^2)#{i}", (sigma * rng.standard_normal(code_dim)).astype(np.float32))
        for i in range(n_random)
    ]
    return codes


def gs_protocol_sets(net, real: str | None, sim_val: int, limit: int | None = None) -> dict:
    """The frame sets of the paper's G-S protocol for an exported model ``net`` (:class:`runtime.network.DepthNetwork`):
    ``real`` RGB-D folders (or None) and ``sim_val`` fresh realistic synthetic rooms (seed 1000), as ``dit-eval
    depth`` builds them (:func:`train.evaluate.protocol_sets`)."""
    from omegaconf import OmegaConf

    from train.evaluate import protocol_sets

    cfg = OmegaConf.create(
        {
            "protocol": "gs",
            "seed": 0,
            "real": real,
            "limit": limit,
            "sim": {"n_val": sim_val, "seed": 1000, "realism": True, "root": None},
        }
    )
    return protocol_sets(cfg, net.modality, net.height, net.width)


@dataclass
class PosedGsFrame:
    """One frame of an ``rgbd_real`` folder at its recorded pose, with the paper's G-S input (:func:`posed_gs_frames`).

    Attributes:
        index: the frame's index in the folder.
        rgb: (H, W, 3) colour image; depth: (H, W) full-resolution depth [m] (0 = invalid).
        T_w_c: (4, 4) the recorded camera pose.
        cam: the full-resolution pinhole camera; mapping: its :class:`runtime.geometry.NetworkMapping`;
            net_cam: the network camera.
        gt: (h, w) true depth at network resolution; sparse: (h, w) the G-S sparse input (125 FAST points).
        kd: the network's prior (:class:`runtime.network.KeyframeDepth`) on that input.
    """

    index: int
    rgb: np.ndarray
    depth: np.ndarray
    T_w_c: np.ndarray
    cam: object
    mapping: object
    net_cam: object
    gt: np.ndarray
    sparse: np.ndarray
    kd: object


def posed_gs_frames(frames, net):
    """Yield :class:`PosedGsFrame` for every frame of ``frames`` (a :class:`runtime.io.rgbd_frames.RgbdFolder`),
    its input built as ``dit-eval depth`` builds it (seed 0, epoch 0) for the exported model ``net``.

    Raises:
        ValueError: a frame has no pose file.
    """
    from runtime.geometry import Camera
    from train.augment import FrameTransform
    from train.sparse import SparseConfig

    tf = FrameTransform(net.height, net.width, net.modality, False, None, SparseConfig())
    K = frames.K
    for i in range(len(frames)):
        rgb, depth = frames[i]
        T_w_c = frames.pose(i)
        if T_w_c is None:
            raise ValueError(f"{frames.root}: frame {i} has no pose file")
        H, W = depth.shape
        cam = Camera(K[0, 0], K[1, 1], K[0, 2], K[1, 2], W, H)
        mapping = tf.mapping((H, W))
        x = tf(rgb, depth, np.random.default_rng([0, 0, i]))
        img = x["image"][0] if not net.modality.startswith("rgb") else x["image"][:3].transpose(1, 2, 0)
        sparse = np.asarray(x["image"][-1], np.float32)
        kd = net.prior(img, sparse if net.uses_sparse else None)
        yield PosedGsFrame(
            i, rgb, depth, np.asarray(T_w_c, np.float64), cam, mapping, mapping.camera(cam), x["depth"][0], sparse, kd
        )
