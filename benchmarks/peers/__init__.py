"""Helpers of ``benchmarks/bench_peers.py``: the peers' settings, their runners and the common scoring.

``settings`` and ``scoring`` need only numpy, PyYAML and evo (tested without the peers installed); the runners
(``orbslam3``, ``cuvslam``) import ``pyorbslam3`` / ``dim_odom`` from the extra ``peers`` and run in a child
process of the benchmark. Nothing in ``runtime/`` imports this package.
"""
