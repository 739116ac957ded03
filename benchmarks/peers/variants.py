"""Variants of a rendered sequence with one realism effect taken out, for ablations of a run (``diagnose``):
the same images (linked, not copied), one file changed.

    python -m benchmarks.peers.variants --source outputs/peers/seq/flight_s0 --kind accel-bias-removed \\
        --out outputs/peers/diag/seq_flight_s0_noba

Kinds:

* ``accel-bias-removed`` / ``gyro-bias-removed``: ``imu0`` minus the ground truth's accelerometer (gyroscope) bias
  at each sample (interpolated in time), and that bias set to 0 in the ground truth;
* ``true-calibration``: ``cam0/sensor.yaml`` with the intrinsics and distortion the images were rendered with
  (``sim_info.json`` ``render_camera``) instead of the perturbed ones written for the system;
* ``true-time``: ``cam0`` stamps moved by ``sim_info.json`` ``time_offset_s`` (the frame stamped t shows the
  scene at t + offset), so that they are the true capture times.

The IMU without vibration is ``dit-sim imu source=... vibration=false`` (a refit of the IMU to the ground truth).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
from pathlib import Path

import numpy as np

KINDS = ("accel-bias-removed", "gyro-bias-removed", "true-calibration", "true-time")
_BIAS_COLS = {"gyro-bias-removed": (slice(0, 3), slice(10, 13)), "accel-bias-removed": (slice(3, 6), slice(13, 16))}


def _read_csv(path: Path) -> tuple[str, list[str], np.ndarray]:
    lines = [ln for ln in path.read_text().splitlines() if ln.strip()]
    head = [ln for ln in lines if ln.startswith("#")]
    rows = [ln.split(",") for ln in lines if not ln.startswith("#")]
    return (head[0] if head else ""), [r[0].strip() for r in rows], np.array([[float(x) for x in r[1:]] for r in rows])


def _write_csv(path: Path, head: str, ts: list[str], a: np.ndarray) -> None:
    body = "".join(t + "," + ",".join(repr(float(v)) for v in r) + "\n" for t, r in zip(ts, a, strict=True))
    path.write_text((head + "\n" if head else "") + body)


def _link(src: Path, dst: Path) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    os.symlink(src.resolve(), dst)


def make_variant(source: str | Path, out: str | Path, kind: str) -> Path:
    """Write the variant ``kind`` of the EuRoC-layout sequence ``source`` into ``out`` (which must not exist)."""
    if kind not in KINDS:
        raise ValueError(f"unknown variant '{kind}' (known: {', '.join(KINDS)})")
    src, out = Path(source), Path(out)
    if out.exists():
        raise FileExistsError(f"{out}: exists already; the variant is written into a new folder")
    mav = src / "mav0"
    if not (mav / "cam0" / "data.csv").is_file():
        raise FileNotFoundError(f"{mav / 'cam0' / 'data.csv'}: not an EuRoC-layout sequence")
    info_path = src / "sim_info.json"
    info = json.loads(info_path.read_text()) if info_path.is_file() else {}
    changed = {"imu0/data.csv", "state_groundtruth_estimate0/data.csv"} if kind in _BIAS_COLS else set()
    changed |= {"cam0/sensor.yaml"} if kind == "true-calibration" else set()
    changed |= {"cam0/data.csv"} if kind == "true-time" else set()
    for d in sorted(p for p in mav.iterdir() if p.is_dir()):
        mine = {c.split("/")[1] for c in changed if c.startswith(d.name + "/")}
        if not mine:
            _link(d, out / "mav0" / d.name)
            continue
        (out / "mav0" / d.name).mkdir(parents=True)
        for f in d.iterdir():
            if f.name not in mine:
                _link(f, out / "mav0" / d.name / f.name)
    if info_path.is_file():
        shutil.copy(info_path, out / "sim_info.json")
    if kind in _BIAS_COLS:
        _remove_bias(mav, out / "mav0", *_BIAS_COLS[kind])
    elif kind == "true-calibration":
        cam = info.get("render_camera")
        if not cam or len(cam) < 8:
            raise KeyError(f"{info_path}: no 'render_camera' (fx fy cx cy k1 k2 p1 p2) to restore")
        text = (mav / "cam0" / "sensor.yaml").read_text()
        text = re.sub(r"(?m)^intrinsics:.*$", f"intrinsics: [{', '.join(repr(float(v)) for v in cam[:4])}]", text)
        dist = ", ".join(repr(float(v)) for v in cam[4:8])
        text = re.sub(r"(?m)^distortion_coefficients:.*$", f"distortion_coefficients: [{dist}]", text)
        (out / "mav0" / "cam0" / "sensor.yaml").write_text(text)
    else:
        if info.get("time_offset_s") is None:
            raise KeyError(f"{info_path}: no 'time_offset_s'")
        shift = int(round(float(info["time_offset_s"]) * 1e9))
        lines = (mav / "cam0" / "data.csv").read_text().splitlines()
        rows = [ln if ln.startswith("#") or not ln.strip() else _shift(ln, shift) for ln in lines]
        (out / "mav0" / "cam0" / "data.csv").write_text("\n".join(rows) + "\n")
    return out


def _shift(line: str, shift: int) -> str:
    t, _, rest = line.partition(",")
    return f"{int(t) + shift},{rest}"


def _remove_bias(mav: Path, out: Path, imu_cols: slice, gt_cols: slice) -> None:
    head_i, ts_i, imu = _read_csv(mav / "imu0" / "data.csv")
    head_g, ts_g, gt = _read_csv(mav / "state_groundtruth_estimate0" / "data.csv")
    ti, tg = np.array(ts_i, np.int64), np.array(ts_g, np.int64)
    bias = np.column_stack([np.interp((ti - tg[0]) * 1e-9, (tg - tg[0]) * 1e-9, gt[:, c]) for c in range(16)[gt_cols]])
    imu[:, imu_cols] -= bias
    gt[:, gt_cols] = 0.0
    _write_csv(out / "imu0" / "data.csv", head_i, ts_i, imu)
    _write_csv(out / "state_groundtruth_estimate0" / "data.csv", head_g, ts_g, gt)


def main(argv: list[str] | None = None) -> Path:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--source", required=True, help="EuRoC-layout sequence (dit-sim output)")
    ap.add_argument("--kind", required=True, choices=KINDS)
    ap.add_argument("--out", required=True, help="new folder for the variant")
    a = ap.parse_args(argv)
    out = make_variant(a.source, a.out, a.kind)
    print(f"wrote {out} ({a.kind} of {a.source})")
    return out


if __name__ == "__main__":
    main()
