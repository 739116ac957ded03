"""Session fixtures shared across test folders: the 64x64 stand-in model and one synthetic NYU frame."""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import pytest


class Standin64(NamedTuple):
    cache: Path  # a ``DIT_SLAM_CACHE`` holding the export under the name the benchmarks look up
    model_dir: Path  # the exported stand-in (grays, 64x64, width 0.25, seed 0)
    data: Path  # NYU layout root with one synthetic val frame (seed 0)


@pytest.fixture(scope="session")
def standin_64(tmp_path_factory) -> Standin64:
    """The benchmarks' stand-in network exported once per session (an ONNX export is tens of seconds).

    Exported with ``benchmarks.common.standin_model`` into the cache folder that the benchmarks use when no
    ``--standin-dir`` is given, so that a run with ``DIT_SLAM_CACHE=cache`` (notebook 02) reuses it after its
    own parity check, as a second run on a user's machine does.
    """
    import torch

    from benchmarks import common
    from sim.nyu import write_nyu_dataset

    base = tmp_path_factory.mktemp("standin64")
    cache = base / "cache"
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with pytest.MonkeyPatch.context() as mp:
            mp.setenv("DIT_SLAM_CACHE", str(cache))
            model = common.standin_model("grays", 64, 64, 0.25, seed=0, log=lambda *a: None)
    finally:
        torch.set_num_threads(threads)
    assert model.model_dir.parent == cache
    data = write_nyu_dataset(base / "nyu", n_train=0, n_val=1, seed=0, progress=False)
    return Standin64(cache, Path(model.model_dir), Path(data))
