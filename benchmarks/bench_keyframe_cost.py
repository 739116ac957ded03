"""Per-keyframe cost of the depth network, two exported models side by side: prior + code Jacobian.

What a keyframe pays in ``dit-slam`` with dense on: ``DepthNetwork.prior(grey, sparse)`` once (for a relative model
this includes the interpolation of the sparse depth that ``prior.onnx`` takes as ``fill``), then the
finite-difference Jacobian (Eq. 17) at a fresh code. Both models are timed in interleaved blocks of one run
(``benchmarks.common.time_blocks``), so the ratio holds on a loaded machine; absolute milliseconds come with the
CPU model.

Usage::

    python benchmarks/bench_keyframe_cost.py --base runtime/assets/default_model --new OUT/model [--points 125]

Prints a table and writes ``keyframe_cost.json`` into ``--out`` (default ``benchmarks/results/``).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from benchmarks import common


def _frame(h: int, w: int, points: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A smooth grey image and ``points`` sparse depths (0.5-6 m) at random pixels, at network size."""
    import cv2

    rng = np.random.default_rng(seed)
    grey = cv2.resize(rng.random((h // 8, w // 8)).astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR)
    sparse = np.zeros((h, w), np.float32)
    idx = rng.choice(h * w, size=min(points, h * w), replace=False)
    sparse.flat[idx] = rng.uniform(0.5, 6.0, len(idx))
    return grey, sparse


def keyframe_fn(model_dir: Path, points: int, threads: int, seed: int = 0):
    """A function running one keyframe's prior and Jacobian (a new code each call), and the network."""
    from runtime.network import DepthNetwork, SessionConfig

    net = DepthNetwork(model_dir, SessionConfig(threads=threads))
    grey, sparse = _frame(net.height, net.width, points, seed)
    rng = np.random.default_rng(seed)

    def run() -> None:
        kf = net.prior(grey, sparse)
        kf.jacobian(rng.normal(0.0, 0.5, net.code_dim).astype(np.float32))

    return run, net


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--base", type=Path, required=True, help="exported model directory: the reference")
    p.add_argument("--new", type=Path, required=True, help="exported model directory: the one compared")
    p.add_argument("--points", type=int, default=125, help="sparse depth samples per keyframe")
    p.add_argument("--threads", type=int, default=1, help="ORT intra-op threads (the runtime default: 1)")
    p.add_argument("--runs", type=int, default=30, help="timed keyframes per model")
    p.add_argument("--rounds", type=int, default=5, help="interleaved rounds")
    p.add_argument("--out", type=Path, default=common.RESULTS)
    args = p.parse_args(argv)
    for d in (args.base, args.new):
        if not (d / "manifest.json").is_file():
            p.error(f"{d}: no manifest.json (expected a dit-export folder)")
    fns, nets = {}, {}
    for name, d in (("base", args.base), ("new", args.new)):
        fns[name], nets[name] = keyframe_fn(d, args.points, args.threads)
    stats = common.time_blocks(fns, args.runs, warmup=2, rounds=args.rounds)
    ratio = stats["new"]["median_ms"] / stats["base"]["median_ms"]
    rows = [
        [name, str(d), "fill + prior + J" if nets[name].takes_fill else "prior + J", f"{s['median_ms']:.1f}"]
        for (name, d), s in zip((("base", args.base), ("new", args.new)), stats.values(), strict=True)
    ]
    print(common.markdown_table(["model", "dir", "per keyframe", "median ms"], rows))
    print(f"\nratio new / base: {ratio:.2f} (median of {stats['new']['n']} keyframes each)")
    out = {
        "machine": common.machine_info(ort_threads=args.threads),
        "points": args.points,
        "models": {"base": str(args.base), "new": str(args.new)},
        "stats": stats,
        "ratio_new_over_base": ratio,
    }
    common.write_json(args.out / "keyframe_cost.json", out)
    return out


if __name__ == "__main__":
    main()
