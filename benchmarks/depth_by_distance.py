"""Where an exported depth network wins or loses against the interpolation of its own sparse input.

    python benchmarks/depth_by_distance.py --model runtime/assets/default_model --real ../shared/data/rgbd_real
        [--sim-val 40] [--out F.json]

The paper's G-S protocol (125 FAST points with their true depth, no noise, code c = 0), on the frame sets of
``dit-eval depth``. Per set it prints and writes:

* how far the network's depth departs from the sparse depth at the sample pixels, ``|log(depth / sparse)|``
  (median and 90th percentile). The interpolation is exact there, so a network that departs has learned to
  distrust its points;
* the RMSE of the network and of the interpolation by distance to the nearest sample (pixels, at network
  resolution). It says whether a gap lies next to the points or between them;
* the same by the network's relative uncertainty ``B / depth`` (Eq. 6's ``B``) at each pixel. It says whether the
  uncertainty marks the pixels where the correction fails, which a gate on it would need;
* the RMSE with the network's correction of the interpolation scaled by ``alpha``, ``fill * (depth / fill) ** alpha``
  (0: the interpolation, 1: the network). A best ``alpha`` near 1 says the correction is right and only its size
  could be tuned; near 0, that on this set it carries little information beyond the interpolation.
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy.ndimage import distance_transform_edt

#: Distance bins [px] to the nearest sample: [0, 2), [2, 5), ... [20, inf).
EDGES = (0.0, 2.0, 5.0, 10.0, 20.0, np.inf)
#: Bins of the relative uncertainty ``B / depth``.
UNC_EDGES = (0.0, 0.05, 0.1, 0.25, np.inf)
#: Scales of the network's correction of the interpolation (0: the interpolation, 1: the network).
ALPHAS = (0.0, 0.25, 0.5, 0.75, 1.0, 1.25, 1.5)


def scaled_correction(depth: np.ndarray, fill: np.ndarray, alpha: float) -> np.ndarray:
    """``fill * (depth / fill) ** alpha``: the network's correction of the interpolation ``fill``, scaled in log depth.

    >>> scaled_correction(np.array([4.0, 1.0]), np.array([1.0, 1.0]), 0.5).tolist()
    [2.0, 1.0]
    """
    return fill * np.exp(alpha * np.log(depth / fill))


def sample_departure(depth: np.ndarray, sparse: np.ndarray) -> np.ndarray:
    """``|log(depth / sparse)|`` at the pixels with a sample (``sparse > 0``), one value a sample.

    >>> sample_departure(np.array([[2.0, 1.0]]), np.array([[1.0, 0.0]])).round(3).tolist()
    [0.693]
    """
    m = sparse > 0
    return np.abs(np.log(depth[m] / sparse[m]))


def squared_errors_binned(preds: list[np.ndarray], gt: np.ndarray, key: np.ndarray, edges) -> list[list[np.ndarray]]:
    """Squared depth errors of the pixels with ground truth, split by a per-pixel ``key`` (H, W).

    Args:
        preds: (H, W) depth predictions [m], scored on the same bins.
        gt: (H, W) depth [m], 0 = invalid.
        edges: increasing bin edges; bin k holds keys in ``[edges[k], edges[k + 1])``.

    Returns:
        per prediction, one array of squared errors per bin.
    """
    valid = gt > 0
    masks = [valid & (key >= lo) & (key < hi) for lo, hi in zip(edges[:-1], edges[1:], strict=True)]
    return [[((pred - gt) ** 2)[m] for m in masks] for pred in preds]


def squared_errors_by_distance(
    preds: list[np.ndarray], gt: np.ndarray, sparse: np.ndarray, edges=EDGES
) -> list[list[np.ndarray]]:
    """:func:`squared_errors_binned` by the distance [px] to the nearest sample (``sparse`` > 0)."""
    return squared_errors_binned(preds, gt, distance_transform_edt(sparse <= 0), edges)


def _bin_rows(sq_net: list[list], sq_itp: list[list], edges, lo_key: str, hi_key: str) -> list[dict]:
    """Pooled RMSE of the network and of the interpolation per bin."""
    rows = []
    for k, (lo, hi) in enumerate(zip(edges[:-1], edges[1:], strict=True)):
        a, b = np.concatenate(sq_net[k]), np.concatenate(sq_itp[k])
        rows.append(
            {
                lo_key: float(lo),
                hi_key: None if np.isinf(hi) else float(hi),
                "pixels": int(a.size),
                "network_rmse_m": float(np.sqrt(a.mean())) if a.size else None,
                "interpolation_rmse_m": float(np.sqrt(b.mean())) if b.size else None,
            }
        )
    return rows


def evaluate(net, sets: dict, edges=EDGES) -> dict:
    """The figures of the module docstring for ``net`` (a :class:`runtime.network.DepthNetwork`) on each frame
    set (``train.evaluate.protocol_sets``)."""
    from train.sparse import interpolate_sparse

    code = np.zeros(net.code_dim, np.float32)
    out = {}
    for name, ds in sets.items():
        dep, sq_net, sq_itp = [], [[] for _ in edges[1:]], [[] for _ in edges[1:]]
        uq_net, uq_itp = [[] for _ in UNC_EDGES[1:]], [[] for _ in UNC_EDGES[1:]]
        sq_scaled = [[] for _ in ALPHAS]
        for i in range(len(ds)):
            item = ds[i]
            image, gt = np.asarray(item["image"]), np.asarray(item["depth"])[0]
            sparse = image[-1]
            prior = net.prior(image[0], sparse)
            depth = prior.depth(code)
            dep.append(sample_departure(depth, sparse))
            fill = interpolate_sparse(sparse)
            valid = gt > 0
            for k, a in enumerate(ALPHAS):
                sq_scaled[k].append(((scaled_correction(depth, fill, a) - gt) ** 2)[valid])
            binned = (
                (squared_errors_by_distance([depth, fill], gt, sparse, edges), (sq_net, sq_itp)),
                (squared_errors_binned([depth, fill], gt, prior.uncertainty / depth, UNC_EDGES), (uq_net, uq_itp)),
            )
            for per_pred, accs in binned:
                for acc, bins in zip(accs, per_pred, strict=True):
                    for k, e in enumerate(bins):
                        acc[k].append(e)
        d = np.concatenate(dep)
        scaled = [float(np.sqrt(np.concatenate(e).mean())) for e in sq_scaled]
        itp = scaled[ALPHAS.index(0.0)]
        out[name] = {
            "frames": len(ds),
            "departure_at_samples": {"median": float(np.median(d)), "p90": float(np.quantile(d, 0.9))},
            "by_distance": _bin_rows(sq_net, sq_itp, edges, "from_px", "to_px"),
            "by_relative_uncertainty": _bin_rows(uq_net, uq_itp, UNC_EDGES, "from", "to"),
            "correction_scaled": [
                {"alpha": a, "rmse_m": e, "ratio_to_interpolation": e / itp}
                for a, e in zip(ALPHAS, scaled, strict=True)
            ],
            "best_alpha": ALPHAS[int(np.argmin(scaled))],
        }
    return out


def _fmt(x: float | None) -> str:
    return "-" if x is None else f"{x:.3f}"


def _print_bins(title: str, rows: list[dict], lo_key: str, hi_key: str) -> None:
    """A markdown table of :func:`_bin_rows`' rows, ``title`` naming the binned quantity."""
    print(f"| {title} | pixels | network RMSE [m] | interpolation RMSE [m] |")
    print("|---|---|---|---|")
    for b in rows:
        span = f"{b[lo_key]:g}-{b[hi_key]:g}" if b[hi_key] is not None else f">= {b[lo_key]:g}"
        print(f"| {span} | {b['pixels']} | {_fmt(b['network_rmse_m'])} | {_fmt(b['interpolation_rmse_m'])} |")


def main(argv: list[str] | None = None) -> dict:
    from benchmarks.common import gs_protocol_sets, machine_info, write_json
    from runtime.network import DepthNetwork, default_model_dir

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", default=str(default_model_dir()), help="exported model directory")
    ap.add_argument("--real", default=None, help="RGB-D frame folders in the rgbd_real layout (or one folder)")
    ap.add_argument("--sim-val", type=int, default=0, help="fresh realistic synthetic rooms (seed 1000)")
    ap.add_argument("--limit", type=int, default=None, help="first N frames of each set")
    ap.add_argument("--out", default=None, help="JSON path")
    args = ap.parse_args(argv)
    net = DepthNetwork(args.model)
    if not net.uses_sparse:
        raise SystemExit(f"{args.model}: a {net.modality} model has no sparse input to compare with")
    res = evaluate(net, gs_protocol_sets(net, args.real, args.sim_val, args.limit))
    for name, r in res.items():
        dep = r["departure_at_samples"]
        print(
            f"\n{name}: {r['frames']} frames; |log(depth / sparse)| at the samples: median {dep['median']:.4f}, "
            f"p90 {dep['p90']:.4f}"
        )
        _print_bins("distance to nearest sample [px]", r["by_distance"], "from_px", "to_px")
        _print_bins("relative uncertainty B / depth", r["by_relative_uncertainty"], "from", "to")
        cs = "  ".join(f"{c['alpha']:g}: {c['ratio_to_interpolation']:.3f}" for c in r["correction_scaled"])
        print(f"correction scaled by alpha, RMSE over interpolation: {cs} (best alpha {r['best_alpha']:g})")
    doc = {"model": str(args.model), "protocol": "gs", "sets": res, "machine": machine_info()}
    if args.out:
        print(f"wrote {write_json(args.out, doc)}")
    return doc


if __name__ == "__main__":
    main()
