"""The ground-truth depth source: a diagnostic upper bound of the dense system (bench mode ``dense_gt_eq13_14``).

A keyframe's depth is the rendered depth (``mav0/depth0``) plus the network's code-dependent part,
``D(c) = D_gt + D_net(c) - D_net(0)``, so the codes and the code Jacobian are the network's, with the
uncertainty ``b`` everywhere: it tells what a perfect depth network would buy. Pass it to the mapper,
``DenseMapper(..., depth_source=oracle_depth_source(seq.depth))``.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from runtime.dense.map import gt_depth_to_network
from runtime.geometry import Camera, NetworkMapping

__all__ = ["GroundTruthDepth", "OracleDepthSource", "oracle_depth_source"]


class GroundTruthDepth:
    """A keyframe's depth with the rendered ground truth in place of the prior.

    ``D(c) = D_gt + D_net(c) - D_net(0)`` where ``D_gt`` is valid (the network's depth elsewhere), the network's
    code Jacobian, uncertainty ``b`` everywhere. Same interface as :class:`runtime.network.KeyframeDepth`.
    """

    def __init__(self, kd, gt_net: np.ndarray, b: float) -> None:
        self.kd = kd
        self.net = kd.net
        d0 = np.asarray(kd.depth(np.zeros(kd.net.code_dim)), np.float64)
        gt = np.asarray(gt_net, np.float64)
        if gt.shape != d0.shape:
            raise ValueError(f"ground-truth depth {gt.shape} does not match the network's {d0.shape}")
        self.offset = np.where(gt > 0, gt - d0, 0.0)
        self.uncertainty = np.full(np.shape(kd.uncertainty), b, np.float32)

    def depth(self, code: np.ndarray) -> np.ndarray:
        return np.asarray(self.kd.depth(code), np.float64) + self.offset

    def jacobian(self, code: np.ndarray, delta: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        d, J = self.kd.jacobian(code) if delta is None else self.kd.jacobian(code, delta)
        return np.asarray(d, np.float64) + self.offset, J


class OracleDepthSource:
    """A depth source (:data:`runtime.dense.mapper.DepthSource`) that wraps each keyframe's network prior in a
    :class:`GroundTruthDepth`.

    Args:
        depth_gt: ``frame_idx -> (H, W) metres or None``, ground truth on cam0's (distorted) grid.
        b: Laplace scale ``B`` [m] given to every pixel.
    """

    def __init__(self, depth_gt: Callable[[int], np.ndarray | None], b: float = 0.02) -> None:
        if depth_gt is None:
            raise ValueError("the ground-truth depth source needs a sequence with ground-truth depth (mav0/depth0)")
        if not b > 0:
            raise ValueError(f"b={b}: the ground-truth depth's Laplace scale must be > 0")
        self.depth_gt = depth_gt
        self.b = float(b)

    def __call__(self, kd, frame_idx: int, camera: Camera, mapping: NetworkMapping) -> GroundTruthDepth:
        gt = self.depth_gt(frame_idx)
        if gt is None:
            raise ValueError(f"the ground-truth depth source has no depth for frame {frame_idx}")
        return GroundTruthDepth(kd, gt_depth_to_network(gt, camera, mapping), self.b)


def oracle_depth_source(depth_gt: Callable[[int], np.ndarray | None], b: float = 0.02) -> OracleDepthSource:
    """The ground-truth depth source of a sequence: ``oracle_depth_source(seq.depth)`` (``seq.has_depth``)."""
    return OracleDepthSource(depth_gt, b)
