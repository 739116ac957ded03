"""Benchmark scripts: each prints a table and writes JSON (``benchmarks/results/`` holds the committed runs).

Run one as ``python benchmarks/bench_dense.py`` or ``python -m benchmarks.bench_dense``. They import the installed
packages (``pip install -e .``); notebooks and tests import their public functions from here.
"""

import os

# As apps/__init__.py (dit-slam): one OpenBLAS thread, so that `python -m benchmarks.<name>` times what dit-slam runs.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
