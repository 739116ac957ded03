"""Fixtures of the benchmark smoke tests: a tiny stand-in model (64x64) and one synthetic validation frame."""

import pytest
import torch

from benchmarks import common

H = W = 64


@pytest.fixture(scope="session")
def tiny(standin_64):
    """(stand-in model dir, NYU root with one val frame, benchmarks.common); built once per session
    (``tests/conftest.py::standin_64``, shared with notebook 02's test)."""
    torch.set_num_threads(1)
    return standin_64.model_dir, standin_64.data, common


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
