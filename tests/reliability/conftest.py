"""Shared data of the reliability suite: one tiny rendered sequence (4 s, 188x120); the logging state restored
after each test."""

import logging

import pytest


@pytest.fixture(scope="session")
def tiny_seq(tmp_path_factory):
    sim_euroc = pytest.importorskip("sim.euroc")
    out = tmp_path_factory.mktemp("rel") / "seq"
    return sim_euroc.write_euroc_sequence(out, "textured", duration=4.0, seed=1, progress=False, scale=0.25)


@pytest.fixture(autouse=True)
def _logging_restored():
    """Commands run in-process (``dit-sim``'s ``hydra/job_logging: disabled``) disable every existing logger and
    set the root level to ERROR; later tests that check log records (caplog) need them back as they were."""
    root = logging.getLogger()
    level = root.level
    manager = logging.root.manager
    disabled = {n: lg.disabled for n, lg in manager.loggerDict.items() if isinstance(lg, logging.Logger)}
    yield
    root.setLevel(level)
    for name, lg in list(manager.loggerDict.items()):
        if isinstance(lg, logging.Logger):
            lg.disabled = disabled.get(name, False)
