"""Depth metrics of an exported model (ONNX Runtime, code c = 0) on regenerated synthetic validation frames.

    python benchmarks/eval_onnx_depth.py --model runtime/assets/default_model [--n-val 20] [--seed 0] [--realism]
        [--out F.json]

The frames come from ``sim.nyu.write_nyu_dataset(n_train=1, n_val=N, seed=S, realism=R)`` (validation rooms are drawn
from their own seed branch, never seen in training), are prepared by training's evaluation transform (resize + centre
crop, 125 FAST corners without noise for the ``*s`` modalities) and decoded at the prior mean. The shipped model
records these figures in its folder (``val_metrics.json``); ``tests/test_default_model.py`` regenerates the frames
and checks them.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np


def onnx_depth_metrics(
    model_dir: str | Path,
    n_val: int = 20,
    seed: int = 0,
    data_root: str | Path | None = None,
    progress: bool = False,
    realism: bool = False,
) -> dict:
    """Mean per-image metrics (RMSE, iRMSE, AbsRel, MAE, MAPE, delta1-3) and ms/frame of ``model_dir``."""
    import torch

    from runtime.io.nyu import list_nyu_h5, read_nyu_h5
    from runtime.network import DepthNetwork
    from sim.nyu import write_nyu_dataset
    from train.augment import FrameTransform
    from train.metrics import DepthMetrics

    net = DepthNetwork(model_dir)
    tf = FrameTransform(net.height, net.width, net.modality, train=False)
    with tempfile.TemporaryDirectory() as tmp:
        root = (
            Path(data_root)
            if data_root
            else write_nyu_dataset(
                Path(tmp) / "val", n_train=1, n_val=n_val, seed=seed, progress=progress, realism=realism
            )
        )
        files = list_nyu_h5(root, "val")[:n_val]
        acc, times = DepthMetrics(), []
        for i, f in enumerate(files):
            rgb, depth = read_nyu_h5(f)
            sample = tf(rgb, depth, np.random.default_rng([seed, 0, i]))
            x = sample["image"]
            sparse = x[-1] if net.uses_sparse else None
            image = x[:-1] if net.uses_sparse else x
            image = image[0] if image.shape[0] == 1 else image.transpose(1, 2, 0)
            t0 = time.perf_counter()
            kf = net.prior(image, sparse)
            pred = kf.depth(np.zeros(net.code_dim, np.float32))
            times.append(time.perf_counter() - t0)
            acc.update(torch.from_numpy(pred[None, None]), torch.from_numpy(sample["depth"][None]))
    out = acc.compute()
    out["ms"] = 1000.0 * float(np.median(times))
    out["frames"] = len(files)
    if realism:
        out["realism"] = True
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", default="runtime/assets/default_model")
    p.add_argument("--n-val", type=int, default=20)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--data", default=None, help="an NYU-layout root to use instead of regenerating frames")
    p.add_argument("--realism", action="store_true", help="realistic rooms through the camera physics")
    p.add_argument("--out", default=None)
    a = p.parse_args()
    m = onnx_depth_metrics(a.model, a.n_val, a.seed, a.data, progress=True, realism=a.realism)
    from train.metrics import format_table

    print(format_table({f"{a.model} (ONNX, c=0)": m}))
    if a.out:
        Path(a.out).write_text(json.dumps(m, indent=2))
        print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
