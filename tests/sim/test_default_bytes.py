"""The output of ``textured`` and ``whitewall`` with ``realism=false`` and of ``dit-sim nyu`` is unchanged byte
for byte.

Every preset is realistic by default; the earlier synthetic data stay available (``realism=false``), and
runtime changes are also judged by ATE on them, so they must stay what they were. The hashes below were
computed with the code of commit 37c3c9b.

The bytes depend on the CPU's vector paths as well: OpenBLAS's kernel (``DYNAMIC_ARCH``) and numpy's dispatched
loops round differently with AVX-512 than with AVX2, and the rendered pixels and IMU samples move in their last
bits (on an AVX-512 AMD EPYC every EuRoC hash differed). The hashes are those of the AVX2 paths, so the data are
written in a subprocess that asks for them (``OPENBLAS_CORETYPE=Haswell``, numpy's AVX-512 dispatch targets
disabled); docs/PITFALLS.md.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import pytest

EXPECTED = {
    "textured": "29346709dbd702f6e0d4961902348c182f76fbed0fc250f68345c2c611c9b346",
    "whitewall": "443e9f1d1b593325585fdfbd016ef149869ab8647c75bacade393c268b33d129",
    "nyu": "fbafe6a7a57d3147a19d19e986056efb25c752f68fc028ba6128cda5735d7b0d",
}


def _avx2_env() -> dict:
    """The environment that makes OpenBLAS and numpy use their AVX2 paths on any x86-64 CPU that has them."""
    from numpy._core import _multiarray_umath as m

    wide = [t for t in m.__cpu_dispatch__ if m.__cpu_features__.get(t) and (t == "X86_V4" or t.startswith("AVX512"))]
    env = dict(os.environ, OPENBLAS_CORETYPE="Haswell")
    env.pop("NPY_DISABLE_CPU_FEATURES", None)
    if wide:
        env["NPY_DISABLE_CPU_FEATURES"] = " ".join(wide)
    return env


def _write(code: str) -> None:
    """Run ``code`` (which writes a data set) in a fresh interpreter with AVX2 numerics."""
    subprocess.run([sys.executable, "-c", code], env=_avx2_env(), check=True, cwd=Path(__file__).parents[2])


def _digest(root: Path) -> str:
    h = hashlib.sha256()
    for p in sorted(root.rglob("*")):
        if p.is_file():
            h.update(p.relative_to(root).as_posix().encode())
            h.update(p.read_bytes())
    return h.hexdigest()


@pytest.mark.parametrize(("preset", "duration"), [("textured", 3.0), ("whitewall", 24.0)])
def test_default_euroc_bytes_unchanged(tmp_path, preset, duration):
    root = tmp_path / preset
    _write(
        "from sim.euroc import write_euroc_sequence; "
        f"write_euroc_sequence({str(root)!r}, {preset!r}, duration={duration}, seed=3, imu_noise=True, "
        "progress=False, scale=0.125, realism=False)"
    )
    assert _digest(root) == EXPECTED[preset]


def test_default_nyu_bytes_unchanged(tmp_path):
    root = tmp_path / "nyu"
    _write(
        "from sim.nyu import write_nyu_dataset; "
        f"write_nyu_dataset({str(root)!r}, n_train=1, n_val=1, seed=3, progress=False, frames_per_scene=1, "
        "compression=None)"
    )
    assert _digest(root) == EXPECTED["nyu"]
