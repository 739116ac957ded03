"""Named benchmark sequences, rendered (or completed) on first use into a data folder and reused afterwards.

Names (``benchmarks/bench_peers.py`` and ``benchmarks/ablate.py`` take them):

* ``PRESET_sSEED``: ``dit-sim euroc preset=PRESET seed=SEED duration=...`` with the preset's own realism
  (every preset is realistic by default), e.g. ``flight_s70``;
* ``PRESET-ideal_sSEED``: the same with ``realism=false``;
* ``mh05``: the real MH_05 excerpt of ``../shared/data`` completed by ``dit-sim imu`` (vibrating IMU, its default
  seed); ``mh05_sSEED``: the same with IMU seed ``SEED`` (``dit-sim imu seed=SEED``).
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from benchmarks.common import REPO

BIN = Path(sys.executable).parent
MH05 = REPO.parent / "shared" / "data" / "euroc_MH_05_excerpt"

__all__ = ["BIN", "MH05", "dit_sim", "parse_sequence", "ensure_sequence"]


def dit_sim(*args: str) -> None:
    """Run ``dit-sim`` with ``args``; raises RuntimeError with the end of its output when it fails."""
    r = subprocess.run([str(BIN / "dit-sim"), *args], capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"dit-sim {' '.join(args)} failed: {(r.stderr or r.stdout).strip()[-800:]}")


def parse_sequence(name: str) -> dict:
    """``flight_s1`` -> preset flight, seed 1, its own realism; ``flight-ideal_s0`` -> realism=false;
    ``mh05`` -> the real excerpt with the default IMU seed; ``mh05_s3`` -> IMU seed 3. Raises ValueError for
    another form."""
    if name == "mh05":
        return {"kind": "mh05"}
    stem, sep, seed = name.rpartition("_s")
    if not sep or not seed.isdigit() or not stem:
        raise ValueError(f"sequence name '{name}' is not PRESET_sSEED, PRESET-ideal_sSEED, mh05 or mh05_sSEED")
    if stem == "mh05":
        return {"kind": "mh05", "seed": int(seed)}
    preset, ideal = (stem[: -len("-ideal")], True) if stem.endswith("-ideal") else (stem, False)
    return {"kind": "sim", "preset": preset, "seed": int(seed), "realism": False if ideal else None}


def ensure_sequence(name: str, data: Path, duration: float) -> Path:
    """The rendered (or completed) sequence ``name`` under ``data``, made on first use (into a hidden folder
    renamed into place, so an interrupted render is made again)."""
    seq = Path(data) / name
    if (seq / "mav0" / "cam0" / "data.csv").is_file():
        return seq
    spec = parse_sequence(name)
    tmp = Path(data) / f".{name}.part"
    if spec["kind"] == "mh05":
        if not (MH05 / "mav0").is_dir():
            raise FileNotFoundError(f"{MH05}: the MH_05 excerpt is not here (../shared/data)")
        seed = [f"seed={spec['seed']}"] if "seed" in spec else []
        dit_sim("imu", f"source={MH05}", f"out={tmp}", "progress=false", *seed)
    else:
        extra = [] if spec["realism"] is None else ["realism=false"]
        dit_sim(
            "euroc",
            f"out={tmp}",
            f"preset={spec['preset']}",
            f"seed={spec['seed']}",
            f"duration={duration:g}",
            "progress=false",
            *extra,
        )
    tmp.rename(seq)
    return seq
