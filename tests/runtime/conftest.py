"""Runtime tests read log records (caplog): make sure no earlier logging config (e.g. a Hydra entry point run
in
the same process with ``job_logging: disabled``) has muted the runtime's loggers."""

import logging

import pytest


@pytest.fixture(autouse=True)
def _runtime_loggers_enabled():
    for name in list(logging.root.manager.loggerDict):
        if name.startswith("runtime"):
            logging.getLogger(name).disabled = False
    yield
