"""Fixtures of the benchmark smoke tests: a tiny stand-in model (64x64) and one synthetic validation frame."""

import importlib.util
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[2]
H = W = 64


def load_script(name: str):
    """Import ``benchmarks/<name>.py`` (benchmarks/ is not an installed package)."""
    if f"_bench_{name}" in sys.modules:
        return sys.modules[f"_bench_{name}"]
    spec = importlib.util.spec_from_file_location(f"_bench_{name}", ROOT / "benchmarks" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)  # puts the repo root on sys.path for `benchmarks.common`
    return module


@pytest.fixture(scope="session")
def tiny(tmp_path_factory):
    """(stand-in model dir, NYU root with one val frame, benchmarks.common); built once per session."""
    torch.set_num_threads(1)
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    from benchmarks import common
    from sim.nyu import write_nyu_dataset

    base = tmp_path_factory.mktemp("bench")
    data = write_nyu_dataset(base / "nyu", n_train=0, n_val=1, seed=0, progress=False)
    model = common.standin_model("grays", H, W, 0.25, seed=0, out_dir=base / "standin", log=lambda *a: None)
    return model.model_dir, data, common


def standin_args(model_dir, data) -> list[str]:
    return [
        "--height",
        str(H),
        "--width",
        str(W),
        "--width-mult",
        "0.25",
        "--standin-dir",
        str(model_dir),
        "--data",
        str(data),
        "--threads",
        "1",
    ]
