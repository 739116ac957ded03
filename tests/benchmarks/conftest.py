"""Fixtures of the benchmark smoke tests: a tiny stand-in model (64x64), one synthetic validation frame, and a
user's ^C in the middle of a benchmark's runs."""

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


@pytest.fixture
def interrupt_second_run(monkeypatch):
    """``patch(module)``: the second call of ``module.run_sequence`` is stopped by a KeyboardInterrupt (a user's
    ^C); returns the list of the output folder names it is called with (clear it to count again)."""

    def patch(module) -> list[str]:
        real, calls = module.run_sequence, []

        def interrupted(seq, out, *a, **kw):
            calls.append(out.name)
            if len(calls) == 2:
                raise KeyboardInterrupt
            return real(seq, out, *a, **kw)

        monkeypatch.setattr(module, "run_sequence", interrupted)
        return calls

    return patch
