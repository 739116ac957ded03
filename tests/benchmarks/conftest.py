"""Fixtures of the benchmark smoke tests: a tiny stand-in model (64x64) and one synthetic validation frame."""

import pytest
import torch

from benchmarks import common

H = W = 64


@pytest.fixture(scope="session")
def tiny(tmp_path_factory):
    """(stand-in model dir, NYU root with one val frame, benchmarks.common); built once per session."""
    torch.set_num_threads(1)
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
