"""Shared data of the reliability suite: one tiny rendered sequence (4 s, 188x120)."""

import pytest


@pytest.fixture(scope="session")
def tiny_seq(tmp_path_factory):
    sim_euroc = pytest.importorskip("sim.euroc")
    out = tmp_path_factory.mktemp("rel") / "seq"
    return sim_euroc.write_euroc_sequence(out, "textured", duration=4.0, seed=1, progress=False, scale=0.25)
