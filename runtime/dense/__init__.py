"""The dense side of the system: depth codes in the sliding window (Eq. 13-17), the Sec. 5.2 sampler and the
local dense map. One idea a module:

* :mod:`runtime.dense.config`: :class:`DenseConfig` (with :class:`DepthFactorConfig`, :class:`DenseMapConfig`);
* :mod:`runtime.dense.lookup`: bilinear lookup and the depth-edge test;
* :mod:`runtime.dense.factors`: the Eq. 13 and Eq. 14 GTSAM factors;
* :mod:`runtime.dense.sampling`: the Sec. 5.2 pixel sampler of Eq. 14;
* :mod:`runtime.dense.linearized`: the decoder cache (:class:`LinearizedDepth`) and its error probe;
* :mod:`runtime.dense.mapper`: :class:`DenseMapper`, the backend's factor provider;
* :mod:`runtime.dense.map`: back-projection, uncertainty filter, voxel means, per-keyframe maps, depth metrics;
* :mod:`runtime.dense.fusion`: the fused dense map of a run (``VoxelMap``, written by ``write_fused_map``).
"""

from runtime.dense.config import DenseConfig, DenseMapConfig, DepthFactorConfig
from runtime.dense.linearized import ApproxErrorProbe, LinearizedDepth
from runtime.dense.mapper import DenseMapper, DepthSource, network_depth

__all__ = [
    "DenseConfig",
    "DepthFactorConfig",
    "DenseMapConfig",
    "DenseMapper",
    "DepthSource",
    "network_depth",
    "LinearizedDepth",
    "ApproxErrorProbe",
]
