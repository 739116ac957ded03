"""Training throughput (images/s) per model variant at 224x224 on this machine; prints a table, writes JSON.

    python benchmarks/bench_train.py                       # 4 variants, grays, batch 8, 224x224
    python benchmarks/bench_train.py --modalities rgb grays --batch 16 --size 128 128 --out /tmp/b.json

For each variant and modality: the optimisation step alone (forward with the ground truth, Eq. 8 / L1 loss,
backward, AdamW step; random inputs, timed after warm-up, median over ``--steps``), the data pipeline alone
(read an NYU-layout h5 frame, training augmentation, FAST sparse sampling; from the synthetic cache when
present, else from an in-memory synthetic frame) and their serial combination ``1 / (1/step + 1/data)``, which
is what one process with ``num_workers=0`` achieves. Torch uses ``--threads`` threads (default: torch's
default); idle OpenMP threads sleep (OMP_WAIT_POLICY=PASSIVE, as train/fit.py). These machines are shared:
compare variants within one run, not across runs.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

from models import MODALITY_CHANNELS, build_model  # noqa: E402
from models.losses import total_loss  # noqa: E402

VARIANTS = ("dit", "codevio8", "codevio32", "fastdepth")


def step_throughput(name: str, modality: str, h: int, w: int, batch: int, steps: int, warmup: int) -> dict:
    torch.manual_seed(0)
    net = build_model(name, modality, height=h, width=w).train()
    opt = torch.optim.AdamW(net.parameters(), 1e-3)
    cin = MODALITY_CHANNELS[modality]
    x = torch.rand(batch, cin, h, w)
    if modality.endswith("s"):
        x[:, -1] = torch.where(torch.rand(batch, h, w) < 0.005, 1.0 + 3.0 * torch.rand(batch, h, w), 0.0)
    gt = 1.0 + 3.0 * torch.rand(batch, 1, h, w)
    times = []
    for i in range(warmup + steps):
        t0 = time.perf_counter()
        out = net(x, gt_depth=gt)
        loss, _ = total_loss(out, gt)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if i >= warmup:
            times.append(time.perf_counter() - t0)
    t = statistics.median(times)
    return {
        "step_ms": 1000.0 * t,
        "step_img_s": batch / t,
        "params": sum(p.numel() for p in net.parameters()),
    }


def data_throughput(modality: str, h: int, w: int, n: int) -> dict:
    from train.augment import FrameTransform
    from train.data import NyuFrames, NyuH5Dataset, default_sim_root

    tf = FrameTransform(h, w, modality, train=True)
    root = default_sim_root(1000, 100, 0)
    try:
        ds = NyuH5Dataset(root, "train", tf)
        source = f"h5 frames in {root}"
    except (ValueError, OSError):
        rng = np.random.default_rng(0)
        rgb = (rng.random((480, 640, 3)) * 255).astype(np.uint8)
        depth = (1.0 + 3.0 * rng.random((480, 640))).astype(np.float32)

        class _Mem:
            def __len__(self):
                return 1

            def __getitem__(self, i):
                return rgb, depth

        ds = NyuFrames(_Mem(), tf)
        source = "one in-memory 480x640 frame (no file reading)"
    t0 = time.perf_counter()
    for i in range(n):
        ds[(0, i, i % len(ds))]
    t = (time.perf_counter() - t0) / n
    return {"data_ms_per_img": 1000.0 * t, "data_img_s": 1.0 / t, "data_source": source}


def _cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description="training throughput per variant")
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--modalities", nargs="+", default=["grays"], choices=list(MODALITY_CHANNELS))
    ap.add_argument("--size", nargs=2, type=int, default=[224, 224], metavar=("H", "W"))
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--data-frames", type=int, default=40)
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent / "results" / "bench_train.json"))
    a = ap.parse_args(argv)
    if a.threads:
        torch.set_num_threads(a.threads)
    h, w = a.size
    rows = []
    data = {m: data_throughput(m, h, w, a.data_frames) for m in a.modalities}
    for m in a.modalities:
        for v in a.variants:
            r = {
                "variant": v,
                "modality": m,
                **step_throughput(v, m, h, w, a.batch, a.steps, a.warmup),
                **data[m],
            }
            r["combined_img_s"] = 1.0 / (1.0 / r["step_img_s"] + 1.0 / r["data_img_s"])
            rows.append(r)
            print(f"  {v}/{m}: {r['step_img_s']:.1f} img/s", flush=True)
    env = {
        "machine": platform.machine(),
        "cpu": _cpu_name(),
        "cpus": os.cpu_count(),
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "load_avg_1min": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
        "size": [h, w],
        "batch": a.batch,
        "steps": a.steps,
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
    }
    print(
        f"\nTraining throughput at {h}x{w}, batch {a.batch}, {env['threads']} torch threads, "
        f"{env['cpus']} CPUs ({env['cpu']}) "
        f"(1-min load average at the end: {env['load_avg_1min']:.1f}); data: {rows[0]['data_source']}\n"
    )
    print("| variant | modality | params | step [ms] | step [img/s] | data [img/s] | step + data [img/s] |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['variant']} | {r['modality']} | {r['params'] / 1e6:.2f} M | {r['step_ms']:.0f} | "
            f"{r['step_img_s']:.1f} | {r['data_img_s']:.1f} | {r['combined_img_s']:.1f} |"
        )
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    res = {"env": env, "rows": rows}
    out.write_text(json.dumps(res, indent=2))
    print(f"\nwrote {out}")
    return res


if __name__ == "__main__":
    main()
