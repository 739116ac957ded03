"""Parameters, FLOPs and CPU forward time of every model variant x modality (issue 3, item 3, models half).

For each of ``dit | codevio8 | codevio32 | fastdepth`` x ``rgb | rgbs | gray | grays`` at H x W (default
224 x 224), batch 1, torch eager on the CPU in eval mode under ``torch.inference_mode``:

* ``params``: trainable parameters of the whole module (the CVAE models include the training-only depth
  encoder; ``infer_params`` counts only what inference runs: UNet stream + decoder);
* ``gflops``: FLOPs of one inference forward (code = 0, no depth encoder), counted by
  ``torch.utils.flop_counter.FlopCounterMode`` (convolutions and matmuls; 1 multiply-add = 2 FLOPs);
* ``forward_ms`` (mean), ``forward_ms_std``, ``_median``, ``_min`` over ``--runs`` timed forwards after
  ``--warmup`` untimed ones, with ``--threads`` intra-op threads; the models of one modality are timed
  interleaved (run r of each model, then run r + 1), so that load from other processes hits them alike.
  BatchNorm statistics are first filled by two train-mode forwards, so that activations have
  trained-network magnitudes; ``--channels-last`` switches the memory format;
* for the CVAE models also ``prior_ms`` (UNet stream alone) and ``decoder_b8_ms`` (the decoder on a batch of
  8 codes with batch-1 features: the finite-difference Jacobian of Eq. 17), medians, and
  ``decoder_gflops_per_code``;
* ``ratio_vs_fastdepth``: median forward time over FastDepth's for the same modality, from the same
  interleaved runs (the machines are shared; compare ratios, quote absolute times with the machine).

Usage::

    python benchmarks/bench_models.py                      # all 16 rows, 224x224, N=5, 2 threads
    python benchmarks/bench_models.py --models dit fastdepth --modalities grays --runs 20

Prints a markdown table and writes JSON (``--out``, default ``benchmarks/results/models.json``).
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import torch
from torch.utils.flop_counter import FlopCounterMode

from models import MODALITY_CHANNELS, MODEL_NAMES, build_model

DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "models.json"


def _stats(ts: list[float]) -> dict:
    """Mean, standard deviation, median and minimum of times [ms]."""
    return {
        "mean": statistics.fmean(ts),
        "std": statistics.stdev(ts) if len(ts) > 1 else 0.0,
        "median": statistics.median(ts),
        "min": min(ts),
    }


def _time_once(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return (time.perf_counter() - t0) * 1e3


def _time_ms(fn, warmup: int, runs: int) -> dict:
    for _ in range(warmup):
        fn()
    return _stats([_time_once(fn) for _ in range(runs)])


def _flops(fn) -> int:
    counter = FlopCounterMode(display=False)
    with counter:
        fn()
    return counter.get_total_flops()


def _sample_input(modality: str, h: int, w: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(1, MODALITY_CHANNELS[modality], h, w, generator=g)
    if modality.endswith("s"):  # 125 sparse depth samples, as at evaluation
        x[:, -1] = 0.0
        idx = torch.randperm(h * w, generator=g)[:125]
        x[0, -1].view(-1)[idx] = 0.5 + 4.5 * torch.rand(125, generator=g)
    return x


def _calibrate_bn(net: torch.nn.Module, modality: str, h: int, w: int, steps: int = 2) -> None:
    """Give BatchNorm running statistics from a few train-mode forwards (as a trained network has).

    Fresh statistics (mean 0, var 1) let eval-mode activations shrink to ~1e-16 through the depthwise layers,
    which is not what a trained network computes on.
    """
    for m in net.modules():
        if isinstance(m, torch.nn.modules.batchnorm._BatchNorm):
            m.reset_running_stats()
            m.momentum = None
    net.train()
    with torch.no_grad():
        for s in range(steps):
            x = torch.cat([_sample_input(modality, h, w, seed=100 + 2 * s + i) for i in range(2)])
            kw = {"code": torch.randn(2, net.code_dim)} if getattr(net, "code_dim", None) else {}
            net(x, **kw)
    net.eval()


def _prepare(name: str, modality: str, args) -> tuple[torch.nn.Module, torch.Tensor]:
    torch.manual_seed(0)
    net = build_model(name, modality, width_mult=args.width_mult, height=args.height, width=args.width)
    _calibrate_bn(net, modality, args.height, args.width)
    x = _sample_input(modality, args.height, args.width)
    if args.channels_last:
        net = net.to(memory_format=torch.channels_last)
        x = x.contiguous(memory_format=torch.channels_last)
    return net, x


def bench_modality(modality: str, args) -> list[dict]:
    """All models of one modality; forward timings interleaved (run r of every model, then run r + 1)."""
    nets = {name: _prepare(name, modality, args) for name in args.models}
    rows = {}
    with torch.inference_mode():
        for name, (net, x) in nets.items():
            rows[name] = {
                "model": name,
                "modality": modality,
                "params": sum(p.numel() for p in net.parameters()),
                "infer_params": sum(p.numel() for p in net.parameters())
                - (sum(p.numel() for p in net.recognition.parameters()) if MODEL_NAMES[name] else 0),
                "gflops": _flops(lambda net=net, x=x: net(x)) / 1e9,
            }
            for _ in range(args.warmup):
                net(x)
        times = {name: [] for name in nets}
        for _ in range(args.runs):
            for name, (net, x) in nets.items():
                times[name].append(_time_once(lambda net=net, x=x: net(x)))
        for name, (net, x) in nets.items():
            st = _stats(times[name])
            rows[name].update({f"forward_ms{'' if k == 'mean' else '_' + k}": v for k, v in st.items()})
            if MODEL_NAMES[name] is None or not args.parts:
                continue
            rows[name]["prior_ms"] = _time_ms(lambda net=net, x=x: net.prior(x), args.warmup, args.runs)[
                "median"
            ]
            _, feats = net.prior(x)
            codes = torch.randn(8, net.code_dim, generator=torch.Generator().manual_seed(1))
            one = functools.partial(net.decoder, codes[:1], *feats)
            batch = functools.partial(net.decoder, codes, *feats)
            rows[name]["decoder_gflops_per_code"] = _flops(one) / 1e9
            rows[name]["decoder_b8_ms"] = _time_ms(batch, args.warmup, args.runs)["median"]
        del nets
    return list(rows.values())


def markdown(rows: list[dict]) -> str:
    head = (
        "| model | modality | params (M) | infer params (M) | GFLOPs | forward ms mean ± std | median | min "
        "| vs fastdepth | prior ms | decoder b8 ms | decoder GFLOPs/code |"
    )
    lines = [head, "|" + "---|" * (head.count("|") - 1)]

    def f(v, fmt):
        return format(v, fmt) if v is not None else "-"

    for r in rows:
        lines.append(
            f"| {r['model']} | {r['modality']} | {r['params'] / 1e6:.2f} | {r['infer_params'] / 1e6:.2f} "
            f"| {r['gflops']:.2f} | {r['forward_ms']:.1f} ± {r['forward_ms_std']:.1f} "
            f"| {r['forward_ms_median']:.1f} | {r['forward_ms_min']:.1f} "
            f"| {f(r.get('ratio_vs_fastdepth'), '.2f')} | {f(r.get('prior_ms'), '.1f')} "
            f"| {f(r.get('decoder_b8_ms'), '.1f')} | {f(r.get('decoder_gflops_per_code'), '.3f')} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--models", nargs="+", default=list(MODEL_NAMES), choices=list(MODEL_NAMES))
    p.add_argument(
        "--modalities", nargs="+", default=list(MODALITY_CHANNELS), choices=list(MODALITY_CHANNELS)
    )
    p.add_argument("--height", type=int, default=224)
    p.add_argument("--width", type=int, default=224)
    p.add_argument("--width-mult", type=float, default=1.0)
    p.add_argument("--runs", type=int, default=5, help="timed forwards per row")
    p.add_argument("--warmup", type=int, default=2, help="untimed forwards before timing")
    p.add_argument("--threads", type=int, default=2, help="torch intra-op threads")
    p.add_argument("--channels-last", action="store_true", help="run in torch.channels_last memory format")
    p.add_argument(
        "--no-parts", dest="parts", action="store_false", help="skip prior / decoder-batch timings"
    )
    p.add_argument("--out", type=Path, default=DEFAULT_OUT, help="JSON output path")
    args = p.parse_args(argv)
    if args.runs < 1 or args.warmup < 0 or args.threads < 1:
        p.error(f"need runs >= 1, warmup >= 0, threads >= 1 (got {args.runs}, {args.warmup}, {args.threads})")

    torch.set_num_threads(args.threads)
    machine = {
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "threads": args.threads,
        "torch": torch.__version__,
        "python": sys.version.split()[0],
        "loadavg_start": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
    }
    rows = []
    for modality in args.modalities:
        rows += bench_modality(modality, args)
        for r in rows[-len(args.models) :]:
            print(
                f"  {r['model']:9s} {modality:5s} {r['forward_ms_median']:7.1f} ms",
                file=sys.stderr,
                flush=True,
            )
    for r in rows:  # ratio of medians of interleaved runs
        ref = [q for q in rows if q["model"] == "fastdepth" and q["modality"] == r["modality"]]
        r["ratio_vs_fastdepth"] = r["forward_ms_median"] / ref[0]["forward_ms_median"] if ref else None
    machine["loadavg_end"] = list(os.getloadavg()) if hasattr(os, "getloadavg") else None
    result = {
        "benchmark": "models",
        "config": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
        "machine": machine,
        "rows": rows,
    }
    print(
        f"\nModels at {args.height}x{args.width}, batch 1, torch {torch.__version__} CPU, "
        f"{args.threads} threads, "
        f"{'channels_last' if args.channels_last else 'NCHW'}, "
        f"mean ± std of {args.runs} runs after {args.warmup} warm-up; machine: {machine['processor']}, "
        f"{machine['cpu_count']} cores, load {machine['loadavg_start']}\n"
    )
    print(markdown(rows))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"\nwrote {args.out}")
    return result


if __name__ == "__main__":
    main()
