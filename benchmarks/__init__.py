"""Benchmark scripts: each prints a table and writes JSON (``benchmarks/results/`` holds the committed runs).

Run one as ``python benchmarks/bench_dense.py`` or ``python -m benchmarks.bench_dense``. They import the installed
packages (``pip install -e .``); notebooks and tests import their public functions from here.
"""
