"""Diagnostics outside the SLAM hot path: tools that benchmarks and notebooks inject or call to explain a run's
figures.

:mod:`runtime.diagnostics.oracle_depth`: the rendered depth in place of the network's prior (an upper bound).
:mod:`runtime.diagnostics.coast`: the IMU-only coast in front of a textureless wall, smoothed from exact end
states (oracles), and a run's ATE split around that coast.
"""
